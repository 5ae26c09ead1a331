"""Simulation backends' world: object meshes (:mod:`drivers.sim.objects`) and the ray-casting scene
(:mod:`drivers.sim.scene`) that the sim depth sensors render. Units metres, base frame z-up."""

from drivers.sim.objects import ObjectInfo, ObjectMesh, list_objects, load_object, sample_surface
from drivers.sim.scene import HIT_NONE, HIT_OBJECT, HIT_TABLE, RayHits, SimScene

__all__ = [
    "HIT_NONE",
    "HIT_OBJECT",
    "HIT_TABLE",
    "ObjectInfo",
    "ObjectMesh",
    "RayHits",
    "SimScene",
    "list_objects",
    "load_object",
    "sample_surface",
]
