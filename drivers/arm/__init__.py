"""Robot arms: one interface (:mod:`drivers.arm.base`), backends chosen by ``type:`` in the config."""
