"""The kernel layer (diffkin.kernels): joint encodings, the tree product in both layouts, the Jacobian of
trees, the parameter Jacobian; against scipy, numpy products of the textbook's matrices, finite
differences and gradcheck."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from diffkin import DHChain
from diffkin.kernels.columns import apply_fixed, plan_of
from diffkin.kernels.joints import axis_alignment, dh_joints, general_joints, origin_transform
from diffkin.kernels.tree import Topology
from diffkin.models import from_urdf

F64 = torch.float64
DATA = Path(__file__).parent / "data" / "urdf"
ALLEGRO_TIPS = [f"link_{i}.0_tip" for i in (3, 7, 11, 15)]


def _np_dh(a, alpha, d, theta):  # (2.52) written out for the test
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d],
                     [0, 0, 0, 1]])


def _np_roty(b):
    c, s = np.cos(b), np.sin(b)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


# ------------------------------------------------------------------------------------------ joints
def test_axis_alignment_maps_ez_to_the_axis_and_is_a_rotation():
    rng = np.random.default_rng(0)
    k = np.concatenate([rng.normal(size=(50, 3)), np.eye(3), -np.eye(3), [[1e-9, 0, -1.0]]])
    axis = torch.tensor(k, dtype=F64)
    S = axis_alignment(axis, axis[:, 2] < 0)
    unit = axis / axis.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(S[..., 2], unit, atol=1e-14, rtol=0)
    torch.testing.assert_close(S.transpose(-1, -2) @ S, torch.eye(3, dtype=F64).expand_as(S), atol=1e-14,
                               rtol=0)
    torch.testing.assert_close(torch.linalg.det(S), torch.ones(len(k), dtype=F64), atol=1e-14, rtol=0)
    # axis-aligned axes of real URDFs give exact signed permutations (constant plans skip every zero)
    exact = axis_alignment(torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]], dtype=F64),
                           torch.tensor([False, False, True]))
    assert bool(((exact == 0) | (exact.abs() == 1)).all())
    # finite, correct gradients w.r.t. the axis (normalised inside)
    x = torch.tensor([[0.3, -0.2, 0.9], [0.1, 0.5, -0.7]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: axis_alignment(v, torch.tensor([False, True])), (x,))


def test_general_joint_is_rodrigues_about_the_axis():
    """Pre · Rz(q) · Post = origin · Rot(k, q) (scipy's rotation vector k q), for tilted and negative axes."""
    rng = np.random.default_rng(1)
    J = 20
    xyz, rpy = rng.normal(size=(J, 3)), rng.uniform(-3, 3, (J, 3))
    k = rng.normal(size=(J, 3))
    q = rng.uniform(-3, 3, J)
    t = lambda a: torch.tensor(a, dtype=F64)  # noqa: E731
    pre, post = general_joints(t(xyz), t(rpy), t(k), t(k[:, 2] < 0))
    c, s = np.cos(q), np.sin(q)
    Rz = np.zeros((J, 4, 4))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2], Rz[:, 3, 3] = c, -s, s, c, 1, 1
    A = pre.numpy() @ Rz @ post.numpy()
    O = np.tile(np.eye(4), (J, 1, 1))
    O[:, :3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()  # URDF rpy: fixed-axis x, y, z
    O[:, :3, 3] = xyz
    M = np.tile(np.eye(4), (J, 1, 1))
    M[:, :3, :3] = Rotation.from_rotvec(k / np.linalg.norm(k, axis=1, keepdims=True) * q[:, None]).as_matrix()
    np.testing.assert_allclose(A, O @ M, atol=1e-13)
    np.testing.assert_allclose(origin_transform(t(xyz), t(rpy)).numpy(), O, atol=1e-14)


@pytest.mark.parametrize("modified", [False, True])
def test_dh_joints_match_the_textbook_matrices(modified):
    """Pre · M(q + offset) · Post = (2.52) (standard, with Hayati's Ry(β)) or Craig's matrix, R and P."""
    rng = np.random.default_rng(2)
    n = 12
    a, alpha, d, theta, beta = (rng.uniform(-1, 1, n) for _ in range(5))
    rev = (rng.random(n) > 0.4).astype(float)
    q = rng.uniform(-2, 2, n)
    t = lambda x: torch.tensor(x, dtype=F64)  # noqa: E731
    hayati = None if modified else t(beta)
    pre, off, post = dh_joints(t(a), t(alpha), t(d), t(theta), t(rev), modified, hayati)
    for i in range(n):
        th, dd = (theta[i] + q[i], d[i]) if rev[i] else (theta[i], d[i] + q[i])
        if modified:
            ref = Rotation.from_euler("x", alpha[i]).as_matrix()
            T1 = np.eye(4)
            T1[:3, :3] = ref
            Tx = np.eye(4)
            Tx[0, 3] = a[i]
            ref = T1 @ Tx @ _np_dh(0.0, 0.0, dd, th)
        else:
            ref = _np_dh(a[i], alpha[i], dd, th) @ _np_roty(beta[i])
        qi = q[i] + off[i].item()
        c, s = math.cos(qi), math.sin(qi)
        M = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]) if rev[i] else \
            np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, qi], [0, 0, 0, 1.0]])
        P = np.eye(4) if pre is None else pre[i].numpy()
        Q = np.eye(4) if post is None else post[i].numpy()
        np.testing.assert_allclose(P @ M @ Q, ref, atol=1e-14)


