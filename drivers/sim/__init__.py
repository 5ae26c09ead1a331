"""Simulation backends' world: object meshes (:mod:`drivers.sim.objects`) and the ray-casting scene
(:mod:`drivers.sim.scene`) that the sim depth sensors render. Units metres, base frame z-up.

Nothing is imported here: the cell file's models import :mod:`drivers.sim.board` and
:mod:`drivers.sim.errors`, and every ``cell`` command reads a cell file, while the scene loads Open3D
(about a second), which only a simulated scan needs."""
