"""Tests of diffkin.transforms (§2.7) against scipy.spatial.transform, torch.linalg.inv, the homogeneous
form (2.43), autograd and gradcheck."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from diffkin import rotations as rot
from diffkin import transforms as tf
from diffkin.errors import ConventionError, DiffkinError, DTypeError, NonFiniteError, ShapeError

F64 = torch.float64
DTYPES = [torch.float32, torch.float64]
prop = settings(max_examples=20, deadline=None)
seeds = st.integers(0, 2**31 - 1)
shapes = st.sampled_from([(), (5,), (2, 3, 4)])
dtypes = st.sampled_from(DTYPES)


def tol(dtype):
    return 2e-4 if dtype == torch.float32 else 1e-9


def close(a, b, dtype=F64, scale=1.0):
    a = torch.as_tensor(a, dtype=F64)
    b = torch.as_tensor(b, dtype=F64)
    assert a.shape == b.shape, (a.shape, b.shape)
    err = (a - b).abs().max().item() if a.numel() else 0.0
    assert err <= scale * tol(dtype), f"max error {err:.3g} > {scale * tol(dtype):.3g}"


def random_poses(seed, shape=(), dtype=F64):
    """scipy rotations (flat), translations (flat numpy) and the (*shape, 4, 4) transforms."""
    n = max(math.prod(shape), 1)
    r = Rotation.random(n, random_state=seed)
    p = np.random.default_rng(seed).normal(size=(n, 3))
    T = np.zeros((n, 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = r.as_matrix(), p, 1.0
    return r, p, torch.tensor(T, dtype=dtype).reshape(*shape, 4, 4)


# ------------------------------------------------------------------------------- round trips
@prop
@given(seed=seeds, shape=shapes, dtype=dtypes)
def test_roundtrip_make_split(seed, shape, dtype):
    _, _, T = random_poses(seed, shape, dtype)
    R, p = tf.split_transform(T)
    assert R.shape == (*shape, 3, 3) and p.shape == (*shape, 3)
    T2 = tf.make_transform(R, p)
    assert T2.shape == T.shape and T2.dtype == dtype
    close(T2, T, dtype)
    assert tf.check_transform(T2) is T2


@prop
@given(seed=seeds, shape=shapes, dtype=dtypes)
def test_roundtrip_inverse_compose(seed, shape, dtype):
    _, _, T = random_poses(seed, shape, dtype)
    Ti = tf.transform_inverse(T)
    eye = torch.eye(4, dtype=dtype).expand(*shape, 4, 4)
    close(tf.compose(T, Ti), eye, dtype)
    close(tf.compose(Ti, T), eye, dtype)
    close(tf.transform_inverse(Ti), T, dtype)
    close(Ti, torch.linalg.inv(T.double()), dtype)  # (2.45) vs a general inverse


@prop
@given(seed=seeds, shape=shapes, dtype=dtypes)
def test_roundtrip_points(seed, shape, dtype):
    _, _, T = random_poses(seed, shape, dtype)
    pts = torch.randn(*shape, 3, generator=torch.Generator().manual_seed(seed), dtype=F64).to(dtype)
    out = tf.transform_points(T, pts)
    assert out.shape == pts.shape and out.dtype == dtype
    close(tf.transform_points(tf.transform_inverse(T), out), pts, dtype, scale=5)


# ------------------------------------------------------------------------ independent references
def test_make_transform_broadcasts():
    R = rot.rot_z(torch.linspace(0, 1, 5, dtype=F64))
    p = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    T = tf.make_transform(R, p)
    assert T.shape == (5, 4, 4)
    close(T[:, :3, 3], p.expand(5, 3))
    close(T[:, 3], torch.tensor([0.0, 0, 0, 1]).expand(5, 4))
    T = tf.make_transform(torch.eye(3, dtype=F64), torch.zeros(2, 3, 3, dtype=F64))
    assert T.shape == (2, 3, 4, 4)


@pytest.mark.parametrize("dtype", DTYPES)
def test_transform_points_vs_scipy_and_homogeneous(dtype):
    r, p, T = random_poses(1, (50,), dtype)
    pts = np.random.default_rng(2).normal(size=(50, 3))
    out = tf.transform_points(T, torch.tensor(pts, dtype=dtype))
    close(out, r.apply(pts) + p, dtype)  # (2.38)
    hom = torch.cat((torch.tensor(pts, dtype=dtype), torch.ones(50, 1, dtype=dtype)), -1)
    close(out, torch.einsum("nij,nj->ni", T, hom)[:, :3], dtype)  # (2.43)
    # N points per transform through an explicit broadcast dim
    many = torch.randn(50, 7, 3, dtype=dtype)
    assert tf.transform_points(T[:, None], many).shape == (50, 7, 3)


@pytest.mark.parametrize("dtype", DTYPES)
def test_compose_vs_scipy(dtype):
    r1, p1, T1 = random_poses(3, (30,), dtype)
    r2, p2, T2 = random_poses(4, (30,), dtype)
    r3, p3, T3 = random_poses(5, (30,), dtype)
    T = tf.compose(T1, T2, T3)
    r12, p12 = r1 * r2, p1 + r1.apply(p2)
    r123, p123 = r12 * r3, p12 + r12.apply(p3)
    close(T[:, :3, :3], r123.as_matrix(), dtype)
    close(T[:, :3, 3], p123, dtype)
    assert tf.compose(T1) is T1
    assert tf.compose(T1[:, None], T2[None, :4]).shape == (30, 4, 4, 4)  # batch dims broadcast
    R = tf.compose(T1[:, :3, :3], T2[:, :3, :3])  # rotations compose too (2.15)
    close(R, (r1 * r2).as_matrix(), dtype)


def test_identity_transform():
    T = tf.identity_transform((2, 3), dtype=F64)
    assert T.shape == (2, 3, 4, 4) and T.dtype == F64
    close(T, torch.eye(4).expand(2, 3, 4, 4))


# ---------------------------------------------------------------------------------- pose error
def test_pose_error_zero_and_parts():
    _, _, T = random_poses(6, (20,))
    for o in tf.POSE_ERROR_ORIENTATIONS:
        close(tf.pose_error(T, T, orientation=o), torch.zeros(20, 6))
    _, _, T2 = random_poses(7, (20,))
    e = tf.pose_error(T, T2)
    assert e.shape == (20, 6)
    close(e[:, :3], T[:, :3, 3] - T2[:, :3, 3])  # (3.78)
    close(e[:, 3:], rot.orientation_error_axis_angle(T[:, :3, :3], T2[:, :3, :3]))
    e = tf.pose_error(T, T2, orientation="rotvec")
    close(e[:, 3:], rot.orientation_error_axis_angle(T[:, :3, :3], T2[:, :3, :3], form="rotvec"))
    e = tf.pose_error(T, T2, orientation="quaternion")
    close(e[:, 3:], rot.orientation_error_quaternion(T[:, :3, :3], T2[:, :3, :3]))


def test_pose_error_vs_scipy():
    r_d, p_d, T_d = random_poses(8, (40,))
    r_e, p_e, T_e = random_poses(9, (40,))
    v = (r_d * r_e.inv()).as_rotvec()  # R_d R_e^T (3.84), expressed in the base frame
    th = np.linalg.norm(v, axis=-1, keepdims=True)
    close(tf.pose_error(T_d, T_e), np.concatenate([p_d - p_e, np.sin(th) * v / th], -1))
    close(tf.pose_error(T_d, T_e, "rotvec"), np.concatenate([p_d - p_e, v], -1))
    dq = (r_d * r_e.inv()).as_quat(canonical=True)[:, :3]
    e_q = tf.pose_error(T_d, T_e, "quaternion")[:, 3:].numpy()
    close(np.abs(e_q), np.abs(dq))  # (3.91) equals Delta eps up to the sign of Delta eta


@pytest.mark.parametrize("orientation", ["axis_angle", "rotvec", "quaternion"])
def test_pose_error_jacobian_at_zero_is_base_frame(orientation):
    """Perturbing the current pose by a base-frame twist (dp, dw) changes the error by -(dp, dw)
    (-(dp, dw/2) for the quaternion form): the error lives in the base frame."""
    _, _, T_d = random_poses(10, ())

    def err(x):
        T_e = tf.make_transform(rot.rotvec_to_matrix(x[3:]) @ T_d[:3, :3], T_d[:3, 3] + x[:3])
        return tf.pose_error(T_d, T_e, orientation)

    J = torch.autograd.functional.jacobian(err, torch.zeros(6, dtype=F64))
    expected = -torch.eye(6, dtype=F64)
    if orientation == "quaternion":
        expected[3:, 3:] *= 0.5
    close(J, expected)


@pytest.mark.parametrize("orientation", ["axis_angle", "rotvec", "quaternion"])
def test_grad_finite_pose_error_at_zero_error(orientation):
    _, _, T = random_poses(11, (3,))
    a, b = T.clone().requires_grad_(), T.clone().requires_grad_()
    grads = torch.autograd.grad(tf.pose_error(a, b, orientation).sum(), (a, b))
    assert all(bool(torch.isfinite(g).all()) for g in grads)


# ------------------------------------------------------------------------------------ gradcheck
def _T(seed):
    return random_poses(seed, (2,))[2].requires_grad_()


@pytest.mark.parametrize(
    "name,fn,make",
    [
        ("make_transform", tf.make_transform,
         lambda: (rot.rot_x(torch.tensor([0.2, 1.0], dtype=F64)).requires_grad_(),
                  torch.randn(2, 3, dtype=F64, requires_grad=True))),
        ("transform_inverse", tf.transform_inverse, lambda: (_T(12),)),
        ("compose", tf.compose, lambda: (_T(12), _T(13), _T(14))),
        ("transform_points", tf.transform_points,
         lambda: (_T(12), torch.randn(2, 3, dtype=F64, requires_grad=True))),
        ("pose_error_axis_angle", tf.pose_error, lambda: (_T(12), _T(13))),
        ("pose_error_rotvec", lambda a, b: tf.pose_error(a, b, "rotvec"), lambda: (_T(12), _T(13))),
        ("pose_error_quaternion", lambda a, b: tf.pose_error(a, b, "quaternion"), lambda: (_T(12), _T(13))),
    ],
)
def test_gradcheck(name, fn, make):
    assert torch.autograd.gradcheck(fn, make(), eps=1e-6, atol=1e-6), name


# --------------------------------------------------------------------------------------- errors
def test_check_transform_accepts_rigid_float32_chains():
    _, _, T = random_poses(15, (50,), torch.float32)
    T = tf.compose(*[T[i] for i in range(50)])  # accumulated float32 round-off stays within tolerance
    assert tf.check_transform(T) is T
    assert tf.check_transform(torch.eye(4, dtype=F64)).shape == (4, 4)


def test_check_transform_errors():
    _, _, T = random_poses(16, (4,))
    with pytest.raises(ShapeError, match=r"\(\.\.\., 4, 4\).*got \(4, 3, 4\)"):
        tf.check_transform(T[:, :3])
    bad = T.clone()
    bad[1, 0, 3] = float("nan")
    with pytest.raises(NonFiniteError):
        tf.check_transform(bad, name="T_base_ee")
    scaled = T.clone()
    scaled[2, :3, :3] *= 1.01
    with pytest.raises(DiffkinError, match="orthonormal"):
        tf.check_transform(scaled)
    reflected = T.clone()
    reflected[0, :3, 0] *= -1
    with pytest.raises(DiffkinError, match="det"):
        tf.check_transform(reflected)
    bottom = T.clone()
    bottom[3, 3, 0] = 0.5
    with pytest.raises(DiffkinError, match="bottom row"):
        tf.check_transform(bottom)
    tf.check_transform(scaled, atol=0.1)  # user tolerance
    small = T.clone()
    small[0, :3, :3] += 1e-3  # above the rigidity tolerance (1e-3 on max |RᵀR − I|)
    with pytest.raises(DiffkinError):
        tf.check_transform(small)
    assert issubclass(DiffkinError, ValueError)


def test_errors_bad_input():
    T = torch.eye(4, dtype=F64)
    with pytest.raises(ConventionError, match="axis_angle.*quaternion.*rotvec"):
        tf.pose_error(T, T, orientation="euler")
    with pytest.raises(ShapeError, match=r"\(\.\.\., 4, 4\)"):
        tf.pose_error(T[:3], T)
    with pytest.raises(ShapeError, match=r"\(\.\.\., 3\)"):
        tf.make_transform(torch.eye(3, dtype=F64), torch.zeros(4, dtype=F64))
    with pytest.raises(ShapeError):
        tf.transform_points(T, torch.zeros(2, dtype=F64))
    with pytest.raises(ShapeError):
        tf.compose(T, torch.eye(3, dtype=F64))
    with pytest.raises(DiffkinError):
        tf.compose()
    with pytest.raises(DTypeError):
        tf.compose(T, T.float())
    nan = T.clone()
    nan[0, 3] = float("inf")
    with pytest.raises(NonFiniteError):
        tf.transform_inverse(nan)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_device_preserved():
    _, _, T = random_poses(17, (8,))
    T = T.cuda()
    assert tf.transform_inverse(T).is_cuda
    assert tf.pose_error(T, tf.compose(T, T)).is_cuda
    assert tf.make_transform(T[:, :3, :3], T[:, :3, 3]).is_cuda
