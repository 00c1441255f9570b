"""Tests of diffkin.rotations against scipy.spatial.transform, finite differences, gradcheck and the
textbook's closed forms (§2.2–2.6, (3.64), §3.7.3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from diffkin import rotations as rot
from diffkin.errors import ConventionError, DiffkinError, DTypeError, NonFiniteError, ShapeError

F64 = torch.float64
SHAPES = [(), (5,), (2, 3, 4)]
DTYPES = [torch.float32, torch.float64]
SCIPY_EULER = {"ZYZ": "ZYZ", "RPY": "ZYX"}  # intrinsic (uppercase) sequences

seeds = st.integers(0, 2**31 - 1)
shapes = st.sampled_from(SHAPES)
dtypes = st.sampled_from(DTYPES)
prop = settings(max_examples=20, deadline=None)


def tol(dtype):
    return 2e-4 if dtype == torch.float32 else 1e-9


def random_rotations(seed, shape=(), dtype=F64):
    """scipy Rotation (flat) and its matrices as a (*shape, 3, 3) tensor."""
    n = math.prod(shape)
    r = Rotation.random(max(n, 1), random_state=seed)
    R = torch.tensor(r.as_matrix(), dtype=dtype).reshape(*shape, 3, 3)
    return r, R


def scipy_quat(r):
    """scipy (x, y, z, w) -> scalar-first (w, x, y, z) with w >= 0."""
    q = r.as_quat(canonical=True)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def wrap(a):
    return torch.atan2(torch.sin(a), torch.cos(a))


def close(a, b, dtype=F64, scale=1.0):
    a = torch.as_tensor(a, dtype=F64)
    b = torch.as_tensor(b, dtype=F64)
    assert a.shape == b.shape, (a.shape, b.shape)
    err = (a - b).abs().max().item() if a.numel() else 0.0
    assert err <= scale * tol(dtype), f"max error {err:.3g} > {scale * tol(dtype):.3g}"


def gen(seed):
    return torch.Generator().manual_seed(seed)


# ---------------------------------------------------------------------------- round trips (hypothesis)
@prop
@given(seed=seeds, shape=shapes, dtype=dtypes)
def test_roundtrip_quaternion(seed, shape, dtype):
    _, R = random_rotations(seed, shape, dtype)
    Q = rot.matrix_to_quaternion(R)
    assert Q.shape == (*shape, 4) and Q.dtype == dtype
    assert bool((Q[..., 0] >= 0).all())
    close(rot.quaternion_to_matrix(Q), R, dtype)
    close(rot.matrix_to_quaternion(rot.quaternion_to_matrix(Q)), Q, dtype)


@prop
@given(seed=seeds, shape=shapes, dtype=dtypes)
def test_roundtrip_rotvec(seed, shape, dtype):
    _, R = random_rotations(seed, shape, dtype)
    v = rot.matrix_to_rotvec(R)
    assert v.shape == (*shape, 3) and v.dtype == dtype
    close(rot.rotvec_to_matrix(v), R, dtype)
    v = 0.9 * v  # keep away from the pi boundary where the sign flips
    close(rot.matrix_to_rotvec(rot.rotvec_to_matrix(v)), v, dtype, scale=2)
    close(rot.quaternion_to_rotvec(rot.rotvec_to_quaternion(v)), v, dtype, scale=2)


@prop
@given(seed=seeds, shape=shapes, dtype=dtypes)
def test_roundtrip_axis_angle(seed, shape, dtype):
    _, R = random_rotations(seed, shape, dtype)
    axis, angle = rot.matrix_to_axis_angle(R)
    assert axis.shape == (*shape, 3) and angle.shape == shape and angle.dtype == dtype
    assert bool(((angle >= 0) & (angle <= math.pi)).all())
    close(rot.axis_angle_to_matrix(axis, angle), R, dtype)
    angle = angle.clamp(0.05, math.pi - 0.05)
    axis2, angle2 = rot.matrix_to_axis_angle(rot.axis_angle_to_matrix(axis, angle))
    close(axis2, axis, dtype, scale=5)
    close(angle2, angle, dtype, scale=5)
    axis3, angle3 = rot.quaternion_to_axis_angle(rot.axis_angle_to_quaternion(axis, angle))
    close(axis3, axis, dtype, scale=5)
    close(angle3, angle, dtype, scale=5)


@pytest.mark.parametrize("convention", ["ZYZ", "RPY"])
@pytest.mark.parametrize("branch", ["positive", "negative"])
@prop
@given(seed=seeds, shape=shapes, dtype=dtypes)
def test_roundtrip_euler_matrix(convention, branch, seed, shape, dtype):
    _, R = random_rotations(seed, shape, dtype)
    ang = rot.matrix_to_euler(R, convention, branch)
    assert ang.shape == (*shape, 3) and ang.dtype == dtype
    close(rot.euler_to_matrix(ang, convention), R, dtype)


@pytest.mark.parametrize("convention", ["ZYZ", "RPY"])
@prop
@given(seed=seeds, shape=shapes, dtype=dtypes)
def test_roundtrip_euler_angles(convention, seed, shape, dtype):
    u = torch.rand(*shape, 3, generator=gen(seed), dtype=F64)
    phi, psi = (2 * u[..., 0] - 1) * math.pi, (2 * u[..., 2] - 1) * math.pi
    if convention == "ZYZ":  # theta in (0, pi), margin from the singularity
        theta = 0.05 + u[..., 1] * (math.pi - 0.1)
    else:  # theta in (-pi/2, pi/2)
        theta = (2 * u[..., 1] - 1) * (math.pi / 2 - 0.05)
    ang = torch.stack((phi, theta, psi), -1).to(dtype)
    back = rot.matrix_to_euler(rot.euler_to_matrix(ang, convention), convention)
    close(wrap(back - ang), torch.zeros_like(ang), dtype, scale=10)


@prop
@given(seed=seeds, shape=shapes, dtype=dtypes)
def test_roundtrip_skew_vee(seed, shape, dtype):
    v = torch.randn(*shape, 3, generator=gen(seed), dtype=F64).to(dtype)
    S = rot.skew(v)
    close(S, -S.transpose(-1, -2), dtype)
    close(rot.vee(S), v, dtype)
    w = torch.randn(*shape, 3, generator=gen(seed + 1), dtype=F64).to(dtype)
    close(torch.einsum("...ij,...j->...i", S, w), torch.linalg.cross(v, w, dim=-1), dtype, scale=10)


# ---------------------------------------------------------------------------------- scipy agreement
N = 200


@pytest.mark.parametrize("dtype", DTYPES)
def test_elementary_rotations_vs_scipy(dtype):
    a = torch.linspace(-4, 4, 17, dtype=dtype)
    for fn, ax in ((rot.rot_x, "x"), (rot.rot_y, "y"), (rot.rot_z, "z")):
        close(fn(a), Rotation.from_euler(ax, a.double().numpy()[:, None]).as_matrix(), dtype)
    close(rot.rot_z(math.pi / 2), Rotation.from_euler("z", math.pi / 2).as_matrix(), torch.float32)


@pytest.mark.parametrize("convention", ["ZYZ", "RPY"])
@pytest.mark.parametrize("dtype", DTYPES)
def test_euler_vs_scipy(convention, dtype):
    r, R = random_rotations(1, (N,), dtype)
    ang_sp = r.as_euler(SCIPY_EULER[convention])
    close(rot.euler_to_matrix(torch.tensor(ang_sp, dtype=dtype), convention), R, dtype)
    ang = rot.matrix_to_euler(R, convention)
    close(wrap(ang.double() - torch.tensor(ang_sp)), torch.zeros(N, 3), dtype, scale=10)


@pytest.mark.parametrize("convention", ["ZYZ", "RPY"])
def test_euler_negative_branch_book_relation(convention):
    # (2.20) vs (2.19): (phi + pi, -theta, psi + pi); (2.23) vs (2.22): (phi + pi, pi - theta, psi + pi)
    r, R = random_rotations(2, (N,))
    pos, neg = rot.matrix_to_euler(R, convention), rot.matrix_to_euler(R, convention, branch="negative")
    other_theta = -pos[:, 1] if convention == "ZYZ" else math.pi - pos[:, 1]
    expected = torch.stack((pos[:, 0] + math.pi, other_theta, pos[:, 2] + math.pi), -1)
    close(wrap(neg - expected), torch.zeros(N, 3))
    if convention == "ZYZ":
        assert bool(((neg[:, 1] < 0) & (neg[:, 1] > -math.pi)).all())
    else:
        assert bool((torch.cos(neg[:, 1]) < 0).all())


def test_euler_rpy_is_fixed_axes_product():
    u = torch.randn(N, 3, generator=gen(3), dtype=F64)
    R = rot.rot_z(u[:, 0]) @ rot.rot_y(u[:, 1]) @ rot.rot_x(u[:, 2])  # (2.21)
    close(rot.euler_to_matrix(u, "RPY"), R)
    close(rot.euler_to_matrix(u, "zyx"), R)
    R = rot.rot_z(u[:, 0]) @ rot.rot_y(u[:, 1]) @ rot.rot_z(u[:, 2])  # (2.18)
    close(rot.euler_to_matrix(u, "ZYZ"), R)


@pytest.mark.parametrize("dtype", DTYPES)
def test_axis_angle_and_rotvec_vs_scipy(dtype):
    r, R = random_rotations(4, (N,), dtype)
    v_sp = r.as_rotvec()
    close(rot.matrix_to_rotvec(R), v_sp, dtype)
    close(rot.rotvec_to_matrix(torch.tensor(v_sp, dtype=dtype)), R, dtype)
    axis, angle = rot.matrix_to_axis_angle(R)
    close(angle, np.linalg.norm(v_sp, axis=-1), dtype)
    close(axis, v_sp / np.linalg.norm(v_sp, axis=-1, keepdims=True), dtype, scale=5)
    ang_t = torch.tensor(np.linalg.norm(v_sp, axis=-1), dtype=dtype)
    close(rot.axis_angle_to_matrix(3.0 * axis, ang_t), R, dtype)  # axis is normalised


@pytest.mark.parametrize("dtype", DTYPES)
def test_quaternion_vs_scipy(dtype):
    r, R = random_rotations(5, (N,), dtype)
    q_sp = scipy_quat(r)
    close(rot.matrix_to_quaternion(R), q_sp, dtype)
    close(rot.quaternion_to_matrix(torch.tensor(q_sp, dtype=dtype)), R, dtype)
    close(rot.quaternion_to_matrix(torch.tensor(-2.0 * q_sp, dtype=dtype)), R, dtype)  # normalised, sign-free
    close(rot.rotvec_to_quaternion(torch.tensor(r.as_rotvec(), dtype=dtype)), q_sp, dtype)
    close(rot.quaternion_to_rotvec(torch.tensor(-q_sp, dtype=dtype)), r.as_rotvec(), dtype)


def test_matrix_to_quaternion_book_formula():
    """Shepperd's evaluation equals (2.34)-(2.35) where the book's formula is well conditioned."""
    _, R = random_rotations(6, (N,))
    r = R.numpy()
    tr = np.trace(r, axis1=-2, axis2=-1)
    eta = 0.5 * np.sqrt(tr + 1)
    sgn = lambda x: np.where(x >= 0, 1.0, -1.0)  # noqa: E731
    d = np.diagonal(r, axis1=-2, axis2=-1)
    eps = 0.5 * np.stack([
        sgn(r[:, 2, 1] - r[:, 1, 2]) * np.sqrt(np.clip(d[:, 0] - d[:, 1] - d[:, 2] + 1, 0, None)),
        sgn(r[:, 0, 2] - r[:, 2, 0]) * np.sqrt(np.clip(d[:, 1] - d[:, 2] - d[:, 0] + 1, 0, None)),
        sgn(r[:, 1, 0] - r[:, 0, 1]) * np.sqrt(np.clip(d[:, 2] - d[:, 0] - d[:, 1] + 1, 0, None)),
    ], -1)
    close(rot.matrix_to_quaternion(R), np.concatenate([eta[:, None], eps], -1), scale=1e3)


@pytest.mark.parametrize("dtype", DTYPES)
def test_quaternion_product_and_conjugate_vs_scipy(dtype):
    r1, R1 = random_rotations(7, (N,), dtype)
    r2, R2 = random_rotations(8, (N,), dtype)
    Q1, Q2 = rot.matrix_to_quaternion(R1), rot.matrix_to_quaternion(R2)
    Q12 = rot.quaternion_multiply(Q1, Q2)
    sign = torch.where(Q12[..., :1] < 0, -1.0, 1.0).to(dtype)
    close(Q12 * sign, scipy_quat(r1 * r2), dtype)
    close(rot.quaternion_to_matrix(Q12), R1 @ R2, dtype)  # (2.37) is the quaternion of R1 R2
    close(rot.quaternion_conjugate(Q1), scipy_quat(r1.inv()) * np.array([1, 1, 1, 1]), dtype)
    ident = rot.quaternion_multiply(Q1, rot.quaternion_conjugate(Q1))
    close(ident, torch.tensor([1.0, 0, 0, 0]).expand(N, 4), dtype)
    # broadcasting batch dims
    assert rot.quaternion_multiply(Q1[:4, None], Q2[None, :3]).shape == (4, 3, 4)


@pytest.mark.parametrize("dtype", DTYPES)
def test_slerp_vs_scipy(dtype):
    r0, R0 = random_rotations(9, (20,), dtype)
    r1, R1 = random_rotations(10, (20,), dtype)
    s = torch.linspace(0, 1, 7, dtype=dtype)
    Q0, Q1 = rot.matrix_to_quaternion(R0), rot.matrix_to_quaternion(R1)
    Qs = rot.quaternion_slerp(Q0[:, None], Q1[:, None], s)  # (20, 7, 4)
    assert Qs.shape == (20, 7, 4) and Qs.dtype == dtype
    for i in range(20):
        ref = Slerp([0.0, 1.0], Rotation.concatenate([r0[i], r1[i]]))(s.double().numpy()).as_matrix()
        close(rot.quaternion_to_matrix(Qs[i]), ref, dtype, scale=5)
    close(Qs[:, 0], Q0, dtype)
    close(torch.linalg.norm(Qs, dim=-1), torch.ones(20, 7), dtype)


def test_slerp_shortest_path_and_identical_ends():
    _, R = random_rotations(11, (10,))
    Q = rot.matrix_to_quaternion(R)
    s = torch.rand(10, generator=gen(0), dtype=F64)
    for Q1 in (Q, -Q):  # same rotation: stays put, no NaN
        close(rot.quaternion_to_matrix(rot.quaternion_slerp(Q, Q1, s)), R)
    # shortest path: slerp(Q0, -Q1) gives the same rotations as slerp(Q0, Q1)
    Qb = rot.matrix_to_quaternion(random_rotations(12, (10,))[1])
    a = rot.quaternion_to_matrix(rot.quaternion_slerp(Q, Qb, s))
    close(a, rot.quaternion_to_matrix(rot.quaternion_slerp(Q, -Qb, s)))


# ------------------------------------------------------------------------- Euler rates (3.64)
@pytest.mark.parametrize("convention", ["ZYZ", "RPY"])
def test_euler_rate_matrix_vs_finite_differences(convention):
    g = gen(13)
    phi = torch.randn(50, 3, generator=g, dtype=F64)
    phi_dot = torch.randn(50, 3, generator=g, dtype=F64)
    h = 1e-6
    Rp = rot.euler_to_matrix(phi + h * phi_dot, convention)
    Rm = rot.euler_to_matrix(phi - h * phi_dot, convention)
    R = rot.euler_to_matrix(phi, convention)
    omega_fd = rot.vee((Rp - Rm) / (2 * h) @ R.transpose(-1, -2))  # S(omega) = Rdot R^T (3.6)
    omega = torch.einsum("...ij,...j->...i", rot.euler_rate_matrix(phi, convention), phi_dot)
    assert (omega - omega_fd).abs().max() < 1e-8


def test_euler_rate_matrix_book_zyz_and_determinants():
    phi = torch.randn(20, 3, generator=gen(14), dtype=F64)
    cp, sp = torch.cos(phi[:, 0]), torch.sin(phi[:, 0])
    ct, st = torch.cos(phi[:, 1]), torch.sin(phi[:, 1])
    z, o = torch.zeros(20, dtype=F64), torch.ones(20, dtype=F64)
    book = torch.stack([torch.stack(r, -1) for r in ([z, -sp, cp * st], [z, cp, sp * st], [o, z, ct])], -2)
    close(rot.euler_rate_matrix(phi, "ZYZ"), book)
    close(torch.linalg.det(rot.euler_rate_matrix(phi, "ZYZ")), -st)  # det T = -s_theta
    close(torch.linalg.det(rot.euler_rate_matrix(phi, "RPY")), -ct)


# --------------------------------------------------------------------------- orientation errors
def test_orientation_errors_zero_when_equal():
    _, R = random_rotations(15, (30,))
    Q = rot.matrix_to_quaternion(R)
    zero = torch.zeros(30, 3, dtype=F64)
    close(rot.orientation_error_axis_angle(R, R), zero)
    close(rot.orientation_error_axis_angle(R, R, form="rotvec"), zero)
    close(rot.orientation_error_quaternion(Q, Q), zero)
    close(rot.orientation_error_quaternion(R, R), zero)
    ang = rot.matrix_to_euler(R)
    close(rot.orientation_error_euler(ang, ang), zero)


def test_orientation_error_axis_angle_vs_scipy_and_book():
    r_d, R_d = random_rotations(16, (N,))
    r_e, R_e = random_rotations(17, (N,))
    v = (r_d * r_e.inv()).as_rotvec()  # R_d R_e^T (3.84)
    th = np.linalg.norm(v, axis=-1, keepdims=True)
    close(rot.orientation_error_axis_angle(R_d, R_e), np.sin(th) * v / th)  # (3.83)
    close(rot.orientation_error_axis_angle(R_d, R_e, form="rotvec"), v)
    # (3.85): 1/2 (n_e x n_d + s_e x s_d + a_e x a_d)
    book = 0.5 * sum(np.cross(R_e.numpy()[..., :, k], R_d.numpy()[..., :, k]) for k in range(3))
    close(rot.orientation_error_axis_angle(R_d, R_e), book)


def test_orientation_error_quaternion_vs_scipy():
    r_d, R_d = random_rotations(18, (N,))
    r_e, R_e = random_rotations(19, (N,))
    Q_d, Q_e = torch.tensor(scipy_quat(r_d)), torch.tensor(scipy_quat(r_e))
    dq = scipy_quat(r_d * r_e.inv())  # Delta Q = Q_d * Q_e^-1 (3.90), canonical Delta eta >= 0
    close(rot.orientation_error_quaternion(Q_d, Q_e, shortest=True), dq[:, 1:])
    # plain (3.91): Delta eps of the product itself, its sign follows Delta eta = eta_d eta_e + eps_d.eps_e
    d_eta = (Q_d * Q_e).sum(-1, keepdim=True).numpy()
    close(rot.orientation_error_quaternion(Q_d, Q_e), np.sign(d_eta) * dq[:, 1:])
    close(rot.orientation_error_quaternion(R_d, R_e), rot.orientation_error_quaternion(Q_d, Q_e))


def test_orientation_errors_small_angle_agreement():
    _, R_e = random_rotations(20, (N,))
    delta = 1e-4 * torch.randn(N, 3, generator=gen(21), dtype=F64)
    R_d = rot.rotvec_to_matrix(delta) @ R_e  # R_d R_e^T = exp(S(delta)): error = delta in the base frame
    e_sin = rot.orientation_error_axis_angle(R_d, R_e)
    e_vec = rot.orientation_error_axis_angle(R_d, R_e, form="rotvec")
    e_q = rot.orientation_error_quaternion(R_d, R_e)
    close(e_vec, delta, scale=10)
    assert (e_sin - delta).abs().max() < 1e-10  # third order
    assert (2 * e_q - delta).abs().max() < 1e-11  # Delta eps = sin(theta/2) r
    phi_e = rot.matrix_to_euler(R_e)
    e_eul = rot.orientation_error_euler(rot.matrix_to_euler(R_d), phi_e)
    # Euler error maps to the angular error through T(phi) (3.64)
    omega = torch.einsum("...ij,...j->...i", rot.euler_rate_matrix(phi_e), e_eul)
    assert (omega - delta).abs().max() < 1e-6


def test_orientation_error_euler_wrap():
    a = torch.tensor([3.0, 0.5, -3.0], dtype=F64)
    b = torch.tensor([-3.0, 0.25, 3.0], dtype=F64)
    close(rot.orientation_error_euler(a, b), a - b)  # (3.80) as printed
    wrapped = torch.tensor([6.0 - 2 * math.pi, 0.25, 2 * math.pi - 6], dtype=F64)
    close(rot.orientation_error_euler(a, b, wrap=True), wrapped)


# ----------------------------------------------------------------------------------- gradcheck
def _rand_R(seed=22, n=3):
    return random_rotations(seed, (n,))[1].requires_grad_()


def _rand(shape, seed=23):
    return torch.randn(*shape, generator=gen(seed), dtype=F64).requires_grad_()


GRADCHECK = {
    "rot_x": (rot.rot_x, lambda: (_rand((3,)),)),
    "rot_y": (rot.rot_y, lambda: (_rand((3,)),)),
    "rot_z": (rot.rot_z, lambda: (_rand((3,)),)),
    "skew": (rot.skew, lambda: (_rand((3, 3)),)),
    "vee": (rot.vee, lambda: (_rand((3, 3, 3)),)),
    "euler_to_matrix_zyz": (lambda a: rot.euler_to_matrix(a, "ZYZ"), lambda: (_rand((3, 3)),)),
    "euler_to_matrix_rpy": (lambda a: rot.euler_to_matrix(a, "RPY"), lambda: (_rand((3, 3)),)),
    "matrix_to_euler_zyz": (lambda R: rot.matrix_to_euler(R, "ZYZ"), lambda: (_rand_R(),)),
    "matrix_to_euler_zyz_neg": (lambda R: rot.matrix_to_euler(R, "ZYZ", "negative"), lambda: (_rand_R(),)),
    "matrix_to_euler_rpy": (lambda R: rot.matrix_to_euler(R, "RPY"), lambda: (_rand_R(),)),
    "matrix_to_euler_rpy_neg": (lambda R: rot.matrix_to_euler(R, "RPY", "negative"), lambda: (_rand_R(),)),
    "euler_rate_matrix_zyz": (lambda a: rot.euler_rate_matrix(a, "ZYZ"), lambda: (_rand((3, 3)),)),
    "euler_rate_matrix_rpy": (lambda a: rot.euler_rate_matrix(a, "RPY"), lambda: (_rand((3, 3)),)),
    "axis_angle_to_matrix": (rot.axis_angle_to_matrix, lambda: (_rand((3, 3)), _rand((3,), 24))),
    "matrix_to_axis_angle": (rot.matrix_to_axis_angle, lambda: (_rand_R(),)),
    "rotvec_to_matrix": (rot.rotvec_to_matrix, lambda: (_rand((3, 3)),)),
    "matrix_to_rotvec": (rot.matrix_to_rotvec, lambda: (_rand_R(),)),
    "quaternion_to_matrix": (rot.quaternion_to_matrix, lambda: (_rand((3, 4)),)),
    "matrix_to_quaternion": (rot.matrix_to_quaternion, lambda: (_rand_R(),)),
    "axis_angle_to_quaternion": (rot.axis_angle_to_quaternion, lambda: (_rand((3, 3)), _rand((3,), 24))),
    "quaternion_to_axis_angle": (rot.quaternion_to_axis_angle, lambda: (_rand((3, 4)),)),
    "rotvec_to_quaternion": (rot.rotvec_to_quaternion, lambda: (_rand((3, 3)),)),
    "quaternion_to_rotvec": (rot.quaternion_to_rotvec, lambda: (_rand((3, 4)),)),
    "quaternion_multiply": (rot.quaternion_multiply, lambda: (_rand((3, 4)), _rand((3, 4), 24))),
    "quaternion_conjugate": (rot.quaternion_conjugate, lambda: (_rand((3, 4)),)),
    "quaternion_slerp": (
        rot.quaternion_slerp,
        lambda: (rot.matrix_to_quaternion(_rand_R(25)).detach().requires_grad_(),
                 rot.matrix_to_quaternion(_rand_R(26)).detach().requires_grad_(),
                 torch.rand(3, generator=gen(27), dtype=F64).requires_grad_()),
    ),
    "orientation_error_euler": (rot.orientation_error_euler, lambda: (_rand((3, 3)), _rand((3, 3), 24))),
    "orientation_error_axis_angle": (rot.orientation_error_axis_angle, lambda: (_rand_R(28), _rand_R(29))),
    "orientation_error_rotvec": (
        lambda a, b: rot.orientation_error_axis_angle(a, b, form="rotvec"),
        lambda: (_rand_R(28), _rand_R(29)),
    ),
    "orientation_error_quaternion": (
        rot.orientation_error_quaternion,
        lambda: (_rand((3, 4)), _rand((3, 4), 24)),
    ),
    "orientation_error_quaternion_R": (rot.orientation_error_quaternion, lambda: (_rand_R(28), _rand_R(29))),
}


@pytest.mark.parametrize("name", sorted(GRADCHECK))
def test_gradcheck(name):
    fn, make = GRADCHECK[name]
    assert torch.autograd.gradcheck(fn, make(), eps=1e-6, atol=1e-6)


# --------------------------------------------------------- singular cases: named regression tests
def _grad(fn, x):
    x = x.detach().clone().requires_grad_()
    out = fn(x)
    out = out if isinstance(out, tuple) else (out,)
    (g,) = torch.autograd.grad(sum(o.sum() for o in out), x)
    return out, g


def _assert_finite(*ts):
    for t in ts:
        assert bool(torch.isfinite(t).all()), t


PI_AXES = torch.nn.functional.normalize(
    torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 2, -3], [-0.2, 0.1, 0.05]], dtype=F64), dim=-1
)


def exact_pi_rotation(axis):
    """R(pi, r) = 2 r r^T - I from (2.25): exactly symmetric, so the angle is exactly pi."""
    return 2 * axis[..., :, None] * axis[..., None, :] - torch.eye(3, dtype=axis.dtype)


@pytest.mark.parametrize("dtype", DTYPES)
def test_grad_finite_axis_angle_at_zero(dtype):
    v = torch.zeros(3, dtype=dtype)
    (axis, angle), g = _grad(lambda v: rot.matrix_to_axis_angle(rot.rotvec_to_matrix(v)), v)
    assert angle.item() == 0.0
    close(axis, torch.tensor([1.0, 0, 0]), dtype)
    _, gR = _grad(rot.matrix_to_axis_angle, torch.eye(3, dtype=dtype))
    _assert_finite(g, gR)


@pytest.mark.parametrize("dtype", DTYPES)
def test_grad_finite_axis_angle_at_pi(dtype):
    axes = PI_AXES.to(dtype)
    R = exact_pi_rotation(axes)
    (axis, angle), gR = _grad(rot.matrix_to_axis_angle, R)
    close(angle, torch.full((5,), math.pi, dtype=F64), dtype)
    # deterministic sign: the largest-magnitude component of the axis is positive
    big = axes.abs().argmax(-1, keepdim=True)
    close(axis, axes * torch.sign(axes.gather(-1, big)), dtype, scale=10)
    close(rot.axis_angle_to_matrix(axis, angle), R, dtype)
    _, g = _grad(lambda v: rot.matrix_to_axis_angle(rot.rotvec_to_matrix(v)), math.pi * axes)
    _assert_finite(gR, g)


@pytest.mark.parametrize("dtype", DTYPES)
def test_grad_rotvec_at_zero_is_identity(dtype):
    jac = torch.autograd.functional.jacobian(
        lambda v: rot.matrix_to_rotvec(rot.rotvec_to_matrix(v)), torch.zeros(3, dtype=dtype)
    )
    close(jac, torch.eye(3), dtype)
    _, g = _grad(rot.matrix_to_rotvec, torch.eye(3, dtype=dtype))
    _assert_finite(g)


@pytest.mark.parametrize("dtype", DTYPES)
def test_grad_finite_rotvec_at_pi(dtype):
    v = math.pi * PI_AXES.to(dtype)
    out, g = _grad(lambda v: rot.matrix_to_rotvec(rot.rotvec_to_matrix(v)), v)
    close(rot.rotvec_to_matrix(out[0]), rot.rotvec_to_matrix(v), dtype)
    close(torch.linalg.norm(out[0], dim=-1), torch.full((5,), math.pi, dtype=F64), dtype)
    _, gR = _grad(rot.matrix_to_rotvec, exact_pi_rotation(PI_AXES.to(dtype)))
    _assert_finite(g, gR)


@pytest.mark.parametrize("dtype", DTYPES)
def test_grad_finite_quaternion_at_pi(dtype):
    R = exact_pi_rotation(PI_AXES.to(dtype))
    Q, gR = _grad(rot.matrix_to_quaternion, R)
    close(Q[0][..., 0], torch.zeros(5), dtype)
    close(rot.quaternion_to_matrix(Q[0]), R, dtype)
    v = math.pi * PI_AXES.to(dtype)
    _, gq = _grad(lambda v: rot.quaternion_to_rotvec(rot.rotvec_to_quaternion(v)), v)
    _assert_finite(gR, gq)


@pytest.mark.parametrize("dtype", DTYPES)
def test_grad_finite_quaternion_at_zero(dtype):
    Q, gR = _grad(rot.matrix_to_quaternion, torch.eye(3, dtype=dtype))
    close(Q[0], torch.tensor([1.0, 0, 0, 0]), dtype)
    _, g = _grad(rot.quaternion_to_rotvec, torch.tensor([1.0, 0, 0, 0], dtype=dtype))
    _assert_finite(gR, g)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("theta", [0.0, math.pi])
@pytest.mark.parametrize("branch", ["positive", "negative"])
def test_grad_finite_zyz_gimbal_lock(dtype, theta, branch):
    ang = torch.tensor([[0.3, theta, 0.5], [-2.0, theta, 1.0], [0.0, theta, 0.0]], dtype=dtype)
    R = rot.euler_to_matrix(ang, "ZYZ")
    out, g = _grad(lambda a: rot.matrix_to_euler(rot.euler_to_matrix(a, "ZYZ"), "ZYZ", branch), ang)
    back = out[0]
    close(back[:, 0], torch.zeros(3), dtype)  # phi = 0 by convention
    close(rot.euler_to_matrix(back, "ZYZ"), R, dtype)
    _, gR = _grad(lambda R: rot.matrix_to_euler(R, "ZYZ", branch), R)
    _assert_finite(back, g, gR)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("theta", [math.pi / 2, -math.pi / 2])
@pytest.mark.parametrize("branch", ["positive", "negative"])
def test_grad_finite_rpy_singular(dtype, theta, branch):
    ang = torch.tensor([[0.3, theta, 0.5], [-2.0, theta, 1.0], [0.0, theta, 0.0]], dtype=dtype)
    R = rot.euler_to_matrix(ang, "RPY")
    out, g = _grad(lambda a: rot.matrix_to_euler(rot.euler_to_matrix(a, "RPY"), "RPY", branch), ang)
    back = out[0]
    close(rot.euler_to_matrix(back, "RPY"), R, dtype)
    _, gR = _grad(lambda R: rot.matrix_to_euler(R, "RPY", branch), R)
    _assert_finite(back, g, gR)


def test_grad_finite_slerp_identical_and_antipodal():
    Q = rot.matrix_to_quaternion(random_rotations(30, (4,))[1])
    for Q1 in (Q, -Q):
        q0, q1 = Q.clone().requires_grad_(), Q1.clone().requires_grad_()
        s = torch.full((4,), 0.3, dtype=F64, requires_grad=True)
        out = rot.quaternion_slerp(q0, q1, s)
        grads = torch.autograd.grad(out.sum(), (q0, q1, s))
        _assert_finite(out, *grads)


def test_grad_finite_orientation_errors_at_zero():
    _, R = random_rotations(31, (4,))
    for fn in (
        rot.orientation_error_axis_angle,
        lambda a, b: rot.orientation_error_axis_angle(a, b, form="rotvec"),
        rot.orientation_error_quaternion,
    ):
        a, b = R.clone().requires_grad_(), R.clone().requires_grad_()
        grads = torch.autograd.grad(fn(a, b).sum(), (a, b))
        _assert_finite(*grads)


# -------------------------------------------------------------------------------- shapes and errors
def test_scalar_batch_and_dtype_preserved():
    for dtype in DTYPES:
        a = torch.tensor(0.4, dtype=dtype)
        assert rot.rot_x(a).shape == (3, 3) and rot.rot_x(a).dtype == dtype
        R = rot.euler_to_matrix(torch.tensor([0.1, 0.2, 0.3], dtype=dtype))
        assert R.shape == (3, 3) and R.dtype == dtype
        for fn, shape in (
            (rot.matrix_to_quaternion, (4,)),
            (rot.matrix_to_rotvec, (3,)),
            (rot.matrix_to_euler, (3,)),
            (rot.vee, (3,)),
        ):
            out = fn(R)
            assert out.shape == shape and out.dtype == dtype
        axis, angle = rot.matrix_to_axis_angle(R)
        assert axis.shape == (3,) and angle.shape == () and angle.dtype == dtype
    assert rot.rot_z(math.pi / 2).dtype == torch.get_default_dtype()


def test_errors_bad_shapes():
    with pytest.raises(ShapeError, match=r"\(\.\.\., 3\).*got \(4, 2\)"):
        rot.euler_to_matrix(torch.zeros(4, 2))
    with pytest.raises(ShapeError, match=r"\(\.\.\., 3, 3\)"):
        rot.matrix_to_quaternion(torch.zeros(3, 4))
    with pytest.raises(ShapeError, match=r"\(\.\.\., 4\)"):
        rot.quaternion_to_matrix(torch.zeros(5, 3))
    with pytest.raises(ShapeError):
        rot.orientation_error_quaternion(torch.eye(3), torch.tensor([1.0, 0, 0, 0]))
    with pytest.raises(ShapeError):
        rot.skew(torch.zeros(2))
    assert issubclass(ShapeError, ValueError)


def test_errors_conventions():
    with pytest.raises(ConventionError, match="ZYZ.*RPY"):
        rot.euler_to_matrix(torch.zeros(3), "XYZ")
    with pytest.raises(ConventionError, match="ZYZ.*RPY"):
        rot.matrix_to_euler(torch.eye(3), "ZXZ")
    with pytest.raises(ConventionError, match="ZYZ.*RPY"):
        rot.euler_rate_matrix(torch.zeros(3), "foo")
    with pytest.raises(ConventionError, match="positive.*negative"):
        rot.matrix_to_euler(torch.eye(3), "ZYZ", branch="up")
    with pytest.raises(ConventionError, match="sin.*rotvec"):
        rot.orientation_error_axis_angle(torch.eye(3), torch.eye(3), form="cos")


def test_errors_non_finite_and_types():
    bad = torch.eye(3)
    bad[0, 0] = float("nan")
    for fn in (rot.matrix_to_quaternion, rot.matrix_to_euler, rot.matrix_to_rotvec, rot.matrix_to_axis_angle):
        with pytest.raises(NonFiniteError):
            fn(bad)
    with pytest.raises(NonFiniteError):
        rot.rot_x(torch.tensor([0.0, float("inf")]))
    with pytest.raises(NonFiniteError):
        rot.quaternion_to_matrix(torch.tensor([float("nan"), 0, 0, 0]))
    with pytest.raises(DTypeError):
        rot.euler_to_matrix(torch.zeros(3, dtype=torch.int64))
    with pytest.raises(DTypeError):
        rot.quaternion_multiply(torch.zeros(4), torch.zeros(4, dtype=F64))
    with pytest.raises(DiffkinError, match="non-zero"):
        rot.axis_angle_to_matrix(torch.zeros(3), torch.tensor(1.0))
    with pytest.raises(DiffkinError, match="non-zero"):
        rot.quaternion_to_matrix(torch.zeros(4))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_device_preserved():
    _, R = random_rotations(32, (8,))
    R = R.cuda()
    for fn in (rot.matrix_to_quaternion, rot.matrix_to_rotvec, rot.matrix_to_euler):
        out = fn(R)
        assert out.device == R.device
        assert out.dtype == R.dtype
    Q = rot.matrix_to_quaternion(R)
    assert rot.quaternion_slerp(Q, Q.flip(0), torch.tensor(0.5, device="cuda", dtype=F64)).is_cuda
