"""What every device backend shares (``Arm``, ``DepthSensor``): a connection opened with ``connect`` and
closed with ``disconnect``, or held by a ``with`` block."""

from __future__ import annotations

from abc import ABC, abstractmethod
from types import TracebackType
from typing import Self


class Device(ABC):
    """A device with a connection. Use as a context manager, or call ``connect`` / ``disconnect``."""

    name: str = "device"

    @abstractmethod
    def connect(self) -> None:
        """Open the connection; raises ``DriverError`` with the reason when it cannot."""

    @abstractmethod
    def disconnect(self) -> None:
        """Close the connection (an arm stops its motion first). Safe to call twice."""

    @property
    @abstractmethod
    def is_connected(self) -> bool: ...

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.disconnect()
