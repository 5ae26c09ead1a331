"""Robot kinematic models (DH kinematics, limits, capsules), looked up by name with ``get_robot_model``."""

from __future__ import annotations

from collections.abc import Callable

from drivers.robots.model import Capsule, CapsuleSpec, RobotModel
from drivers.robots.panda import panda_model
from drivers.robots.ur5e import ur5e_model

_MODELS: dict[str, Callable[[], RobotModel]] = {"panda": panda_model, "ur5e": ur5e_model}

ROBOT_MODEL_NAMES: tuple[str, ...] = tuple(_MODELS)


def get_robot_model(name: str) -> RobotModel:
    """The nominal model named ``name`` ("panda" or "ur5e"); raises ``ValueError`` for any other name."""
    try:
        factory = _MODELS[name]
    except KeyError:
        raise ValueError(f"unknown robot model {name!r} (allowed: {', '.join(ROBOT_MODEL_NAMES)})") from None
    return factory()


__all__ = ["ROBOT_MODEL_NAMES", "Capsule", "CapsuleSpec", "RobotModel", "get_robot_model"]