def test_constant_plans_apply_like_the_tensor():
    """apply_fixed with a Python-float plan (zero terms skipped) ≡ with the tensor, in both layouts."""
    rng = np.random.default_rng(3)
    R = Rotation.random(random_state=4).as_matrix()
    for M in (R, np.round(R)):  # a generic and a (snapped) signed-permutation-like matrix
        T = torch.eye(4, dtype=F64)
        T[:3, :3] = torch.tensor(M)
        T[:3, 3] = torch.tensor(rng.normal(size=3))
        F = torch.tensor(rng.normal(size=(5, 4, 4)), dtype=F64)
        cols_bl = tuple(F[:, :3, j].T.contiguous() for j in range(4))  # batch last (3, 5)
        cols_bf = tuple(F[:, :3, j] for j in range(4))  # batch first (5, 3)
        want = (F @ T)[:, :3, :]
        for fixed in (T, plan_of(T)):
            got_bl = apply_fixed(cols_bl, fixed, 0)
            got_bf = apply_fixed(cols_bf, fixed, -1)
            for j in range(4):
                torch.testing.assert_close(got_bl[j].T, want[:, :, j], atol=1e-14, rtol=0)
                torch.testing.assert_close(got_bf[j], want[:, :, j], atol=1e-14, rtol=0)


# ------------------------------------------------------------------------------------------ Hayati
def test_hayati_beta_chain_fk_gradcheck_and_yaml_round_trip():
    rng = np.random.default_rng(5)
    n = 4
    table = [rng.uniform(-1, 1, n) for _ in range(4)]
    beta = rng.uniform(-0.3, 0.3, n)
    chain = DHChain(*(torch.tensor(c, dtype=F64) for c in table), beta=torch.tensor(beta, dtype=F64))
    q = torch.tensor(rng.uniform(-2, 2, (6, n)), dtype=F64)
    ref = np.stack([np.linalg.multi_dot([_np_dh(table[0][i], table[1][i], table[2][i], table[3][i] + qq[i])
                                         @ _np_roty(beta[i]) for i in range(n)]) for qq in q.numpy()])
    torch.testing.assert_close(chain.forward_kinematics(q).detach(), torch.tensor(ref), atol=1e-13, rtol=0)
    assert {k for k, _ in chain.named_parameters()} >= {"beta"}
    b = chain.beta.detach().clone().requires_grad_(True)
    fk = lambda x: torch.func.functional_call(chain, {"beta": x}, (q,))  # noqa: E731
    assert torch.autograd.gradcheck(fk, (b,))
    again = DHChain.from_yaml(chain.to_yaml(), dtype=F64)
    torch.testing.assert_close(again.beta, chain.beta, atol=0, rtol=0)
    with pytest.raises(Exception, match="standard"):
        DHChain(*table, convention="modified", beta=beta)


