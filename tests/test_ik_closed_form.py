"""Closed-form IK (§2.12): every branch reproduces the target, the true configuration is among them,
unreachable targets are flagged with finite values, and chains without a closed form are refused."""

from __future__ import annotations

import math

import pytest
import torch

from diffkin import models
from diffkin.chain import DHChain
from diffkin.errors import DTypeError, ModelError, ShapeError
from diffkin.ik.analytic import CLOSED_FORM_STRUCTURES, closed_form, identify_structure

PI = math.pi
F64 = torch.float64
# the book's structures with other numbers than the bundled models: lengths, d_1, joint offsets
TABLES = {
    "three_link_planar": ([0.6, 0.45, 0.2], [0, 0, 0], [0.1, 0.1, 0.0], [0.2, -0.1, 0.3], "RRR"),
    "spherical_arm": ([0, 0, 0], [-PI / 2, PI / 2, 0], [0.3, 0.2, 0.05], [0.1, -0.2, 0.4], "RRP"),
    "anthropomorphic_arm": ([0, 0.7, 0.55], [PI / 2, 0, 0], [0.35, 0, 0], [0.3, -0.2, 0.1], "RRR"),
    "spherical_wrist": ([0, 0, 0], [-PI / 2, PI / 2, 0], [0.05, 0, 0.12], [0.2, 0.1, -0.3], "RRR"),
    "stanford": (
        [0] * 6,
        [-PI / 2, PI / 2, 0, -PI / 2, PI / 2, 0],
        [0.4, 0.15, 0.1, 0.05, 0, 0.12],
        [0.1, 0, 0.2, 0, 0.3, 0],
        "RRPRRR",
    ),
    "anthropomorphic_wrist": (
        [0, 0.6, 0, 0, 0, 0],
        [PI / 2, 0, PI / 2, -PI / 2, PI / 2, 0],
        [0.3, 0, 0, 0.55, 0, 0.15],
        [0.1, -0.2, 0.3, 0.1, 0.0, -0.4],
        "RRRRRR",
    ),
}
BRANCHES = {"three_link_planar": 2, "spherical_arm": 2, "anthropomorphic_arm": 4, "spherical_wrist": 2,
            "stanford": 4, "anthropomorphic_wrist": 8}  # fmt: skip
POSITION_ONLY = ("spherical_arm", "anthropomorphic_arm")


def _rigid(g: torch.Generator) -> torch.Tensor:
    Q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64))
    Q = Q * torch.sign(torch.linalg.det(Q))
    T = torch.eye(4, dtype=F64)
    T[:3, :3], T[:3, 3] = Q, 0.3 * torch.randn(3, generator=g, dtype=F64)
    return T


def _chain(name: str, base_tool: bool = False, seed: int = 0) -> DHChain:
    a, alpha, d, theta, types = TABLES[name]
    g = torch.Generator().manual_seed(seed)
    base = _rigid(g) if base_tool else None
    tool = _rigid(g) if base_tool and name not in POSITION_ONLY else None
    t = lambda x: torch.tensor(x, dtype=F64)  # noqa: E731
    return DHChain(t(a), t(alpha), t(d), t(theta), joint_types=types, base=base, tool=tool, name=f"my_{name}")


