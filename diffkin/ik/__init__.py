"""Inverse kinematics: closed form (§2.12), CLIK (§3.5–3.7), numerical and optimisation-based solvers.

- :func:`solve` — batched Levenberg–Marquardt with joint limits and restarts, per-sample success flags;
- :func:`optimize` — any differentiable cost over the batch with L-BFGS / Adam / Gauss–Newton;
- :func:`closed_form` — every solution branch of the textbook's structures;
- :func:`clik` — closed-loop IK integrators tracking a time-varying target;
- :func:`joint_trajectory_from_poses` — an operational-space trajectory turned into a joint trajectory.
"""

from .along_path import JointTrajectory as JointTrajectory
from .along_path import finite_difference_twists as finite_difference_twists
from .along_path import joint_trajectory_from_poses as joint_trajectory_from_poses
from .along_path import refine_path as refine_path
from .analytic import CLOSED_FORM_STRUCTURES as CLOSED_FORM_STRUCTURES
from .analytic import ClosedFormSolution as ClosedFormSolution
from .analytic import closed_form as closed_form
from .analytic import identify_structure as identify_structure
from .closed_loop import CLIK_ALGORITHMS as CLIK_ALGORITHMS
from .closed_loop import CLIK_ORIENTATIONS as CLIK_ORIENTATIONS
from .closed_loop import CLIKResult as CLIKResult
from .closed_loop import clik as clik
from .closed_loop import joint_limit_objective as joint_limit_objective
from .numerical import LMConfig as LMConfig
from .numerical import dls_delta as dls_delta
from .numerical import dls_step as dls_step
from .numerical import solve as solve
from .optimization import CallableCost as CallableCost
from .optimization import JointLimitCost as JointLimitCost
from .optimization import ManipulabilityCost as ManipulabilityCost
from .optimization import PoseCost as PoseCost
from .optimization import RestPostureCost as RestPostureCost
from .optimization import optimize as optimize
from .residuals import CostContext as CostContext
from .result import IKResult as IKResult

__all__ = [
    "CLIK_ALGORITHMS",
    "CLIK_ORIENTATIONS",
    "CLOSED_FORM_STRUCTURES",
    "CLIKResult",
    "CallableCost",
    "ClosedFormSolution",
    "CostContext",
    "IKResult",
    "JointLimitCost",
    "JointTrajectory",
    "LMConfig",
    "ManipulabilityCost",
    "PoseCost",
    "RestPostureCost",
    "clik",
    "closed_form",
    "dls_delta",
    "dls_step",
    "finite_difference_twists",
    "identify_structure",
    "joint_limit_objective",
    "joint_trajectory_from_poses",
    "optimize",
    "refine_path",
    "solve",
]

from .differential import solve_velocity as solve_velocity  # noqa: E402
from .limits import CollisionLimit as CollisionLimit  # noqa: E402
from .limits import ConfigurationLimit as ConfigurationLimit  # noqa: E402
from .limits import Limit as Limit  # noqa: E402
from .limits import VelocityLimit as VelocityLimit  # noqa: E402
from .tasks import ComTask as ComTask  # noqa: E402
from .tasks import DampingTask as DampingTask  # noqa: E402
from .tasks import FrameTask as FrameTask  # noqa: E402
from .tasks import PostureTask as PostureTask  # noqa: E402
from .tasks import RelativeFrameTask as RelativeFrameTask  # noqa: E402
from .tasks import Task as Task  # noqa: E402
from .velocity import velocity_step as velocity_step  # noqa: E402

__all__ += ["CollisionLimit", "ComTask", "ConfigurationLimit", "DampingTask", "FrameTask", "Limit",
            "PostureTask", "RelativeFrameTask", "Task", "VelocityLimit", "solve_velocity", "velocity_step"]

from .collision_cost import CollisionCost as CollisionCost  # noqa: E402

__all__ += ["CollisionCost"]
