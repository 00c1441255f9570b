"""Fuzz cases of the geometry modules: rotations, transforms, jacobian helpers, statics, manipulability,
trajectories (see ``tests/fuzzing.py`` for the format)."""

from __future__ import annotations

import functools

import torch

import diffkin.jacobian as jac
import diffkin.manipulability as man
import diffkin.rotations as rot
import diffkin.statics as st
import diffkin.trajectories as tr
import diffkin.transforms as tf
from diffkin import models
from tests.fuzzing import Arg, Case, call_dtype, constant, rotation, transform, uniform, unit_quaternion

#: modules whose every public callable must have a case or an exemption
MODULES: list[str] = [
    "diffkin.rotations",
    "diffkin.transforms",
    "diffkin.jacobian",
    "diffkin.statics",
    "diffkin.manipulability",
    "diffkin.trajectories",
]


@functools.cache
def _chain_of(name: str, dtype: torch.dtype):
    return models.load(name, dtype=dtype)


def _chain(name: str = "ur5"):
    """The model in the dtype of the call being fuzzed (before its mutation)."""
    return _chain_of(name, call_dtype())


def A(make, trailing=None, batched=True, finite=True) -> Arg:
    return Arg(make, trailing, batched, finite)


ANGLE = A(uniform(low=-3.0, high=3.0))
VEC3 = A(uniform(3), (3,))
ROT = A(rotation, (3, 3))
TRANSFORM = A(transform, (4, 4))
QUAT = A(unit_quaternion, (4,))
JAC6 = A(uniform(6, 4), (6, None))  # (..., 6, n), n free
TIMES = A(uniform(7, low=-0.2, high=2.5), batched=False)  # query times (T,), also outside [0, t_f]
POINTS = A(uniform(4, 2), (4, None))  # N = 4 path points of n = 2 joints (N must match the knot times)
KNOTS = A(constant([0.0, 1.0, 2.5, 3.5]), (4,), batched=False)
SIGMA = A(uniform(5, low=0.0, high=1.0))  # a normalised timing sigma(t), (..., T)


def _unary(fn, make: Arg, **fixed) -> Case:
    return Case(fn.__name__, fn, {"x": make}, fixed=fixed)


# ------------------------------------------------------------------------------------------ rotations
ROTATIONS = [
    _unary(rot.rot_x, ANGLE),
    _unary(rot.rot_y, ANGLE),
    _unary(rot.rot_z, ANGLE),
    _unary(rot.skew, VEC3),
    _unary(rot.vee, A(uniform(3, 3), (3, 3))),
    _unary(rot.euler_to_matrix, VEC3),
    Case("euler_to_matrix[RPY]", rot.euler_to_matrix, {"angles": VEC3}, fixed={"convention": "RPY"}),
    _unary(rot.matrix_to_euler, ROT),
    Case("matrix_to_euler[RPY]", rot.matrix_to_euler, {"R": ROT}, fixed={"convention": "RPY"}),
    _unary(rot.euler_rate_matrix, VEC3),
    Case("axis_angle_to_matrix", rot.axis_angle_to_matrix, {"axis": VEC3, "angle": ANGLE}),
    _unary(rot.matrix_to_axis_angle, ROT),
    _unary(rot.rotvec_to_matrix, VEC3),
    _unary(rot.matrix_to_rotvec, ROT),
    _unary(rot.quaternion_to_matrix, QUAT),
    _unary(rot.matrix_to_quaternion, ROT),
    Case("axis_angle_to_quaternion", rot.axis_angle_to_quaternion, {"axis": VEC3, "angle": ANGLE}),
    _unary(rot.quaternion_to_axis_angle, QUAT),
    _unary(rot.rotvec_to_quaternion, VEC3),
    _unary(rot.quaternion_to_rotvec, QUAT),
    Case("quaternion_multiply", rot.quaternion_multiply, {"Q1": QUAT, "Q2": QUAT}),
    _unary(rot.quaternion_conjugate, QUAT),
    Case("quaternion_slerp", rot.quaternion_slerp,
         {"Q0": QUAT, "Q1": QUAT, "s": A(uniform(low=0.0, high=1.0))}),
    Case("orientation_error_euler", rot.orientation_error_euler, {"phi_d": VEC3, "phi_e": VEC3}),
    Case("orientation_error_axis_angle", rot.orientation_error_axis_angle, {"R_d": ROT, "R_e": ROT}),
    Case("orientation_error_axis_angle[rotvec]", rot.orientation_error_axis_angle, {"R_d": ROT, "R_e": ROT},
         fixed={"form": "rotvec"}),
    Case("orientation_error_quaternion", rot.orientation_error_quaternion, {"Q_d": QUAT, "Q_e": QUAT}),
    Case("orientation_error_quaternion[R]", rot.orientation_error_quaternion, {"R_d": ROT, "R_e": ROT}),
]

