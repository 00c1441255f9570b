"""Motion generation (ch. 4 with obstacles): batched collision-free, limit-respecting timed trajectories.

:func:`plan` (start joints to goal joints or poses through a :class:`~diffkin.collision.World`) returns a
:class:`MotionResult` (``optimize=True`` or an :class:`OptimizeConfig`: the optimisation stage of
:mod:`diffkin.motion.optimize`, whose knots carry an implicit gradient); :func:`joint_reach` is the
per-joint bound on geom travel its continuous collision checks rest on (:mod:`diffkin.motion._edges`).
"""

from ._reach import joint_reach as joint_reach
from .optimize import OptimizeConfig as OptimizeConfig
from .plan import MotionResult as MotionResult
from .plan import plan as plan

__all__ = ["MotionResult", "OptimizeConfig", "joint_reach", "plan"]
