"""The second synthetic crash world: a three-mass vehicle with a folding-wave crush zone.

Structurally different from the first world (:mod:`crashfuse.world.vehicle`,
:mod:`crashfuse.world.simulate`) and from the diagnosis' effect laws: its own force-crush family,
its own forms of the five catalogue effects, its own measurement chain, CAE runs written raw. It
writes the same campaign folders, so the method and the diagnosis can be judged on a world they
were not written against. Equations, parameters and calibration: ``docs/world-second.md`` and the
module docstrings of :mod:`.structure`, :mod:`.effects` and :mod:`.simulate`.

Nothing here imports the first world's physics (``vehicle``, ``simulate``, ``effects``); it shares
only the paper's Table 1 and the CAE Latin hypercube of :mod:`crashfuse.world.presets`.
"""

# Bumped (with the reason in docs/world-second.md) whenever this world's physics or defaults change.
WORLD_VERSION = "multibody-1"
WORLD_NAME = "multibody"
