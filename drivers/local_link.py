"""The connection of a backend that has no link to open (a simulated device, a recording)."""

from __future__ import annotations

from drivers.errors import DriverError


class LocalLink:
    """``connect`` / ``disconnect`` / ``is_connected`` when being connected is only a flag, kept so that a
    caller that forgets ``connect()`` gets the error a real device would give. Listed before the device
    interface among the bases, so that these implement its abstract methods."""

    _connected: bool = False

    def connect(self) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _require_connected(self, action: str, device: str) -> None:
        """Raise ``DriverError`` naming ``action`` and ``device`` unless connected."""
        if not self._connected:
            raise DriverError(f"{action} while disconnected; call connect() first", device=device)
