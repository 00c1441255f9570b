"""diffkin: differentiable, batched robot kinematics in PyTorch (Siciliano et al., ch. 2–4).

Submodules follow the textbook's order: :mod:`~diffkin.rotations` → :mod:`~diffkin.transforms` →
:mod:`~diffkin.chain` / :mod:`~diffkin.models` → :mod:`~diffkin.jacobian` → :mod:`~diffkin.ik`,
:mod:`~diffkin.calibration`, :mod:`~diffkin.trajectories`.
"""

from . import calibration as calibration
from . import collision as collision
from . import errors as errors
from . import ik as ik
from . import jacobian as jacobian
from . import manipulability as manipulability
from . import models as models
from . import motion as motion
from . import redundancy as redundancy
from . import retarget as retarget
from . import rotations as rotations
from . import statics as statics
from . import trajectories as trajectories
from . import transforms as transforms
from .chain import DHChain as DHChain
from .chain import KinematicChain as KinematicChain
from .errors import ConventionError as ConventionError
from .errors import DiffkinError as DiffkinError
from .errors import DTypeError as DTypeError
from .errors import ModelError as ModelError
from .errors import NonFiniteError as NonFiniteError
from .errors import ShapeError as ShapeError
from .jacobian import forward_kinematics_and_jacobian as forward_kinematics_and_jacobian
from .jacobian import geometric_jacobian as geometric_jacobian
from .models.urdf import URDFChain as URDFChain

__version__ = "0.1.0"

__all__ = [
    "ConventionError",
    "DHChain",
    "DTypeError",
    "DiffkinError",
    "KinematicChain",
    "ModelError",
    "NonFiniteError",
    "ShapeError",
    "URDFChain",
    "__version__",
    "calibration",
    "collision",
    "errors",
    "forward_kinematics_and_jacobian",
    "geometric_jacobian",
    "ik",
    "jacobian",
    "manipulability",
    "models",
    "motion",
    "redundancy",
    "retarget",
    "rotations",
    "statics",
    "trajectories",
    "transforms",
]