def test_hayati_beta_is_a_small_parameter_for_a_tilt_of_a_parallel_axis():
    """Two parallel axes (α = 0): tilting the second by ε in their plane is β = ε under Hayati; DH would
    need d → ∞ (the classic failure the β parameter exists for)."""
    eps = 1e-3
    nominal = DHChain([0.5, 0.4], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], dtype=F64, beta=[0.0, 0.0])
    tilted = DHChain([0.5, 0.4], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], dtype=F64, beta=[eps, 0.0])
    q = torch.zeros(2, dtype=F64)
    z2 = tilted.forward_kinematics(q)[:3, 2]  # the second axis after the first link: tilted by eps about y
    torch.testing.assert_close(z2, torch.tensor([math.sin(eps), 0.0, math.cos(eps)], dtype=F64))
    assert torch.equal(nominal.forward_kinematics(q)[:3, 2], torch.tensor([0.0, 0.0, 1.0], dtype=F64))


# --------------------------------------------------------------------------------- tree and layouts
@pytest.mark.parametrize("ends", [ALLEGRO_TIPS, ALLEGRO_TIPS[2]])
def test_tree_layouts_and_constant_paths_agree(ends):
    """Batch-last (column) ≡ batch-first (matrix) path; constants (no grad) ≡ tensors (grad), FK and J."""
    chain = from_urdf(DATA / "allegro_right_hand.urdf", ends, dtype=F64)
    q = chain.random_configuration((40,), generator=torch.Generator().manual_seed(0))
    results = {}
    for kernel, small in (("column", -1), ("matrix", 10**9)):
        chain.small_batch = small
        for grad in (False, True):
            with torch.set_grad_enabled(grad):
                T, J = chain.forward_kinematics_and_jacobian(q)
                results[kernel, grad] = (chain.forward_kinematics(q).detach(), T.detach(), J.detach())
    ref = results["matrix", True]
    for key, val in results.items():
        for a, b in zip(val, ref):
            torch.testing.assert_close(a, b, atol=1e-13, rtol=0, msg=str(key))


def test_tree_jacobian_is_masked_by_ancestry_and_matches_finite_differences():
    chain = from_urdf(DATA / "allegro_right_hand.urdf", ALLEGRO_TIPS, dtype=F64)
    q = chain.random_configuration((), generator=torch.Generator().manual_seed(1))
    J = chain.geometric_jacobian(q).detach()
    h = 1e-6
    for i in range(chain.n_joints):
        dq = torch.zeros_like(q)
        dq[i] = h
        Tp, Tm = chain.forward_kinematics(q + dq).detach(), chain.forward_kinematics(q - dq).detach()
        lin = (Tp[..., :3, 3] - Tm[..., :3, 3]) / (2 * h)
        R0 = chain.forward_kinematics(q)[..., :3, :3].detach()
        dR = (Tp[..., :3, :3] - Tm[..., :3, :3]) / (2 * h) @ R0.mT
        ang = torch.stack((dR[..., 2, 1], dR[..., 0, 2], dR[..., 1, 0]), -1)
        torch.testing.assert_close(J[:, :3, i], lin, atol=1e-8, rtol=0)
        torch.testing.assert_close(J[:, 3:, i], ang, atol=1e-8, rtol=0)
    # each finger's 4 joints drive only its own tip
    nonzero = J.abs().sum(-2) > 0  # (K, n)
    assert nonzero.sum(-1).tolist() == [4, 4, 4, 4] and bool((nonzero.sum(0) == 1).all())


