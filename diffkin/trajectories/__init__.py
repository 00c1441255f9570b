"""Trajectory planning (textbook ch. 4): batched and differentiable w.r.t. the boundary conditions.

Joint space point to point (§4.2.1): :func:`cubic`, :func:`quintic`, :func:`trapezoidal`;
through a sequence of points (§4.2.2): :func:`interpolating_polynomial`, :func:`cubic_through_points`,
:func:`cubic_spline`, :func:`linear_parabolic_blends`, :func:`anticipated_segments`; time scaling;
operational space (§4.3): path primitives, :func:`cartesian_trajectory` and orientation laws; time-optimal
timing of a joint path under velocity, acceleration and jerk limits: :func:`time_optimal`.
"""

from ._common import InfeasibleTrajectoryError as InfeasibleTrajectoryError
from ._common import Trajectory as Trajectory
from .operational import OrientationTrajectory as OrientationTrajectory
from .operational import PathSample as PathSample
from .operational import QuaternionTrajectory as QuaternionTrajectory
from .operational import axis_angle_orientation_trajectory as axis_angle_orientation_trajectory
from .operational import cartesian_segment_trajectory as cartesian_segment_trajectory
from .operational import cartesian_trajectory as cartesian_trajectory
from .operational import circle_frame as circle_frame
from .operational import circle_path as circle_path
from .operational import euler_angle_trajectory as euler_angle_trajectory
from .operational import euler_orientation_trajectory as euler_orientation_trajectory
from .operational import quaternion_orientation_trajectory as quaternion_orientation_trajectory
from .operational import segment_path as segment_path
from .point_to_point import cubic as cubic
from .point_to_point import quintic as quintic
from .point_to_point import time_scale as time_scale
from .point_to_point import timing_law as timing_law
from .point_to_point import trapezoidal as trapezoidal
from .through_points import anticipated_segments as anticipated_segments
from .through_points import cubic_spline as cubic_spline
from .through_points import cubic_through_points as cubic_through_points
from .through_points import heuristic_velocities as heuristic_velocities
from .through_points import interpolating_polynomial as interpolating_polynomial
from .through_points import linear_parabolic_blends as linear_parabolic_blends
from .time_optimal import TimedPath as TimedPath
from .time_optimal import time_optimal as time_optimal

__all__ = [
    "Trajectory",
    "InfeasibleTrajectoryError",
    "PathSample",
    "OrientationTrajectory",
    "QuaternionTrajectory",
    "cubic",
    "quintic",
    "trapezoidal",
    "timing_law",
    "time_scale",
    "interpolating_polynomial",
    "cubic_through_points",
    "heuristic_velocities",
    "cubic_spline",
    "linear_parabolic_blends",
    "anticipated_segments",
    "segment_path",
    "circle_path",
    "circle_frame",
    "cartesian_trajectory",
    "cartesian_segment_trajectory",
    "euler_angle_trajectory",
    "euler_orientation_trajectory",
    "axis_angle_orientation_trajectory",
    "quaternion_orientation_trajectory",
    "TimedPath",
    "time_optimal",
]