# ----------------------------------------------------------------------------------------- transforms
TRANSFORMS = [
    Case("make_transform", tf.make_transform, {"R": ROT, "p": VEC3}),
    _unary(tf.split_transform, TRANSFORM),
    _unary(tf.transform_inverse, TRANSFORM),
    Case("compose", tf.compose, {"T1": TRANSFORM, "T2": TRANSFORM, "T3": TRANSFORM}),
    Case("compose[R]", tf.compose, {"R1": ROT, "R2": ROT}),
    Case("transform_points", tf.transform_points, {"T": TRANSFORM, "points": VEC3}),
    Case("pose_error", tf.pose_error, {"T_desired": TRANSFORM, "T_current": TRANSFORM}),
    Case("pose_error[quaternion]", tf.pose_error, {"T_desired": TRANSFORM, "T_current": TRANSFORM},
         fixed={"orientation": "quaternion"}),
    _unary(tf.check_transform, TRANSFORM),
    _unary(tf.as_measured_transform, TRANSFORM),
    # a fixed (4, 4) transform (base, tool) converted to the dtype the caller names
    Case("as_rigid_transform", lambda T: tf.as_rigid_transform(T, "T", call_dtype()),
         {"T": A(transform, (4, 4), batched=False)}, out_batch=None, covers=tf.as_rigid_transform),
]

# ------------------------------------------------------------------------------------------- jacobian
Q6 = A(uniform(6, low=-2.0, high=2.0), (6,))
Q3 = A(uniform(3, low=-2.0, high=2.0), (3,))
JACOBIAN = [
    Case("shift_jacobian_point", jac.shift_jacobian_point, {"J": JAC6, "r": VEC3}),
    Case("rotate_jacobian", jac.rotate_jacobian, {"J": JAC6, "R": ROT}),
    _unary(jac.analytical_transform, VEC3),
    Case("analytical_transform[RPY]", jac.analytical_transform, {"phi": VEC3},
         fixed={"representation": "RPY"}),
    Case("analytical_to_geometric", jac.analytical_to_geometric, {"J_A": JAC6, "phi": VEC3}),
    Case("geometric_to_analytical", jac.geometric_to_analytical, {"J": JAC6, "phi": VEC3}),
    Case("geometric_jacobian", lambda q: jac.geometric_jacobian(_chain(), q), {"q": Q6},
         follows_chain=True, covers=jac.geometric_jacobian),
    Case("geometric_jacobian[point]", lambda q, point: jac.geometric_jacobian(_chain(), q, point=point),
         {"q": Q6, "point": VEC3}, follows_chain=True, covers=jac.geometric_jacobian),
    Case("geometric_jacobian[point base, frame ee]",
         lambda q, point: jac.geometric_jacobian(_chain(), q, frame="ee", point=point, point_frame="base"),
         {"q": Q6, "point": VEC3}, follows_chain=True, covers=jac.geometric_jacobian),
    Case("forward_kinematics_and_jacobian[frame]",
         lambda q, frame: jac.forward_kinematics_and_jacobian(_chain(), q, frame=frame),
         {"q": Q6, "frame": ROT}, follows_chain=True, covers=jac.forward_kinematics_and_jacobian),
    Case("forward_kinematics_and_jacobian[frame T]",
         lambda q, frame: jac.forward_kinematics_and_jacobian(_chain(), q, frame=frame),
         {"q": Q6, "frame": TRANSFORM}, follows_chain=True, covers=jac.forward_kinematics_and_jacobian),
    Case("jacobian_dot_qdot", lambda q, qdot: jac.jacobian_dot_qdot(_chain(), q, qdot),
         {"q": Q6, "qdot": Q6}, follows_chain=True, covers=jac.jacobian_dot_qdot),
    Case("analytical_jacobian", lambda q: jac.analytical_jacobian(_chain(), q, singular="flag"),
         {"q": Q6}, follows_chain=True, covers=jac.analytical_jacobian),
]

