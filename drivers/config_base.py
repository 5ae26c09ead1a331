"""Base of every configuration model: strict (unknown keys are errors) and immutable; and the strict
number types of safety values."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, Strict


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
