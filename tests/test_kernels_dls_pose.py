"""diffkin.kernels: the one damped least-squares solve (3.59) and the one pose error (§3.7.3).

DLS against numpy (both normal-equation sides, λ = 0 vs pinv), batch first ≡ batch last, finite values and
gradients at a singular Jacobian; pose error against scipy's Rotation (rotvec, r sinθ, quaternion vector
part) at random rotations and at θ = 0 and θ = π, columns layout ≡ matrix layout.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from diffkin.kernels.dls import damped_pinv, dls_solve
from diffkin.kernels.pose_error import ORIENTATION_FORMS, orientation_error, pose_error, rotation_angle

F64 = torch.float64


def _J(shape, seed=0, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=g, dtype=F64).to(dtype)


# ------------------------------------------------------------------------------------------ DLS
@pytest.mark.parametrize("k,n", [(6, 7), (3, 7), (6, 6), (12, 7), (18, 4)])
def test_dls_solve_matches_numpy_both_sides(k, n):
    J, e = _J((5, k, n)), _J((5, k), 1)
    lam = torch.tensor([1e-3, 0.01, 0.1, 1.0, 2.5], dtype=F64)
    Jn, en, ln = J.numpy(), e.numpy(), lam.numpy()
    for i in range(5):
        G = Jn[i] @ Jn[i].T + ln[i] * np.eye(k)  # the k×k side
        ref = Jn[i].T @ np.linalg.solve(G, en[i])
        H = Jn[i].T @ Jn[i] + ln[i] * np.eye(n)  # the n×n side
        ref_n = np.linalg.solve(H, Jn[i].T @ en[i])
        np.testing.assert_allclose(ref, ref_n, rtol=1e-9, atol=1e-10)  # the two sides agree
        got = dls_solve(J, e, lam)[i].numpy()
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(damped_pinv(J, lam)[i].numpy(), Jn[i].T @ np.linalg.inv(G), atol=1e-10)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("k,n,m", [(6, 7, 10), (6, 7, 2048), (14, 7, 10), (14, 7, 2048), (3, 7, 1500)])
def test_dls_batch_first_equals_batch_last(dtype, k, n, m):
    J, e = _J((m, k, n), 2, dtype), _J((m, k), 3, dtype)
    lam = 0.01 + torch.rand(m, generator=torch.Generator().manual_seed(4), dtype=F64).to(dtype)
    first = dls_solve(J, e, lam)
    last = dls_solve(J.permute(2, 1, 0).contiguous(), e.T.contiguous(), lam, layout="batch_last").T
    tol = 1e-4 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(last, first, atol=tol, rtol=tol)
    ref = dls_solve(J.double(), e.double(), lam.double())
    torch.testing.assert_close(first.double(), ref, atol=tol, rtol=tol)
    # a scalar λ broadcasts in both layouts
    last = dls_solve(J.permute(2, 1, 0), e.T, 0.1, layout="batch_last").T
    torch.testing.assert_close(last, dls_solve(J, e, 0.1), atol=tol, rtol=tol)


@pytest.mark.parametrize("k,n", [(6, 7), (7, 6), (6, 6)])
def test_undamped_full_rank_is_the_pseudo_inverse(k, n):
    J, e = _J((4, k, n), 5), _J((4, k), 6)
    pinv = np.linalg.pinv(J.numpy())
    np.testing.assert_allclose(damped_pinv(J, 0.0).numpy(), pinv, atol=1e-10)
    ref = (pinv @ e.numpy()[..., None])[..., 0]
    np.testing.assert_allclose(dls_solve(J, e, 0.0).numpy(), ref, atol=1e-10)


def _planar_jacobian(q: torch.Tensor, a=(1.0, 0.8, 0.5)) -> torch.Tensor:
    """Position Jacobian (2 × 3) of a planar 3R arm (3.35-style rows), batch first."""
    th = torch.cumsum(q, -1)
    s, c = torch.sin(th), torch.cos(th)
    a = torch.tensor(a, dtype=q.dtype)
    xs, ys = -(a * s), a * c
    rx = torch.flip(torch.cumsum(torch.flip(xs, [-1]), -1), [-1])
    ry = torch.flip(torch.cumsum(torch.flip(ys, [-1]), -1), [-1])
    return torch.stack((rx, ry), -2)


@pytest.mark.parametrize("layout", ["batch_first", "batch_last"])
def test_singular_stretched_arm_is_finite_with_damping(layout):
    q = torch.zeros(3, 3, dtype=F64, requires_grad=True)  # stretched: rank 1
    J = _planar_jacobian(q)
    e = torch.tensor([[0.1, 0.2], [0.0, 0.3], [1.0, 0.0]], dtype=F64)
    lam = torch.tensor([0.01, 0.1, 1e-4], dtype=F64)
    assert torch.linalg.matrix_rank(J.detach()).max() == 1
    if layout == "batch_first":
        d = dls_solve(J, e, lam)
    else:
        d = dls_solve(J.permute(2, 1, 0), e.T, lam, layout=layout).T
    assert torch.isfinite(d).all()
    assert (d.norm(dim=-1) <= e.norm(dim=-1) / (2 * lam.sqrt()) + 1e-9).all()  # ‖Δ‖ <= ‖e‖ / (2√λ)
    (g,) = torch.autograd.grad(d.square().sum(), q)
    assert torch.isfinite(g).all()
    P = damped_pinv(J, lam)
    assert torch.isfinite(P).all()
    # the bound of the damped inverse: σ/(σ² + λ) <= 1/(2√λ)
    assert (torch.linalg.matrix_norm(P, ord=2) <= 1 / (2 * lam.sqrt()) + 1e-9).all()


def test_dls_gradcheck():
    J = _J((2, 6, 7), 7).requires_grad_()
    e = _J((2, 6), 8).requires_grad_()
    lam = torch.tensor([0.05, 0.2], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda A, b, l: dls_solve(A, b, l), (J, e, lam))
    Jt = _J((2, 9, 4), 9).requires_grad_()  # the n×n side
    et = _J((2, 9), 10).requires_grad_()
    assert torch.autograd.gradcheck(lambda A, b, l: dls_solve(A, b, l), (Jt, et, lam))
    assert torch.autograd.gradcheck(lambda A, l: damped_pinv(A, l), (Jt, lam))
    Jl = _J((7, 6, 3), 11).requires_grad_()
    el = _J((6, 3), 12).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda A, b: dls_solve(A, b, torch.tensor([0.1, 0.2, 0.3], dtype=F64), layout="batch_last"), (Jl, el)
    )


# ----------------------------------------------------------------------------------- pose error
def _rotations(n=64, seed=0):
    rd = Rotation.random(n, random_state=seed)
    re = Rotation.random(n, random_state=seed + 1)
    return rd, re


def _columns(R: torch.Tensor):
    """(m, 3, 3) matrices -> the IK loop's column triple, each (3, m)."""
    return tuple(R[:, :, j].T.contiguous() for j in range(3))