# -------------------------------------------------------------------------------------------- statics
WRENCH = A(uniform(6), (6,))
STATICS = [
    Case("joint_torques_from_wrench", st.joint_torques_from_wrench, {"J": JAC6, "wrench": WRENCH}),
    Case("velocity_transform", st.velocity_transform, {"R": ROT, "r": VEC3}),
    Case("velocity_transform[T]", st.velocity_transform, {"T": TRANSFORM}),
    Case("wrench_transform", st.wrench_transform, {"R": ROT, "r": VEC3}),
    Case("wrench_transform[T]", st.wrench_transform, {"T": TRANSFORM}),
    Case("transform_velocity", st.transform_velocity, {"R": ROT, "r": VEC3, "v": WRENCH}),
    Case("transform_velocity[T]", lambda T, v: st.transform_velocity(T, None, v),
         {"T": TRANSFORM, "v": WRENCH}, covers=st.transform_velocity),
    Case("transform_wrench", st.transform_wrench, {"R": ROT, "r": VEC3, "wrench": WRENCH}),
    Case("transform_wrench[T]", lambda T, w: st.transform_wrench(T, None, w), {"T": TRANSFORM, "w": WRENCH},
         covers=st.transform_wrench),
    Case("closed_chain_torques", st.closed_chain_torques,
         {"upsilon": A(uniform(4, 2), (4, None)), "tau": A(uniform(4), (4,))}),
]

# ------------------------------------------------------------------------------------- manipulability
JAC_ANY = A(uniform(6, 4))  # (..., m, n): both free
MANIPULABILITY = [
    _unary(man.smallest_singular_value, JAC_ANY),
    _unary(man.jacobian_determinant, A(uniform(6, 6), (6, 6))),
    _unary(man.condition_number, JAC_ANY),
    _unary(man.inverse_condition_number, JAC_ANY),
    _unary(man.manipulability, JAC_ANY),
    _unary(man.velocity_ellipsoid, JAC_ANY),
    Case("velocity_ellipsoid[position]", man.velocity_ellipsoid, {"J": JAC6}, fixed={"part": "position"}),
    # m <= n: for m > n the semi-axes along N(J^T) are +inf by design (the harness wants finite results)
    _unary(man.force_ellipsoid, A(uniform(4, 6))),
    Case("force_ellipsoid[position]", man.force_ellipsoid, {"J": JAC6}, fixed={"part": "position"}),
    Case("force_transmission_ratio", man.force_transmission_ratio, {"J": JAC6, "u": WRENCH}),
    Case("velocity_transmission_ratio", man.velocity_transmission_ratio, {"J": JAC6, "u": WRENCH}),
    Case("decoupled_singularities", lambda q: man.decoupled_singularities(_chain("anthropomorphic_arm"), q),
         {"q": Q3}, follows_chain=True, covers=man.decoupled_singularities),
    Case("decoupled_singularities[6R]", lambda q: man.decoupled_singularities(_chain("ur5"), q),
         {"q": Q6}, follows_chain=True, covers=man.decoupled_singularities),
]

# --------------------------------------------------------------------------------------- trajectories
J3 = A(uniform(3), (3,))  # (..., n) boundary data of n = 3 joints
T_F = A(uniform(1, low=0.5, high=2.0), (1,))  # one duration per batch element, (..., 1)
T_F0 = A(uniform(low=0.5, high=2.0))  # (...)
TIMING = {"sigma": SIGMA, "sigma_dot": SIGMA, "sigma_ddot": SIGMA}
S_F = A(uniform(low=0.1, high=2.0))
FACTOR = A(uniform(low=0.5, high=2.0), batched=False)
J2 = A(uniform(2), (2,))  # (..., n) end conditions of the n = 2 joints of POINTS
PATH = {"points": POINTS, "times": KNOTS, "t": TIMES}


