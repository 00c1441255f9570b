"""diffkin: differentiable, batched robot kinematics in PyTorch (Siciliano et al., ch. 2–4)."""

from . import models as models
from .chain import DHChain as DHChain
from .chain import KinematicChain as KinematicChain
from .errors import DiffkinError as DiffkinError

__version__ = "0.1.0"
