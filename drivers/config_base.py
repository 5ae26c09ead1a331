"""Base of every configuration model: strict (unknown keys are errors) and immutable; the strict number
types of safety values; and :class:`Bounds`, the physical range of a length or an angle, whose refusal
says when the value looks like millimetres in a metres field or radians in a degrees field."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import annotated_types
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    ValidationError,
    ValidatorFunctionWrapHandler,
    WrapValidator,
)
from pydantic_core import PydanticCustomError


class StrictModel(BaseModel):
    """A pydantic model that refuses unknown fields and cannot be changed after validation."""

    model_config = ConfigDict(extra="forbid", frozen=True)


Number = Annotated[float, Strict()]
"""A number written as one: an integer or a decimal, never a quoted string ("475") or a boolean. Safety
values use it, so that a value someone quoted is refused instead of read."""
FiniteNumber = Annotated[float, Strict(), Field(allow_inf_nan=False)]
"""A :data:`Number` that is finite: a place or a height, where YAML's ``.inf`` or ``.nan`` means nothing."""
PositiveNumber = Annotated[float, Strict(), Field(gt=0.0)]
NonNegativeNumber = Annotated[float, Strict(), Field(ge=0.0)]
PositiveCount = Annotated[int, Strict(), Field(gt=0)]
"""A positive integer written as one (not ``"3"``, not ``3.0``)."""


UNIT_MISTAKES: dict[str, tuple[str, str, float, float]] = {
    "m": ("millimetres", "mm", 0.001, 1.0),
    "deg": ("radians", "rad", math.degrees(1.0), 0.0),
    "rad": ("degrees", "deg", math.radians(1.0), 0.0),
}
"""For a field in unit m, deg or rad: the unit a person likely wrote instead, its symbol, the factor that
turns a value in it into the field's unit, and the smallest magnitude a value written in it has (a length
in millimetres is a millimetre or more: 0.8 for a 0.5 m bound is metres, too long, not 0.8 mm)."""


@dataclass(frozen=True)
class Bounds(annotated_types.GroupedMetadata):
    """The physical range [``lo``, ``hi``] of a length (``unit`` m) or an angle (deg, rad), for a number in
    ``Annotated``; ``why`` the physical reason for it, in words. A value outside (or NaN) is refused
    saying the value, the unit, the range and why; and, when the value read in the unit a person likely
    wrote instead (:data:`UNIT_MISTAKES`: millimetres for metres, radians for degrees, degrees for radians)
    lies within the range and is a plausible value in that unit, that it looks like that unit and what it
    would be. The range is the field's ``ge`` / ``le`` to pydantic and to the reference
    (``docs/config.md``)."""

    lo: float
    hi: float
    unit: Literal["m", "deg", "rad"]
    why: str

    def __iter__(self) -> Iterator[object]:
        yield annotated_types.Ge(self.lo)
        yield annotated_types.Le(self.hi)
        yield WrapValidator(self._explain)

    def _explain(self, value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        try:
            return handler(value)
        except ValidationError as exc:
            if not all(e["type"] in ("greater_than_equal", "less_than_equal") for e in exc.errors()):
                raise
        raise PydanticCustomError("out_of_range", self.refusal(float(value)))

    def refusal(self, value: float) -> str:
        """Why ``value`` (outside the range) is refused, with the likely unit mistake if there is one."""
        text = f"{value:g} {self.unit} is outside [{self.lo:g}, {self.hi:g}] {self.unit}: {self.why}"
        name, symbol, factor, smallest = UNIT_MISTAKES[self.unit]
        converted = value * factor
        if abs(value) >= smallest and self.lo <= converted <= self.hi:
            text += f"; it looks like {name} ({value:g} {symbol} is {converted:.6g} {self.unit})"
        return text


CELL_EXTENT_M = 2.0
"""How far [m] from the robot's base, along each axis of the base frame, anything a cell file places may
lie (the workspace, barrier planes, the table, obstacles), and the longest size or distance in the cell:
the arms reach less than 0.9 m (UR5e 0.85 m, Panda 0.855 m), and their table and obstacles stand around
them; 850 (millimetres written in a metres field) is refused."""

IN_CELL = Bounds(-CELL_EXTENT_M, CELL_EXTENT_M, "m",
                 f"the cell lies within {CELL_EXTENT_M:g} m of the robot's base")
"""The bounds of a coordinate [m] of a place in the cell (:data:`CELL_EXTENT_M`)."""
CELL_SIZE = Bounds(0.001, CELL_EXTENT_M, "m",
                   f"a size or a distance in the cell is 1 mm to {CELL_EXTENT_M:g} m")
"""The bounds of a size or a distance [m] in the cell (:data:`CELL_EXTENT_M`)."""
ONE_TURN = Bounds(-360.0, 360.0, "deg", "an angle lies within one turn either way")
"""The bounds of an angle [deg] of a rotation or a direction."""

CellCoordinate = Annotated[float, IN_CELL]
"""[m] one coordinate of a place in the cell (:data:`IN_CELL`)."""
CellSize = Annotated[float, CELL_SIZE]
"""[m] a size or a distance in the cell (:data:`CELL_SIZE`)."""
Turn = Annotated[float, ONE_TURN]
"""[deg] an angle of a rotation or a direction (:data:`ONE_TURN`)."""
CellDistance = Annotated[float, Bounds(0.0, CELL_EXTENT_M, "m",
                                       f"a distance in the cell is 0 to {CELL_EXTENT_M:g} m")]
"""[m] a distance in the cell that may be zero: a margin, a clearance, a height above the table
(:data:`CELL_EXTENT_M`)."""
