"""Pseudo-inverses and null-space projector (§3.4–3.5): diffkin.redundancy (re-exported by diffkin.jacobian).

References: numpy's pinv / SVD, the defining properties (3.52), (3.54), (3.50), (3.59), gradcheck.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffkin.errors import ShapeError
from diffkin.jacobian import geometric_jacobian
from diffkin.redundancy import damped_pinv, nullspace_projector, pinv, weighted_pinv
from tests.helpers import anthropomorphic, panda, planar3

F64 = torch.float64


def panda_J(batch=(3,), seed=0, dtype=F64):
    chain = panda(dtype)
    q = chain.random_configuration(batch, generator=torch.Generator().manual_seed(seed))
    return geometric_jacobian(chain, q)


def singular_J(requires_grad=False):
    """J_P of the anthropomorphic arm at an elbow singularity (ϑ3 = 0), rank 2."""
    q = torch.tensor([0.3, 0.5, 0.0], dtype=F64, requires_grad=requires_grad)
    return q, lambda x: geometric_jacobian(anthropomorphic(), x)[..., :3, :]


def test_pinv_right_and_left():  # (3.52) and the left inverse of a tall J
    J = panda_J().detach()
    Jp = pinv(J)
    np.testing.assert_allclose(Jp.numpy(), np.linalg.pinv(J.numpy()), atol=1e-10)
    torch.testing.assert_close(J @ Jp, torch.eye(6, dtype=F64).expand(3, 6, 6))
    Jt = geometric_jacobian(planar3(), torch.tensor([0.3, 0.9, -0.4], dtype=F64)).detach()  # (6, 3)
    np.testing.assert_allclose(pinv(Jt).numpy(), np.linalg.pinv(Jt.numpy()), atol=1e-10)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_nullspace_projector_properties(dtype):  # (3.54)
    J = panda_J(batch=(2, 2), seed=1, dtype=dtype).detach()
    P = nullspace_projector(J)
    tol = dict(atol=1e-4, rtol=0) if dtype == torch.float32 else dict(atol=1e-10, rtol=0)
    torch.testing.assert_close(P @ P, P, **tol)
    torch.testing.assert_close(P, P.mT, **tol)
    torch.testing.assert_close(J @ P, torch.zeros_like(J), **tol)
    assert P.shape == (2, 2, 7, 7) and P.dtype == dtype
    # rank of the projector = n - m = 1 for the 7-DOF arm
    torch.testing.assert_close(P.diagonal(dim1=-2, dim2=-1).sum(-1), torch.ones(2, 2, dtype=dtype), **tol)


def test_damped_pinv_is_the_damped_svd_inverse():  # (3.59)
    J = panda_J(seed=2).detach()
    lam = 0.01  # λ, added to JJᵀ's diagonal
    U, S, Vt = np.linalg.svd(J.numpy(), full_matrices=False)
    expected = np.einsum("bji,bj,bkj->bik", Vt, S / (S**2 + lam), U)
    np.testing.assert_allclose(damped_pinv(J, lam).numpy(), expected, atol=1e-12)
    # per-configuration damping tensor, and the tall form (JᵀJ + λI)⁻¹Jᵀ
    lams = torch.tensor([0.0, 0.01, 0.25], dtype=F64)
    for i in range(3):
        torch.testing.assert_close(damped_pinv(J, lams)[i], damped_pinv(J[i], float(lams[i])))
    Jt = J.mT
    expected = torch.linalg.solve(J @ Jt + lam * torch.eye(6, dtype=F64), J)
    torch.testing.assert_close(damped_pinv(Jt, lam), expected)
    # weighted_pinv and nullspace_projector: the same λ
    Jn, w = J.numpy()[0], np.array([1.0, 2.0, 0.5, 3.0, 1.5, 1.0, 4.0])
    Wi = np.diag(1.0 / w)
    want = Wi @ Jn.T @ np.linalg.inv(Jn @ Wi @ Jn.T + lam * np.eye(6))
    Jw = weighted_pinv(J[0], torch.from_numpy(w), damping=lam)
    np.testing.assert_allclose(Jw.numpy(), want, atol=1e-12)
    P = np.eye(7) - Jn.T @ np.linalg.solve(Jn @ Jn.T + lam * np.eye(6), Jn)
    np.testing.assert_allclose(nullspace_projector(J[0], damping=lam).numpy(), P, atol=1e-12)


def test_adaptive_damping():
    J = panda_J(seed=3).detach()
    smin = torch.linalg.svdvals(J)[..., -1]
    far = damped_pinv(J, 0.04, threshold=float(smin.min()) * 0.5)  # σ_min above the threshold: undamped
    torch.testing.assert_close(far, pinv(J))
    _, f = singular_J()
    Js = f(torch.tensor([0.3, 0.5, 0.0], dtype=F64)).detach()  # σ_min = 0: full damping
    torch.testing.assert_close(damped_pinv(Js, 0.04, threshold=0.1), damped_pinv(Js, 0.04))


def test_weighted_pinv():  # (3.50): minimum of q̇ᵀWq̇ subject to J q̇ = v
    J = panda_J(batch=(), seed=4).detach()
    w = torch.tensor([1.0, 2.0, 0.5, 3.0, 1.5, 1.0, 4.0], dtype=F64)
    Jw = weighted_pinv(J, w)
    torch.testing.assert_close(Jw, weighted_pinv(J, torch.diag(w)))
    torch.testing.assert_close(J @ Jw, torch.eye(6, dtype=F64))
    Wi = np.diag(1.0 / w.numpy())
    Jn = J.numpy()
    np.testing.assert_allclose(Jw.numpy(), Wi @ Jn.T @ np.linalg.inv(Jn @ Wi @ Jn.T), atol=1e-10)
    # any other solution q̇ + P q̇0 has a larger weighted norm
    v = torch.randn(6, dtype=F64, generator=torch.Generator().manual_seed(0))
    qd = Jw @ v
    other = qd + nullspace_projector(J, J_pinv=Jw) @ torch.ones(7, dtype=F64)
    torch.testing.assert_close(J @ other, v)
    assert (other * w * other).sum() > (qd * w * qd).sum()
    torch.testing.assert_close(weighted_pinv(J, torch.ones(7, dtype=F64)), pinv(J))
    with pytest.raises(ShapeError):
        weighted_pinv(J, torch.ones(6, dtype=F64))


def test_finite_at_exact_singularity():
    q, f = singular_J(requires_grad=True)
    J = f(q)
    assert torch.linalg.svdvals(J.detach())[-1] < 1e-12
    outs = [pinv(J), damped_pinv(J, 2.5e-3), weighted_pinv(J, torch.tensor([1.0, 2.0, 3.0], dtype=F64)),
            nullspace_projector(J), damped_pinv(J, 2.5e-3, threshold=0.1)]  # fmt: skip
    for out in outs:
        assert torch.isfinite(out).all()
        (g,) = torch.autograd.grad(out.sum(), q, retain_graph=True)
        assert torch.isfinite(g).all()
    # the lost direction joins the null space: P has rank 1 and J P = 0
    P = nullspace_projector(J).detach()
    torch.testing.assert_close(J.detach() @ P, torch.zeros(3, 3, dtype=F64), atol=1e-9, rtol=0)
    torch.testing.assert_close(P.trace(), torch.tensor(1.0, dtype=F64), atol=1e-6, rtol=0)


def test_gradcheck_at_singularity():
    q, f = singular_J(requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: damped_pinv(f(x), 0.01), (q,))
    assert torch.autograd.gradcheck(lambda x: nullspace_projector(f(x), damping=0.01), (q,))
    w = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    assert torch.autograd.gradcheck(lambda x: weighted_pinv(f(x), w, damping=0.01), (q,))
    assert torch.autograd.gradcheck(lambda x: damped_pinv(f(x), 0.01, threshold=0.2), (q,))
    # and the exact inverse near (not at) the singularity
    q_near = torch.tensor([0.3, 0.5, 0.2], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: pinv(f(x)), (q_near,))
    assert torch.autograd.gradcheck(lambda x: nullspace_projector(geometric_jacobian(panda(), x)),
                                    (torch.full((7,), 0.3, dtype=F64, requires_grad=True),))  # fmt: skip


def test_bounded_near_singularity():
    _, f = singular_J()
    for eps in (1e-3, 1e-6, 1e-9):
        J = f(torch.tensor([0.3, 0.5, eps], dtype=F64)).detach()
        # σ/(σ²+k²) <= 1/2k
        assert torch.linalg.matrix_norm(damped_pinv(J, 0.1), ord=2) <= 1 / (2 * 0.1) + 1e-9
        assert torch.isfinite(pinv(J)).all()
    assert math.isfinite(float(pinv(torch.zeros(2, 3, dtype=F64)).abs().max()))


# ----------------------------------------------------------------- rank-deficient J, singular rows (#15)
def rank_deficient(gen, batch, m, n, r, dtype=F64):
    A = torch.randn(*batch, m, r, generator=gen, dtype=F64)
    return (A @ torch.randn(*batch, r, n, generator=gen, dtype=F64)).to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_pinv_matches_numpy_on_random_rank_deficient_matrices(dtype):
    from diffkin.redundancy import rcond

    g = torch.Generator().manual_seed(0)
    for _ in range(60):
        m, n = (int(v) for v in torch.randint(1, 9, (2,), generator=g))
        r = int(torch.randint(0, min(m, n) + 1, (1,), generator=g))
        J = rank_deficient(g, (5,), m, n, r, dtype)
        ref = np.linalg.pinv(J.double().numpy(), rcond=rcond(dtype))
        scale = max(1.0, float(np.abs(ref).max()))
        tol = 1e-9 if dtype == F64 else 2e-3
        np.testing.assert_allclose(pinv(J).double().numpy() / scale, ref / scale, atol=tol)
        np.testing.assert_allclose(damped_pinv(J, 0.0).double().numpy() / scale, ref / scale, atol=tol)
        P = nullspace_projector(J).double().numpy()
        np.testing.assert_allclose(P, np.eye(n) - ref @ J.double().numpy(), atol=tol * 10)


def stretched_planar():
    from diffkin import models

    return models.load("three_link_planar", dtype=F64)


def test_one_singular_row_does_not_fail_the_batch():
    """A stretched planar arm in a batch used to raise torch's _LinAlgError for the whole batch."""
    chain = stretched_planar()
    q = torch.tensor([[0.0, 0.0, 0.0], [0.4, 0.0, 0.0], [0.3, 0.9, -0.4]], dtype=F64, requires_grad=True)
    J = geometric_jacobian(chain, q)
    for f in (pinv, nullspace_projector, lambda x: damped_pinv(x, 0.0), lambda x: damped_pinv(x, 0.0, 0.1)):
        out = f(J)
        assert torch.isfinite(out).all()
        (g,) = torch.autograd.grad(out.square().sum(), q, retain_graph=True)
        assert torch.isfinite(g).all()
    Jd = J.detach()
    np.testing.assert_allclose(pinv(Jd).numpy(), np.linalg.pinv(Jd.numpy(), rcond=1.5e-8), atol=1e-10)
    torch.testing.assert_close(pinv(Jd)[2], pinv(Jd[2]))  # the regular row is not affected by the others
    torch.testing.assert_close(damped_pinv(Jd, 0.0), pinv(Jd))


