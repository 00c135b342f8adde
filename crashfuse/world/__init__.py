"""The synthetic crash world: physics-grounded physical-test and CAE simulators writing campaigns.

Only validation harnesses use this package; the method sees nothing but the campaign files it
writes (nothing else in crashfuse imports ``crashfuse.world``). Formulas, units and parameters:
``docs/world.md`` and the module docstrings of :mod:`~crashfuse.world.vehicle`,
:mod:`~crashfuse.world.effects` and :mod:`~crashfuse.world.simulate`.
"""

# Bumped (with the reason in docs/world.md) whenever the world's physics or defaults change.
WORLD_VERSION = "1"
