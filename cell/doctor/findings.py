"""A check's outcome."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class Status(StrEnum):
    """``ok``: nothing to do; ``warn``: the cell runs, but worse or riskier; ``fail``: it will not run."""

    OK = "ok"
    WARN = "warn"
    FAIL = "fail"


@dataclass(frozen=True)
class Finding:
    """One check: what was checked (``name``), its ``status``, what was found (``detail``) and, unless
    ok, how to fix it in one line (``fix``)."""

    name: str
    status: Status
    detail: str
    fix: str | None = None

    @classmethod
    def ok(cls, name: str, detail: str) -> Finding:
        return cls(name, Status.OK, detail)

    @classmethod
    def warn(cls, name: str, detail: str, fix: str) -> Finding:
        return cls(name, Status.WARN, detail, fix)

    @classmethod
    def fail(cls, name: str, detail: str, fix: str) -> Finding:
        return cls(name, Status.FAIL, detail, fix)