def _check_against_scipy(rd, re, atol=1e-12):
    Rd, Re = torch.tensor(rd.as_matrix()), torch.tensor(re.as_matrix())
    rel = rd * re.inv()  # R_d R_eᵀ (3.84)
    v = rel.as_rotvec()
    th = np.linalg.norm(v, axis=-1)
    e_rv, ang = orientation_error(Rd, Re, "rotvec")
    pi = np.isclose(th, math.pi)
    np.testing.assert_allclose(e_rv.numpy()[~pi], v[~pi], atol=atol)
    # at θ = π the sign of the axis is a convention: π r ≡ −π r
    np.testing.assert_allclose(np.abs(e_rv.numpy()[pi]), np.abs(v[pi]), atol=1e-9)
    np.testing.assert_allclose(ang.numpy(), th, atol=atol)
    sin_form, _ = orientation_error(Rd, Re, "axis_angle")
    axis = v / np.where(th > 0, th, 1.0)[:, None]
    np.testing.assert_allclose(sin_form.numpy(), np.sin(th)[:, None] * axis, atol=atol)
    q, _ = orientation_error(Rd, Re, "quaternion")
    dq = rel.as_quat(canonical=True)[:, :3]  # (3.91) is Δε up to the sign of Δη
    np.testing.assert_allclose(np.abs(q.numpy()), np.abs(dq), atol=atol)
    qs, _ = orientation_error(Rd, Re, "quaternion", shortest=True)  # Δη >= 0: scipy's canonical quaternion
    np.testing.assert_allclose(qs.numpy()[~pi], dq[~pi], atol=atol)
    return Rd, Re