def test_topology_rejects_parents_after_children():
    with pytest.raises(ValueError, match="precede"):
        Topology((1, -1), ("R", "R"), (0,), (0, 1), (1.0, 1.0), (0.0, 0.0), 2)


# ---------------------------------------------------------------------------------- parameter Jacobian
@pytest.mark.parametrize("which", ["dh", "urdf"])
def test_parameter_jacobian_matches_finite_differences(which):
    if which == "dh":
        chain = DHChain([0.1, 0.4, 0.0], [math.pi / 2, 0.0, -math.pi / 2], [0.3, 0.0, 0.1], [0.0, 0.2, 0.0],
                        joint_types="RPR", dtype=F64, beta=[0.0, 0.01, 0.0])
    else:
        chain = from_urdf(DATA / "ur10.urdf", "tool0", dtype=F64)
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(2))
    Phi, names = chain.parameter_jacobian(q)
    P = sum(p.numel() for p in chain.parameters())
    assert Phi.shape == (3, 6, P) and len(names) == P
    T0 = chain.forward_kinematics(q).detach()
    h = 1e-6
    flat = [(p, i) for p in chain.parameters() for i in range(p.numel())]
    for col, (p, i) in enumerate(flat):
        with torch.no_grad():
            p.view(-1)[i] += h
            Tp = chain.forward_kinematics(q)
            p.view(-1)[i] -= 2 * h
            Tm = chain.forward_kinematics(q)
            p.view(-1)[i] += h
        lin = (Tp[..., :3, 3] - Tm[..., :3, 3]) / (2 * h)
        W = (Tp[..., :3, :3] - Tm[..., :3, :3]) / (2 * h) @ T0[..., :3, :3].mT
        ang = torch.stack((W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]), -1)
        torch.testing.assert_close(Phi[..., :3, col], lin, atol=1e-7, rtol=0, msg=names[col])
        torch.testing.assert_close(Phi[..., 3:, col], ang, atol=1e-7, rtol=0, msg=names[col])


def test_urdf_geometry_gradcheck_origins_and_axes():
    chain = from_urdf(DATA / "irb2400.urdf", "tool0", dtype=F64)
    q = chain.random_configuration((2,), generator=torch.Generator().manual_seed(3))
    names = [k for k, _ in chain.named_parameters()]
    params = [p.detach().clone().requires_grad_(True) for p in chain.parameters()]
    with torch.no_grad():  # away from the nominal (axis-aligned) values
        params[names.index("axis")].add_(0.05)

    def fk(*values):
        return torch.func.functional_call(chain, dict(zip(names, values)), (q,))

    assert torch.autograd.gradcheck(fk, tuple(params))


def test_base_and_tool_are_learnable_and_rigid():
    chain = DHChain([0.3, 0.2], [0.0, math.pi / 2], [0.1, 0.0], [0.0, 0.0], dtype=F64, learnable=True)
    q = torch.tensor([0.3, -0.4], dtype=F64)
    T = chain.forward_kinematics(q)
    T.sum().backward()
    assert chain.base_delta.grad.abs().sum() > 0 and chain.tool_delta.grad.abs().sum() > 0
    with torch.no_grad():  # a large step keeps both rigid
        chain.base_delta.add_(torch.tensor([1.0, -2.0, 0.5, 2.0, 1.0, -3.0], dtype=F64))
        chain.tool_delta.add_(torch.tensor([0.1, 0.2, 0.3, -1.0, 2.5, 0.4], dtype=F64))
    for M in (chain.base, chain.tool):
        R = M[:3, :3].detach()
        torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=F64), atol=1e-14, rtol=0)
    plain = DHChain([0.3, 0.2], [0.0, math.pi / 2], [0.1, 0.0], [0.0, 0.0], dtype=F64)
    with torch.no_grad():
        want = chain.base @ plain.forward_kinematics(q) @ chain.tool
        torch.testing.assert_close(chain.forward_kinematics(q), want, atol=1e-14, rtol=0)
    chain.requires_grad_(False)
    assert not any(p.requires_grad for p in chain.parameters())


