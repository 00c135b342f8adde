"""The classes and functions a model or surrogate file may name (:mod:`crashfuse.io.persist`).

A fitted :class:`~crashfuse.method.model.FittedModel` or
:class:`~crashfuse.method.surrogate.CAESurrogate` holds only built-in values, numpy arrays and
instances of these; loading a file that names anything else is refused. A new class among a
fitted model's attributes goes here (saving one that is missing fails with its name), and a
changed attribute layout bumps :data:`crashfuse.method.model.FORMAT`.
"""

from __future__ import annotations

from sklearn.mixture import GaussianMixture
from sklearn.preprocessing import StandardScaler

from crashfuse.gp.kriging import KrigingGP
from crashfuse.gp.replicates import ReplicateMeanGP
from crashfuse.method.mixture import GMMGPBias
from crashfuse.method.chain import MountResonance
from crashfuse.method.config import MethodConfig
from crashfuse.method.hybrid import PhysicsFirst
from crashfuse.method.model import Condition, FittedModel
from crashfuse.method.onset import OnsetCorrectedBias
from crashfuse.method.projection import nominal_time
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.signals.pulse import Pulse

TYPES = (
    FittedModel,  # the model file
    MethodConfig,  # FittedModel.config
    Condition,  # FittedModel.companions: (Condition, Pulse) pairs
    Pulse,
    CAESurrogate,  # the surrogate file; FittedModel.surrogate
    KrigingGP,  # the surrogate's and the bias models' GPs
    GMMGPBias,  # FittedModel.bias_ per branch
    GaussianMixture,  # GMMGPBias.gmm_
    StandardScaler,  # GMMGPBias.scaler_, KrigingGP's input scaling
    OnsetCorrectedBias,  # the state mode's loading branch
    ReplicateMeanGP,  # OnsetCorrectedBias.onset_gp_
    PhysicsFirst,  # FittedModel.physics: the hybrid's effect laws
    nominal_time,  # OnsetCorrectedBias.time: functools.partial(nominal_time, columns)
    MountResonance,  # FittedModel.chain: the tests' measurement chain
)