def _timed(fn):
    """``fn(x_i, x_f, timing)`` with the Trajectory form of the timing, built from three tensors."""

    def call(x_i, x_f, sigma, sigma_dot, sigma_ddot, **kw):
        return fn(x_i, x_f, tr.Trajectory(sigma, sigma_dot, sigma_ddot), **kw)

    return call


def _time_scale(position, velocity, acceleration, factor):
    return tr.time_scale(tr.Trajectory(position, velocity, acceleration), factor)


def _time_scale_fn(q_i, q_f, t_f, t, factor):
    return tr.time_scale(lambda s: tr.cubic(q_i, q_f, t_f, s), factor)(t)


def _cartesian(p_i, p_f, s, s_dot, s_ddot):
    path = functools.partial(tr.segment_path, p_i, p_f)
    return tr.cartesian_trajectory(path, tr.Trajectory(s, s_dot, s_ddot))


def _time_optimal(points, velocity_limit, acceleration_limit, t):
    return tr.time_optimal(points, velocity_limit, acceleration_limit, grid_per_segment=8).sample(t)


TRAJECTORIES = [
    Case("cubic", tr.cubic, {"q_i": J3, "q_f": J3, "t_f": T_F, "t": TIMES, "v_i": J3, "v_f": J3}),
    Case("cubic[t_f number]", tr.cubic, {"q_i": J3, "q_f": J3, "t": TIMES}, keyword=("t",),
         fixed={"t_f": 1.5}),
    Case("quintic", tr.quintic, {"q_i": J3, "q_f": J3, "t_f": T_F, "t": TIMES, "v_i": J3, "v_f": J3,
                                 "a_i": J3, "a_f": J3}),
    Case("trapezoidal", tr.trapezoidal, {"q_i": J3, "q_f": J3, "t_f": T_F, "t": TIMES}),
    Case("trapezoidal[qdd_max]", tr.trapezoidal,
         {"q_i": J3, "q_f": J3, "t_f": T_F, "t": TIMES, "qdd_max": A(uniform(3, low=50.0, high=60.0), (3,))},
         keyword=("qdd_max",)),
    Case("trapezoidal[qdd_c]", tr.trapezoidal,
         {"q_i": J3, "q_f": J3, "t_f": T_F, "t": TIMES, "qdd_c": A(uniform(3, low=50.0, high=60.0), (3,))},
         keyword=("qdd_c",)),
    Case("timing_law", tr.timing_law, {"s_f": S_F, "t_f": T_F0, "t": TIMES}),
    Case("timing_law[quintic]", tr.timing_law, {"s_f": S_F, "t_f": T_F0, "t": TIMES},
         fixed={"kind": "quintic"}),
    Case("timing_law[trapezoidal]", tr.timing_law,
         {"s_f": S_F, "t_f": T_F0, "t": TIMES, "qdd_max": A(uniform(low=50, high=60))},
         keyword=("qdd_max",), fixed={"kind": "trapezoidal"}),
    Case("time_scale", _time_scale, {"position": J3, "velocity": J3, "acceleration": J3, "factor": FACTOR},
         covers=tr.time_scale),
    Case("time_scale[function]", _time_scale_fn,
         {"q_i": J3, "q_f": J3, "t_f": T_F, "t": TIMES, "factor": FACTOR}, covers=tr.time_scale),
    Case("time_optimal", _time_optimal,
         {"points": POINTS, "velocity_limit": A(uniform(2, low=1.0, high=2.0), (2,)),
          "acceleration_limit": A(uniform(2, low=5.0, high=9.0), (2,)), "t": TIMES}, covers=tr.time_optimal),
    Case("interpolating_polynomial", tr.interpolating_polynomial, PATH),
    Case("cubic_through_points", tr.cubic_through_points, PATH),
    Case("cubic_through_points[velocities]", tr.cubic_through_points,
         {"points": POINTS, "times": KNOTS, "t": TIMES, "velocities": POINTS}),
    Case("heuristic_velocities", tr.heuristic_velocities, {"points": POINTS, "times": KNOTS}),
    Case("cubic_spline", tr.cubic_spline, {**PATH, "v_i": J2, "v_f": J2}),
    Case("cubic_spline[natural_virtual]", tr.cubic_spline,
         {**PATH, "v_i": J2, "v_f": J2, "a_i": J2, "a_f": J2}, keyword=("a_i", "a_f"),
         fixed={"end": "natural_virtual"}),
    Case("cubic_spline[virtual_times]", tr.cubic_spline,
         {**PATH, "virtual_times": A(constant([0.3, 3.0]), (2,), batched=False)},
         keyword=("virtual_times",), fixed={"end": "natural_virtual"}),
    Case("linear_parabolic_blends", tr.linear_parabolic_blends,
         {**PATH, "blend_time": A(constant([0.2] * 4), (4,), batched=False)}),
    Case("linear_parabolic_blends[qdd]", tr.linear_parabolic_blends,
         {"points": POINTS, "times": KNOTS, "t": TIMES, "qdd": A(uniform(2, low=10.0, high=20.0), (2,))},
         keyword=("qdd",)),
    Case("anticipated_segments", tr.anticipated_segments,
         {"points": POINTS, "times": KNOTS, "t": TIMES, "advance": A(uniform(3, low=0.0, high=0.1), (3,)),
          "qdd_c": A(uniform(3, low=20.0, high=30.0), (3,))}),
    Case("segment_path", tr.segment_path, {"p_i": VEC3, "p_f": VEC3, "s": A(uniform(5), batched=False)}),
    Case("circle_path", tr.circle_path,
         {"center": VEC3, "axis": VEC3, "point_on_circle": VEC3, "s": A(uniform(5), batched=False)}),
    Case("circle_frame", tr.circle_frame, {"axis_point": VEC3, "axis": VEC3, "p_i": VEC3}),
    Case("cartesian_trajectory", _cartesian, {"p_i": VEC3, "p_f": VEC3, "s": SIGMA, "s_dot": SIGMA,
                                              "s_ddot": SIGMA}, covers=tr.cartesian_trajectory),
    Case("cartesian_segment_trajectory", tr.cartesian_segment_trajectory,
         {"p_i": VEC3, "p_f": VEC3, "t_f": T_F0, "t": TIMES}),
    Case("euler_angle_trajectory", _timed(tr.euler_angle_trajectory),
         {"phi_i": VEC3, "phi_f": VEC3, **TIMING}, covers=tr.euler_angle_trajectory),
    Case("euler_orientation_trajectory", _timed(tr.euler_orientation_trajectory),
         {"phi_i": VEC3, "phi_f": VEC3, **TIMING}, covers=tr.euler_orientation_trajectory),
    Case("axis_angle_orientation_trajectory", _timed(tr.axis_angle_orientation_trajectory),
         {"R_i": ROT, "R_f": ROT, **TIMING}, covers=tr.axis_angle_orientation_trajectory),
    Case("quaternion_orientation_trajectory", _timed(tr.quaternion_orientation_trajectory),
         {"Q_i": QUAT, "Q_f": QUAT, **TIMING}, covers=tr.quaternion_orientation_trajectory),
]

CASES: list[Case] = ROTATIONS + TRANSFORMS + JACOBIAN + STATICS + MANIPULABILITY + TRAJECTORIES

_RESULT = "a result container (NamedTuple) without input of its own"
#: public callables without a case, with the reason
EXEMPT: dict[str, str] = {
    "diffkin.transforms.identity_transform": "takes no tensor input (a batch shape, a dtype and a device)",
    "diffkin.jacobian.AnalyticalJacobian": _RESULT,
    "diffkin.manipulability.DecoupledSingularities": _RESULT,
    "diffkin.manipulability.Ellipsoid": _RESULT,
    "diffkin.trajectories.Trajectory": _RESULT,
    "diffkin.trajectories.PathSample": _RESULT,
    "diffkin.trajectories.OrientationTrajectory": _RESULT,
    "diffkin.trajectories.QuaternionTrajectory": _RESULT,
    "diffkin.trajectories.TimedPath": "the result of time_optimal (fuzzed through its sample method there)",
}
