"""What the safety layer did during a job: clamps counted by kind, refusals and stops with reasons; and a
refusal's record (:class:`Refusal`), which job recordings and replays read without loading the guard."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Refusal:
    """Why a motion is refused: a short ``kind`` to count by (``collision``, ``barrier``, ``joint margin``,
    ...) and the ``message`` naming what would happen."""

    kind: str
    message: str


@dataclass
class SafetyLog:
    """Counts and reasons recorded by the guard; ``as_dict`` is the ``safety`` section of result.json."""

    clamps: Counter[str] = field(default_factory=Counter)
    refusals: list[dict[str, Any]] = field(default_factory=list)
    stops: list[dict[str, Any]] = field(default_factory=list)

    def clamp(self, kind: str) -> None:
        self.clamps[kind] += 1

    def refuse(self, t: float, reason: str) -> None:
        self.refusals.append({"t": round(t, 6), "reason": reason})

    def stop(self, t: float, reason: str) -> None:
        self.stops.append({"t": round(t, 6), "reason": reason})

    def as_dict(self) -> dict[str, Any]:
        return {"clamps": dict(sorted(self.clamps.items())), "refusals": list(self.refusals),
                "stops": list(self.stops)}
