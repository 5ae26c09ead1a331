"""A UR5e's standard digital I/O for a packing line's handshake, beside whatever drives the arm.

:class:`URDigitalIO` reads the eight standard digital inputs through an RTDE receive client and sets
standard digital outputs through RTDE IO, in a ur-rtde child process of its own
(:mod:`drivers.arm.ur_rtde_process`). It never uploads a control script: the controller serves several
RTDE clients at once, so a job's arm driver (which holds the control script) and this link coexist; the
driver never writes the standard outputs, this link never moves the arm.
"""

from __future__ import annotations

from drivers.arm.config import UR5eArmConfig
from drivers.arm.ur5e import RECEIVE_VARIABLES, REPLY_TIMEOUT_S, bits
from drivers.arm.ur_rtde_process import ClientError, ClientGone, RTDEProcess
from drivers.errors import DriverError


class URDigitalIO:
    """The standard digital inputs and outputs of the UR5e at ``config.host``."""

    def __init__(self, config: UR5eArmConfig) -> None:
        self._config = config
        self._device = f"ur5e digital io at {config.host}"
        self._proc: RTDEProcess | None = None

    def connect(self) -> None:
        """Start the child and connect its receive client; ``DriverError`` when the controller does not
        answer."""
        self.close()
        proc = RTDEProcess()
        proc.start()
        self._proc = proc
        timeout = self._config.connect_timeout_s + REPLY_TIMEOUT_S
        self._call("receive_connect", self._config.host, self._config.rtde_frequency_hz, RECEIVE_VARIABLES,
                   timeout_s=timeout)

    def close(self) -> None:
        if self._proc is not None:
            self._proc.close()
            self._proc = None

    def inputs(self) -> tuple[tuple[bool, ...], float]:
        """The eight standard digital inputs, DI0 first, and when the controller sampled them: its RTDE
        ``timestamp`` [s since the controller started]. A sample read again (no newer package arrived,
        this process or its RTDE child having been descheduled) carries its old time."""
        snapshot = self._call("snapshot", False, timeout_s=REPLY_TIMEOUT_S)
        assert isinstance(snapshot, dict)
        return bits(int(snapshot["digital_inputs"])), float(snapshot["timestamp"])

    def set_outputs(self, outputs: list[tuple[int, bool]]) -> None:
        """Set standard digital outputs ``[(index, level), ...]``; ``DriverError`` when one is refused."""
        refused = self._call("set_outputs", self._config.host, outputs,
                             timeout_s=self._config.connect_timeout_s + REPLY_TIMEOUT_S)
        if refused is not None:
            raise DriverError(f"the controller refused digital output {refused}", device=self._device)

    def _call(self, op: str, *args: object, timeout_s: float) -> object:
        if self._proc is None:
            raise DriverError("not connected (call connect() first)", device=self._device)
        try:
            return self._proc.call(op, *args, timeout_s=timeout_s)
        except (ClientError, ClientGone) as exc:
            self.close()
            raise DriverError(f"{op}: {exc}", device=self._device) from None

    def __enter__(self) -> URDigitalIO:
        self.connect()
        return self

    def __exit__(self, *_: object) -> None:
        self.close()