def test_pinv_gradient_at_constant_rank_matches_finite_differences():
    """The SVD rows' closed-form derivative: gradcheck on a rank-2 family J(x) = A(x) B."""
    g = torch.Generator().manual_seed(3)
    B = torch.randn(2, 5, generator=g, dtype=F64)
    C = torch.randn(4, 2, generator=g, dtype=F64)

    def f(x):
        A = C + x.reshape(4, 2)
        return pinv(A @ B)

    x = torch.randn(8, generator=g, dtype=F64, requires_grad=True) * 0.1
    assert torch.linalg.matrix_rank((C + x.detach().reshape(4, 2)) @ B) == 2
    assert torch.autograd.gradcheck(f, (x,))
    assert torch.autograd.gradcheck(lambda x: nullspace_projector((C + x.reshape(4, 2)) @ B), (x,))


def test_inputs_follow_the_rule():
    from diffkin.errors import DiffkinError, DTypeError, NonFiniteError

    J = panda_J(batch=(2,)).detach()
    for bad in (torch.float16, torch.bfloat16, torch.int64, torch.complex64):
        with pytest.raises(DTypeError):
            pinv(J.to(bad))
    with pytest.raises(DTypeError, match="float32|float64"):
        weighted_pinv(J, torch.ones(7))  # mixed float64 / float32
    Jn = J.clone()
    Jn[0, 1, 2] = float("nan")
    for f in (pinv, nullspace_projector, lambda x: damped_pinv(x, 0.1)):
        with pytest.raises(NonFiniteError):
            f(Jn)
    with pytest.raises(NonFiniteError):
        damped_pinv(J, float("inf"))
    with pytest.raises(DiffkinError, match="positive"):
        weighted_pinv(J, torch.tensor([1.0, 2, 0, 1, 1, 1, 1], dtype=F64))
    with pytest.raises(ShapeError):
        nullspace_projector(J, J_pinv=J)
    torch.testing.assert_close(pinv(J.numpy()), pinv(J))  # numpy converted
    assert pinv(torch.zeros(0, 6, 7, dtype=F64)).shape == (0, 7, 6)
