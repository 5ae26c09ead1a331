"""Depth sensors: one interface (:mod:`drivers.depth.base`), backends chosen by ``type:`` in the config."""