def test_gradient_of_a_zero_base_or_tool_correction_matches_finite_differences():
    """At zero the corrections take a cheap path in grad mode; its gradient must be Δ's exact derivative."""
    chain = DHChain([0.3, 0.2, 0.1], [0.4, math.pi / 2, -0.3], [0.1, 0.0, 0.2], [0.0, 0.5, 0.0], dtype=F64,
                    base=origin_transform(torch.tensor([0.1, 0.2, 0.3], dtype=F64),
                                          torch.tensor([0.3, -0.2, 1.0], dtype=F64)),
                    tool=origin_transform(torch.tensor([0.0, 0.0, 0.1], dtype=F64),
                                          torch.tensor([0.0, 0.5, 0.0], dtype=F64)), learnable=True)
    q = torch.tensor([[0.3, -0.4, 0.8], [1.0, 0.2, -0.5]], dtype=F64)
    w = torch.randn(2, 4, 4, dtype=F64, generator=torch.Generator().manual_seed(0))
    loss = (chain.forward_kinematics(q) * w).sum()
    g_base, g_tool = torch.autograd.grad(loss, (chain.base_delta, chain.tool_delta))
    h = 1e-6
    for delta, g in ((chain.base_delta, g_base), (chain.tool_delta, g_tool)):
        fd = torch.zeros(6, dtype=F64)
        for i in range(6):
            with torch.no_grad():
                delta[i] = h
                up = (chain.forward_kinematics(q) * w).sum()
                delta[i] = -h
                down = (chain.forward_kinematics(q) * w).sum()
                delta[i] = 0.0
            fd[i] = (up - down) / (2 * h)
        torch.testing.assert_close(g, fd, atol=1e-8, rtol=0)


def test_constant_path_follows_buffers_set_after_a_call():
    """Setting a buffer that changes the geometry (a URDF origin correction, a new tool) after a no-grad call
    must not leave the cached constants stale."""
    chain = from_urdf(DATA / "ur10.urdf", "tool0", dtype=F64)
    q = chain.random_configuration((30,), generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        T0 = chain.forward_kinematics(q)
        chain.origin_delta = torch.full((len(chain.joint_origin_names), 6), 1e-3, dtype=F64)
        T1 = chain.forward_kinematics(q)
    T_grad = chain.forward_kinematics(q).detach()  # the tensor path, never cached
    assert float((T1 - T0).abs().max()) > 1e-4
    torch.testing.assert_close(T1, T_grad, atol=1e-14, rtol=0)
    with torch.no_grad():
        chain.tool = origin_transform(torch.tensor([0.0, 0.0, 0.1], dtype=F64), torch.zeros(3, dtype=F64))
        torch.testing.assert_close(chain.forward_kinematics(q), chain.forward_kinematics(q.clone()))
        assert float((chain.forward_kinematics(q) - T1).abs().max()) > 0.05


def test_a_buffer_requiring_grad_keeps_the_graph():
    """A learnable buffer (a calibration's origin correction) must not be read as a constant."""
    chain = from_urdf(DATA / "ur10.urdf", "tool0", dtype=F64).requires_grad_(False)
    delta = torch.zeros(len(chain.joint_origin_names), 6, dtype=F64, requires_grad=True)
    chain.origin_delta = delta
    q = chain.random_configuration((3,), generator=torch.Generator().manual_seed(5))
    T = chain.forward_kinematics(q)
    assert T.requires_grad
    (g,) = torch.autograd.grad(T[..., :3, 3].sum(), delta)
    assert float(g.abs().sum()) > 0