def _random_q(chain: DHChain, shape, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = (torch.rand(*shape, chain.n_joints, generator=g, dtype=F64) * 2 - 1) * PI
    if "P" in chain.joint_types:  # the book keeps d3 >= 0
        q[..., 2] = 0.1 + q[..., 2].abs() / PI
    return q


def _pose_residual(chain, name, q, T):
    Tq = chain.forward_kinematics(q)
    if name in POSITION_ONLY:
        return (Tq[..., :3, 3] - T[..., None, :3, 3]).norm(dim=-1)
    return (Tq - T[..., None, :, :]).flatten(-2).norm(dim=-1)


def _contains(chain, sol_q, q, tol: float = 1e-7) -> torch.Tensor:
    """True where q (mod 2π for revolute joints) is one of the branches."""
    dq = sol_q - q[..., None, :]
    wrapped = torch.atan2(torch.sin(dq), torch.cos(dq))
    dq = torch.where(chain.revolute_mask.bool(), wrapped, dq)
    return (dq.abs().amax(-1) < tol).any(-1)


@pytest.mark.parametrize("base_tool", [False, True])
@pytest.mark.parametrize("name", list(TABLES))
def test_branches_reproduce_target_and_contain_true_q(name, base_tool):
    chain = _chain(name, base_tool)
    q = _random_q(chain, (4, 25))
    T = chain.forward_kinematics(q)
    sol = closed_form(chain, T)
    k = BRANCHES[name]
    assert sol.q.shape == (4, 25, k, chain.n_joints) and sol.success.shape == (4, 25, k)
    assert sol.success.dtype == torch.bool and torch.isfinite(sol.q).all()
    res = _pose_residual(chain, name, sol.q, T)
    assert (res[sol.success] < 1e-9).all()
    assert sol.success.float().mean() > 0.99  # generic targets: every branch exists
    assert _contains(chain, sol.q, q).all()


@pytest.mark.parametrize("name", list(TABLES))
def test_bundled_models_are_recognised_and_solved(name):
    chain = models.load(name, dtype=F64)
    assert identify_structure(chain) == name
    q = chain.random_configuration((30,), generator=torch.Generator().manual_seed(3))
    T = chain.forward_kinematics(q)
    sol = closed_form(chain, T)
    assert (_pose_residual(chain, name, sol.q, T)[sol.success] < 1e-9).all()
    assert _contains(chain, sol.q, q).all()


def test_generic_targets_give_distinct_branches():
    """Four anthropomorphic-arm postures (Fig. 2.33) and eight with the spherical wrist."""
    for name, k in (("anthropomorphic_arm", 4), ("anthropomorphic_wrist", 8)):
        chain = _chain(name)
        sol = closed_form(chain, chain.forward_kinematics(_random_q(chain, (10,))))
        assert sol.success.all()
        d = (sol.q[:, :, None] - sol.q[:, None, :]).abs().amax(-1) + torch.eye(k, dtype=F64) * 10
        assert (d > 1e-3).all()


def test_book_branch_formulas():
    """Three-link planar (2.90)–(2.92): s2 >= 0 is elbow down; anthropomorphic order (2.110); spherical arm:
    the two roots of the book's half-angle formula ϑ1 = 2 Atan2(−p_x ± √(p_x² + p_y² − d_2²), d_2 + p_y)."""
    chain = _chain("anthropomorphic_arm")
    sol = closed_form(chain, chain.forward_kinematics(_random_q(chain, (20,))))
    th = sol.q + chain.theta
    s3 = torch.sin(th[..., 2])
    assert (s3[:, 0] >= 0).all() and (s3[:, 1] <= 0).all() and (s3[:, 2] >= 0).all() and (s3[:, 3] <= 0).all()
    dth1 = torch.remainder(th[:, 2, 0] - th[:, 0, 0], 2 * PI)
    assert torch.allclose(dth1, torch.full_like(dth1, PI), atol=1e-9)  # ϑ1,II = ϑ1,I ± π

    planar = _chain("three_link_planar")
    sol = closed_form(planar, planar.forward_kinematics(_random_q(planar, (20,))))
    s2 = torch.sin(sol.q[..., 1] + planar.theta[1])
    assert (s2[:, 0] >= 0).all() and (s2[:, 1] <= 0).all()

    arm = _chain("spherical_arm")
    T = arm.forward_kinematics(_random_q(arm, (20,)))
    sol = closed_form(arm, T)
    p = T[:, :3, 3] - torch.tensor([0, 0, arm.d[0].item()], dtype=F64)
    d2 = arm.d[1].detach()
    root = torch.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 - d2**2)
    book = torch.stack([2 * torch.atan2(-p[:, 0] + s * root, d2 + p[:, 1]) for s in (1, -1)], -1)
    ours = sol.q[..., 0] + arm.theta[0]
    diff = torch.remainder(ours[:, :, None] - book[:, None, :] + PI, 2 * PI) - PI
    assert (diff.abs().amin(-1) < 1e-9).all()


