"""The input rule of diffkin.validation at the boundary of the geometry modules (issue #15): the defects the
fuzz sweep found, one test each (the sweep itself is tests/test_fuzz.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from diffkin import models
from diffkin import rotations as rot
from diffkin import statics as st
from diffkin import transforms as tf
from diffkin.errors import DTypeError, ModelError, NonFiniteError, ShapeError
from diffkin.jacobian import (
    analytical_to_geometric,
    analytical_transform,
    forward_kinematics_and_jacobian,
    geometric_jacobian,
    geometric_to_analytical,
    jacobian_dot_qdot,
    rotate_jacobian,
    shift_jacobian_point,
)
from diffkin.manipulability import force_transmission_ratio, manipulability

F64 = torch.float64
NAN = float("nan")


@pytest.fixture(scope="module")
def ur5():
    return models.load("ur5", dtype=F64)


def test_numpy_and_numbers_keep_their_dtype():
    """A float64 numpy array gives float64 (it used to come back float32); numbers follow the tensors."""
    assert rot.rot_x(np.array([0.1, 0.2])).dtype == F64
    assert rot.rot_x(np.float64(0.1)).dtype == F64
    assert rot.rot_x(np.array([0.1], dtype=np.float32)).dtype == torch.float32
    assert rot.rot_x(0.1).dtype == torch.get_default_dtype()
    torch.testing.assert_close(rot.rot_z(np.array(0.3)), rot.rot_z(torch.tensor(0.3, dtype=F64)))
    R = rot.axis_angle_to_matrix(torch.tensor([0.0, 0.0, 1.0], dtype=F64), 0.5)  # number -> float64
    assert R.dtype == F64
    assert tf.make_transform(np.eye(3), [1.0, 2.0, 3.0]).dtype == F64


def test_mixed_float_dtypes_raise_dtype_error_naming_both():
    J32, R64 = torch.zeros(6, 4), torch.eye(3, dtype=F64)
    for call in (
        lambda: rotate_jacobian(J32, R64),
        lambda: shift_jacobian_point(J32, torch.zeros(3, dtype=F64)),
        lambda: analytical_to_geometric(J32, torch.zeros(3, dtype=F64)),
        lambda: st.joint_torques_from_wrench(J32, torch.zeros(6, dtype=F64)),
        lambda: st.closed_chain_torques(torch.zeros(4, 2), torch.zeros(4, dtype=F64)),
        lambda: tf.make_transform(R64, torch.zeros(3)),
    ):
        with pytest.raises(DTypeError, match="float32.*float64|float64.*float32"):
            call()
    with pytest.raises(DTypeError):
        rot.rot_x(torch.tensor([1, 2]))  # integers are not angles of a float dtype
    with pytest.raises(DTypeError, match="half"):
        rot.skew(torch.zeros(3, dtype=torch.float16))


def test_wrong_trailing_shapes_raise_shape_error():
    with pytest.raises(ShapeError, match=r"\(\.\.\., 3, 3\)"):
        rotate_jacobian(torch.zeros(6, 4, dtype=F64), torch.zeros(3, 4, dtype=F64))  # used to give 8 rows
    with pytest.raises(ShapeError):
        rot.matrix_to_quaternion(torch.zeros(2, 3, 4, dtype=F64))
    with pytest.raises(ShapeError):
        rot.matrix_to_quaternion(torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ShapeError):
        rot.vee(torch.zeros(3, 4, dtype=F64))
    with pytest.raises(ShapeError):
        rot.vee(torch.zeros(3, dtype=F64))
    with pytest.raises(ShapeError, match="batch dims"):  # no torch broadcast error from inside
        rot.quaternion_multiply(torch.zeros(2, 4, dtype=F64), torch.zeros(3, 4, dtype=F64))
    with pytest.raises(ShapeError, match=r"\(4, 4\)") as info:  # a model error and a shape error
        tf.as_rigid_transform(torch.eye(3), "tool", F64)
    assert isinstance(info.value, ModelError)


def test_nan_and_inf_raise_non_finite_error(ur5):
    J, phi = torch.ones(6, 6, dtype=F64), torch.tensor([0.1, NAN, 0.3], dtype=F64)
    q = torch.zeros(6, dtype=F64)
    bad_point = torch.tensor([0.0, float("inf"), 0.0], dtype=F64)
    calls = {
        "point": lambda: geometric_jacobian(ur5, q, point=bad_point),
        "frame": lambda: forward_kinematics_and_jacobian(ur5, q, frame=torch.full((3, 3), NAN, dtype=F64)),
        "qdot": lambda: jacobian_dot_qdot(ur5, q, torch.full((6,), NAN, dtype=F64)),
        "phi": lambda: analytical_transform(phi),
        "J_A": lambda: analytical_to_geometric(J.clone().fill_(NAN), phi.nan_to_num()),
        "J": lambda: geometric_to_analytical(J.clone().fill_(NAN), phi.nan_to_num()),
        "wrench": lambda: st.joint_torques_from_wrench(J, torch.full((6,), NAN, dtype=F64)),
        "R": lambda: st.velocity_transform(torch.full((3, 3), NAN, dtype=F64), torch.zeros(3, dtype=F64)),
        "T": lambda: st.wrench_transform(torch.full((4, 4), NAN, dtype=F64)),
        "v": lambda: st.transform_velocity(torch.eye(4, dtype=F64), None, torch.full((6,), NAN, dtype=F64)),
        "tau": lambda: st.closed_chain_torques(torch.ones(6, 2, dtype=F64), torch.full((6,), NAN, dtype=F64)),
    }
    for name, call in calls.items():
        with pytest.raises(NonFiniteError, match=name):
            call()
    with pytest.raises(NonFiniteError):  # not torch's svd convergence error
        manipulability(J.clone().fill_(NAN))
    with pytest.raises(NonFiniteError) as info:
        tf.as_rigid_transform([[NAN] * 4] * 4, "base", F64)
    assert isinstance(info.value, ModelError)


def test_empty_batches_give_empty_results(ur5):
    q = torch.zeros(0, 6, dtype=F64)
    assert geometric_jacobian(ur5, q, point=torch.zeros(3, dtype=F64)).shape == (0, 6, 6)
    assert rotate_jacobian(torch.zeros(0, 6, 6, dtype=F64), torch.eye(3, dtype=F64)).shape == (0, 6, 6)
    assert rot.matrix_to_quaternion(torch.zeros(0, 3, 3)).shape == (0, 4)
    assert st.transform_wrench(torch.zeros(0, 4, 4), None, torch.zeros(0, 6)).shape == (0, 6)


def test_far_values_stay_finite_in_float32():
    """1e30 in float32: an axis is still an axis; a transmission ratio is computed without inf squares."""
    R = rot.axis_angle_to_matrix(torch.tensor([0.0, 0.0, 1e30]), torch.tensor(0.5))
    torch.testing.assert_close(R, rot.rot_z(torch.tensor(0.5)))
    J = torch.zeros(6, 6)
    J[0, 0] = 1e30
    u = torch.zeros(6)
    u[0] = 1.0
    alpha = force_transmission_ratio(J, u)
    assert bool(torch.isfinite(alpha)) and float(alpha) == pytest.approx(1e-30, rel=1e-5)