def test_pose_error_vs_scipy_random():
    _check_against_scipy(*_rotations())


def test_pose_error_at_zero_and_pi():
    axes = Rotation.random(6, random_state=3).as_rotvec()
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    re = Rotation.random(12, random_state=4)
    rel = Rotation.from_rotvec(np.concatenate([0.0 * axes, math.pi * axes]))
    rd = rel * re
    Rd, Re = _check_against_scipy(rd, re, atol=1e-9)
    # just below π the axis stays accurate (r sinθ / sinθ would lose ~8 digits at π − 1e-8)
    near = Rotation.from_rotvec((math.pi - 1e-8) * axes) * re[:6]
    e_rv, _ = orientation_error(torch.tensor(near.as_matrix()), Re[:6], "rotvec")
    np.testing.assert_allclose(e_rv.numpy(), (math.pi - 1e-8) * axes, atol=1e-9)
    for form in ORIENTATION_FORMS:
        a, b = Rd.clone().requires_grad_(), Re.clone().requires_grad_()
        e_o, ang = orientation_error(a, b, form)
        grads = torch.autograd.grad(e_o.sum() + ang.sum(), (a, b))
        assert all(bool(torch.isfinite(g).all()) for g in grads), form
        cols = [c.requires_grad_() for c in _columns(Rd) + _columns(Re)]
        e_c, ang_c = orientation_error(cols[:3], cols[3:], form, layout="columns", exact_near_pi=False)
        grads = torch.autograd.grad(e_c.sum() + ang_c.sum(), cols)
        assert all(bool(torch.isfinite(g).all()) for g in grads), form


@pytest.mark.parametrize("form", ORIENTATION_FORMS)
@pytest.mark.parametrize("exact_near_pi", [True, False])
def test_columns_layout_equals_matrix_layout(form, exact_near_pi):
    rd, re = _rotations(200, 7)
    Rd, Re = torch.tensor(rd.as_matrix()), torch.tensor(re.as_matrix())
    p_d, p_e = _J((200, 3), 13), _J((200, 3), 14)
    ep, eo, th = pose_error(p_d, Rd, p_e, Re, form, exact_near_pi=exact_near_pi)
    ep_c, eo_c, th_c = pose_error(p_d.T, _columns(Rd), p_e.T, _columns(Re), form, layout="columns",
                                  exact_near_pi=exact_near_pi)  # fmt: skip
    torch.testing.assert_close(ep_c.T, ep, atol=0, rtol=0)
    torch.testing.assert_close(eo_c.T, eo, atol=1e-14, rtol=0)
    torch.testing.assert_close(th_c, th, atol=1e-14, rtol=0)
    torch.testing.assert_close(rotation_angle(Rd, Re), th, atol=1e-14, rtol=0)
    # float32 too
    eo32, _ = orientation_error(Rd.float(), Re.float(), form, exact_near_pi=exact_near_pi)
    torch.testing.assert_close(eo32.double(), eo, atol=2e-5, rtol=0)


def test_pose_error_gradcheck():
    rd, re = _rotations(3, 21)
    Rd = torch.tensor(rd.as_matrix(), requires_grad=True)
    Re = torch.tensor(re.as_matrix(), requires_grad=True)
    for form in ORIENTATION_FORMS:
        assert torch.autograd.gradcheck(lambda a, b, f=form: orientation_error(a, b, f), (Rd, Re)), form
