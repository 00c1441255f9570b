"""Singularities (§3.3), manipulability and ellipsoids (§3.9): diffkin.manipulability.

References: the textbook's determinants (3.41), §3.3.3 and (3.44), Example 3.6, numpy's SVD / det / cond.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffkin import DHChain
from diffkin.errors import ModelError, ShapeError
from diffkin.jacobian import geometric_jacobian
from diffkin.manipulability import (
    condition_number,
    decoupled_singularities,
    force_ellipsoid,
    force_transmission_ratio,
    inverse_condition_number,
    jacobian_determinant,
    manipulability,
    smallest_singular_value,
    velocity_ellipsoid,
    velocity_transmission_ratio,
)
from tests.helpers import anthropomorphic, panda, planar3, stanford

F64 = torch.float64
PI = math.pi


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def two_link(a1=1.0, a2=1.0) -> DHChain:
    z = torch.zeros(2, dtype=F64)
    return DHChain(torch.tensor([a1, a2], dtype=F64), z, z, z)


def arm_with_wrist(a2=0.5, d4=0.7, d6=0.1) -> DHChain:  # Table 2.6
    return DHChain(
        torch.tensor([0, a2, 0, 0, 0, 0], dtype=F64),
        torch.tensor([PI / 2, 0, PI / 2, -PI / 2, PI / 2, 0], dtype=F64),
        torch.tensor([0, 0, 0, d4, 0, d6], dtype=F64),
        torch.zeros(6, dtype=F64),
    )


def _J2(chain, q):
    return geometric_jacobian(chain, q)[..., :2, :]  # planar position rows (3.40)


# ----------------------------------------------------------------------------------- determinants
def test_two_link_determinant():  # (3.41)
    a1, a2 = 0.7, 0.4
    q = torch.tensor([[0.3, 1.2], [-1.0, -0.4], [2.0, 0.0]], dtype=F64)
    det = jacobian_determinant(_J2(two_link(a1, a2), q))
    torch.testing.assert_close(det.detach(), a1 * a2 * torch.sin(q[:, 1]))


def test_anthropomorphic_determinant():  # §3.3.3: det J_P = -a2 a3 s3 (a2 c2 + a3 c23)
    a2, a3 = 0.6, 0.45
    q = anthropomorphic().random_configuration((6,), generator=torch.Generator().manual_seed(0))
    Jp = geometric_jacobian(anthropomorphic(a2, a3), q)[..., :3, :]
    c2, s3, c23 = torch.cos(q[:, 1]), torch.sin(q[:, 2]), torch.cos(q[:, 1] + q[:, 2])
    expected = -a2 * a3 * s3 * (a2 * c2 + a3 * c23)
    torch.testing.assert_close(jacobian_determinant(Jp).detach(), expected)
    np.testing.assert_allclose(jacobian_determinant(Jp).detach().numpy(), np.linalg.det(Jp.detach().numpy()))


def test_determinant_gradient_at_singularity_is_the_adjugate():
    q = torch.tensor([0.4, 0.0], dtype=F64, requires_grad=True)  # outstretched: det = 0
    J = _J2(two_link(), q)
    (g,) = torch.autograd.grad(jacobian_determinant(J), J)
    Jd = J.detach()
    adj_t = torch.tensor([[Jd[1, 1], -Jd[1, 0]], [-Jd[0, 1], Jd[0, 0]]], dtype=F64)  # d det / dJ = adj(J)ᵀ
    torch.testing.assert_close(g, adj_t)
    with pytest.raises(ShapeError):
        jacobian_determinant(torch.zeros(2, 3, dtype=F64))


def test_singular_configurations_are_found_singular():
    rows = [0, 1, 5]  # the non-null rows of (3.35)
    J = geometric_jacobian(planar3(), torch.tensor([[0.3, 0.0, 0.5], [0.3, 1.0, 0.5]], dtype=F64))
    s = smallest_singular_value(J[..., rows, :]).detach()
    assert s[0] < 1e-12 and s[1] > 1e-2
    arm = anthropomorphic(0.6, 0.45)
    # elbow (ϑ3 = 0, π), shoulder (a2 c2 + a3 c23 = 0), regular
    th2 = 1.2
    th3_sh = math.acos(-0.6 * math.cos(th2) / 0.45) - th2
    q = torch.tensor([[0.2, 0.5, 0.0], [0.2, 0.5, PI], [0.2, th2, th3_sh], [0.2, 0.5, 1.0]], dtype=F64)
    s = smallest_singular_value(geometric_jacobian(arm, q)[..., :3, :]).detach()
    assert torch.all(s[:3] < 1e-12) and s[3] > 1e-2
    q = torch.tensor([[0.3, 0.8, 0.5, -0.6, 0.0, 0.4], [0.3, 0.8, 0.5, -0.6, 1.0, 0.4]], dtype=F64)
    s = smallest_singular_value(geometric_jacobian(stanford(), q)).detach()  # wrist: ϑ5 = 0
    assert s[0] < 1e-12 and s[1] > 1e-2


def test_decoupled_singularities_arm_with_spherical_wrist():  # (3.42)–(3.44), §3.3.2–3.3.3
    a2, d4 = 0.5, 0.7
    chain = arm_with_wrist(a2, d4)
    q = chain.random_configuration((5,), generator=torch.Generator().manual_seed(1))
    out = decoupled_singularities(chain, q)
    det = jacobian_determinant(geometric_jacobian(chain, q))
    torch.testing.assert_close(out.det_arm * out.det_wrist, det)
    torch.testing.assert_close(out.wrist_measure, torch.sin(q[:, 4]).abs())
    T = chain.forward_kinematics(q)
    torch.testing.assert_close(out.wrist_point, T[..., :3, 3] - 0.1 * T[..., :3, 2])  # p_W = p_e - d6 a_e
    th2 = 0.3
    th3_sh = math.asin(-a2 * math.cos(th2) / d4) - th2  # a2 c2 + d4 s23 = 0: wrist point on z0 (2.70)
    q = torch.tensor([
        [0.1, 0.4, 0.6, 0.5, 0.0, 0.2],  # wrist: ϑ5 = 0
        [0.1, 0.4, PI / 2, 0.5, 0.8, 0.2],  # elbow: ϑ3 = π/2 with Table 2.6's frames
        [0.1, th2, th3_sh, 0.5, 0.8, 0.2],  # shoulder
        [0.1, 0.4, 0.6, 0.5, 0.8, 0.2],  # regular
    ], dtype=F64)  # fmt: skip
    out = decoupled_singularities(chain, q)
    assert out.wrist.tolist() == [True, False, False, False]
    assert out.elbow.tolist() == [False, True, False, False]
    assert out.shoulder.tolist() == [False, False, True, False]
    s = smallest_singular_value(geometric_jacobian(chain, q)).detach()
    assert torch.all(s[:3] < 1e-9) and s[3] > 1e-2


def test_decoupled_singularities_anthropomorphic_arm_book_expressions():  # §3.3.3, Table 2.4
    a2, a3 = 0.6, 0.45
    chain = anthropomorphic(a2, a3)
    q = chain.random_configuration((7,), generator=torch.Generator().manual_seed(2)).requires_grad_()
    out = decoupled_singularities(chain, q)
    c2, s3, c23 = torch.cos(q[:, 1]), torch.sin(q[:, 2]), torch.cos(q[:, 1] + q[:, 2])
    torch.testing.assert_close(out.elbow_measure, s3.abs())
    torch.testing.assert_close(out.shoulder_measure, (a2 * c2 + a3 * c23).abs())
    torch.testing.assert_close(out.det_arm, -a2 * a3 * s3 * (a2 * c2 + a3 * c23))
    assert not out.wrist.any()
    sum(f.sum() for f in (out.elbow_measure, out.shoulder_measure, out.det_arm)).backward()
    assert torch.isfinite(q.grad).all()
    with pytest.raises(ModelError):
        decoupled_singularities(panda(), torch.zeros(7, dtype=F64))


# --------------------------------------------------------------------------------- manipulability
def test_manipulability_is_product_of_singular_values():  # (3.56), Problem 3.8
    chain = panda()
    J = geometric_jacobian(chain, chain.random_configuration((4,), generator=_gen(3)))
    Jn = J.detach().numpy()
    w = manipulability(J).detach().numpy()
    np.testing.assert_allclose(w, np.prod(np.linalg.svd(Jn, compute_uv=False), axis=-1), rtol=1e-10)
    np.testing.assert_allclose(w, np.sqrt(np.linalg.det(Jn @ Jn.transpose(0, 2, 1))), rtol=1e-8)


def test_two_link_manipulability_example_3_6():
    a1, a2 = 1.0, 0.8
    q = torch.tensor([[0.2, 0.3], [1.0, -PI / 2], [0.0, PI / 2], [0.5, 0.0]], dtype=F64)
    w = manipulability(_J2(two_link(a1, a2), q)).detach()
    torch.testing.assert_close(w, a1 * a2 * torch.sin(q[:, 1]).abs())  # w = a1 a2 |s2|, max at ±π/2


def test_manipulability_gradients_at_and_near_singularity():
    q = torch.tensor([[0.3, 0.4, 0.0], [0.3, 0.4, PI]], dtype=F64, requires_grad=True)
    w = manipulability(geometric_jacobian(anthropomorphic(), q)[..., :3, :])
    (g,) = torch.autograd.grad(w.sum(), q)
    assert torch.allclose(w, torch.zeros_like(w), atol=1e-12) and torch.isfinite(g).all()
    q_near = torch.tensor([0.3, 0.7, 0.05], dtype=F64, requires_grad=True)
    f = lambda x: manipulability(geometric_jacobian(anthropomorphic(), x)[:3, :])  # noqa: E731
    assert torch.autograd.gradcheck(f, (q_near,))
    q_p = panda().random_configuration((2,), generator=torch.Generator().manual_seed(4)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: manipulability(geometric_jacobian(panda(), x)), (q_p,))


def test_condition_numbers():
    chain = panda()
    J = geometric_jacobian(chain, chain.random_configuration((3,), generator=_gen(5)))
    c = condition_number(J).detach().numpy()
    np.testing.assert_allclose(c, np.linalg.cond(J.detach().numpy()), rtol=1e-10)
    np.testing.assert_allclose(inverse_condition_number(J).detach().numpy(), 1.0 / c, rtol=1e-10)
    Js = torch.tensor([[1.0, 2.0], [2.0, 4.0]], dtype=F64)
    assert torch.isinf(condition_number(Js)) or condition_number(Js) > 1e15
    assert inverse_condition_number(torch.zeros(2, 3, dtype=F64)) == 0


# -------------------------------------------------------------------------------------- ellipsoids
PARTS = [("full", slice(None)), ("position", slice(0, 3)), ("orientation", slice(3, 6))]


@pytest.mark.parametrize("part,rows", PARTS)
def test_ellipsoids_are_the_svd_of_J(part, rows):  # (3.123), (3.126)
    chain = panda()
    J = geometric_jacobian(chain, chain.random_configuration((2,), generator=_gen(6)))
    U_np, S_np, _ = np.linalg.svd(J.detach().numpy()[:, rows, :])
    vel, force = velocity_ellipsoid(J, part=part), force_ellipsoid(J, part=part)
    np.testing.assert_allclose(vel.lengths.detach().numpy(), S_np, rtol=1e-10)
    np.testing.assert_allclose(force.lengths.detach().numpy(), 1.0 / S_np, rtol=1e-10)
    # same principal axes (up to sign) for both ellipsoids, = eigenvectors of J Jᵀ
    dots = np.abs(np.einsum("bij,bij->bj", vel.axes.detach().numpy(), U_np))
    np.testing.assert_allclose(dots, 1.0, atol=1e-9)
    torch.testing.assert_close(force.axes, vel.axes)
    Jp = J[:, rows, :]
    torch.testing.assert_close(vel.axes @ torch.diag_embed(vel.lengths**2) @ vel.axes.mT, Jp @ Jp.mT)


def test_ellipsoid_of_a_tall_jacobian_and_its_surface():
    J = geometric_jacobian(planar3(), torch.tensor([0.3, 0.9, -0.4], dtype=F64))  # (6, 3), rank 3
    vel, force = velocity_ellipsoid(J), force_ellipsoid(J)
    assert vel.axes.shape == (6, 6) and vel.lengths.shape == (6,)
    assert torch.all(vel.lengths[3:] < 1e-7) and torch.all(force.lengths[3:] > 1e6)
    # 2-link arm, square: unit joint velocities map onto the surface vᵀ(JJᵀ)⁻¹v = 1 (3.123)
    J2 = _J2(two_link(), torch.tensor([0.3, 1.1], dtype=F64))
    ell = velocity_ellipsoid(J2)
    qd = torch.tensor([math.cos(0.7), math.sin(0.7)], dtype=F64)
    coords = ell.axes.T @ (J2 @ qd) / ell.lengths
    torch.testing.assert_close((coords**2).sum(), torch.tensor(1.0, dtype=F64))


def test_transmission_ratios_along_the_principal_axes():  # (3.127), (3.128)
    J = _J2(two_link(1.0, 0.6), torch.tensor([[0.3, 1.1], [-0.2, 2.0]], dtype=F64))
    ell = velocity_ellipsoid(J)
    for i in range(2):
        u = ell.axes[..., :, i]
        torch.testing.assert_close(force_transmission_ratio(J, u), 1.0 / ell.lengths[..., i])
        torch.testing.assert_close(velocity_transmission_ratio(J, u), ell.lengths[..., i])
    u = torch.tensor([0.6, 0.8], dtype=F64)
    Jn = J.detach().numpy()
    G = Jn @ Jn.transpose(0, 2, 1)
    np.testing.assert_allclose(velocity_transmission_ratio(J, u).detach().numpy(),
                               (u.numpy() @ np.linalg.inv(G) @ u.numpy()) ** -0.5, rtol=1e-10)  # fmt: skip