def test_unreachable_targets_are_flagged_finite():
    arm = _chain("anthropomorphic_arm")
    far = torch.tensor([[3.0, 0.5, 1.0], [0.0, 0.0, 5.0]], dtype=F64)
    sol = closed_form(arm, far)
    assert not sol.success.any() and torch.isfinite(sol.q).all()

    planar = _chain("three_link_planar")
    sol = closed_form(planar, torch.tensor([5.0, 0.0, 0.3], dtype=F64))
    assert not sol.success.any() and torch.isfinite(sol.q).all()
    T = planar.forward_kinematics(torch.tensor([0.3, 0.4, 0.5], dtype=F64))
    T_tilted = T.clone()
    T_tilted[:3, :3] = T[:3, :3] @ torch.tensor([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=F64)
    assert not closed_form(planar, T_tilted).success.any()  # not a planar pose

    six = _chain("anthropomorphic_wrist")
    T = torch.eye(4, dtype=F64)
    T[:3, 3] = torch.tensor([4.0, 0.0, 0.0], dtype=F64)
    sol = closed_form(six, T)
    assert not sol.success.any() and torch.isfinite(sol.q).all()

    wrist = _chain("spherical_wrist")
    T = wrist.forward_kinematics(torch.tensor([0.3, 0.4, 0.5], dtype=F64))
    T[:3, 3] += 0.5  # the wrist cannot move its centre
    assert not closed_form(wrist, T).success.any()


def test_singular_targets_are_finite_and_valid():
    wrist = _chain("spherical_wrist")
    for q5 in (0.0, PI):  # ϑ5 = 0, π: only ϑ4 ± ϑ6 determined
        q = torch.tensor([0.4, q5 - wrist.theta[1].item(), -0.2], dtype=F64)
        T = wrist.forward_kinematics(q)
        sol = closed_form(wrist, T)
        assert torch.isfinite(sol.q).all() and sol.success.all()
        assert (_pose_residual(wrist, "spherical_wrist", sol.q, T) < 1e-9).all()
    arm = _chain("anthropomorphic_arm")
    p = torch.tensor([0.0, 0.0, 0.9], dtype=F64, requires_grad=True)  # on the z0 axis (shoulder singularity)
    sol = closed_form(arm, p)
    assert torch.isfinite(sol.q).all() and sol.success.all()
    (g,) = torch.autograd.grad(sol.q.sum(), p)
    assert torch.isfinite(g).all()


def test_gradcheck_generic_target():
    planar = _chain("three_link_planar")
    x = torch.tensor([0.5, 0.6, 0.3], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: closed_form(planar, x).q, (x,))
    six = _chain("anthropomorphic_wrist")
    T0 = six.forward_kinematics(_random_q(six, ()))
    w = torch.zeros(3, dtype=F64, requires_grad=True)

    def solve_rotated(w):
        S = torch.zeros(3, 3, dtype=F64)
        S = S + torch.stack([torch.stack([0 * w[0], -w[2], w[1]]), torch.stack([w[2], 0 * w[0], -w[0]]),
                             torch.stack([-w[1], w[0], 0 * w[0]])])  # fmt: skip
        T = T0.clone()
        T = torch.cat((torch.cat((torch.matrix_exp(S) @ T0[:3, :3], T0[:3, 3:]), -1), T0[3:]), -2)
        return closed_form(six, T).q

    assert torch.autograd.gradcheck(solve_rotated, (w,))


def test_reduced_targets_with_base_and_tool():
    """(p_x, p_y, φ) of a planar arm whose base turns about z and whose tool is offset; wrist rotations."""
    a, alpha, d, theta, types = TABLES["three_link_planar"]
    base = torch.eye(4, dtype=F64)
    c, s = math.cos(0.7), math.sin(0.7)
    base[:2, :2] = torch.tensor([[c, -s], [s, c]], dtype=F64)
    base[:3, 3] = torch.tensor([0.2, -0.1, 0.3], dtype=F64)
    tool = torch.eye(4, dtype=F64)
    tool[:3, 3] = torch.tensor([0.1, 0.05, 0.0], dtype=F64)
    t = lambda x: torch.tensor(x, dtype=F64)  # noqa: E731
    chain = DHChain(t(a), t(alpha), t(d), t(theta), joint_types=types, base=base, tool=tool)
    q = _random_q(chain, (16,))
    T = chain.forward_kinematics(q)
    phi = q.sum(-1) + chain.theta.sum() + 0.7  # angle of x_3 in the world
    x = torch.stack([T[:, 0, 3], T[:, 1, 3], phi], -1)
    sol = closed_form(chain, x)
    assert sol.success.all() and _contains(chain, sol.q, q).all()

    wrist = _chain("spherical_wrist", base_tool=True)
    q = _random_q(wrist, (16,))
    sol = closed_form(wrist, wrist.forward_kinematics(q)[..., :3, :3])
    assert sol.success.all() and _contains(wrist, sol.q, q).all()


def test_scalar_batch_and_float32():
    chain = models.load("anthropomorphic_wrist", dtype=torch.float32)
    q = torch.tensor([0.3, -0.4, 0.5, 0.2, 0.6, -0.1])
    sol = closed_form(chain, chain.forward_kinematics(q))
    assert sol.q.shape == (8, 6) and sol.success.shape == (8,) and sol.q.dtype == torch.float32
    assert sol.success.all()
    assert _contains(chain, sol.q, q, tol=1e-4)


def test_unsupported_chains_and_bad_input():
    for name in ("panda", "kuka_iiwa14", "dlr"):  # ur5: ur family, see *_industrial.py
        with pytest.raises(ModelError, match="closed-form"):
            closed_form(models.load(name, dtype=F64), torch.eye(4, dtype=F64))
    two_link = DHChain([1.0, 1.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0])
    with pytest.raises(ModelError):
        identify_structure(two_link)
    bent = _chain("anthropomorphic_arm")
    shoulder_offset = DHChain(bent.a.detach(), bent.alpha.detach(), torch.tensor([0.3, 0.1, 0.0], dtype=F64),
                              bent.theta.detach())  # fmt: skip
    with pytest.raises(ModelError):
        identify_structure(shoulder_offset)
    six = _chain("anthropomorphic_wrist")
    with pytest.raises(ShapeError):
        closed_form(six, torch.zeros(3, dtype=F64))
    with pytest.raises(DTypeError):
        closed_form(six, torch.eye(4, dtype=torch.float32))
    arm = _chain("anthropomorphic_arm")
    tool = torch.eye(4, dtype=F64)
    tool[0, 3] = 0.1
    with_tool = DHChain(arm.a.detach(), arm.alpha.detach(), arm.d.detach(), arm.theta.detach(), tool=tool)
    with pytest.raises(ModelError, match="tool"):
        closed_form(with_tool, torch.tensor([0.5, 0.2, 0.3], dtype=F64))
    assert set(CLOSED_FORM_STRUCTURES) == set(TABLES) | {"ur", "opw"}
