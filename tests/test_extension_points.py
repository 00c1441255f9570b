"""A new IK task is one subclass, a new collision primitive one pair-table entry: both are defined here, in
the test, and work end to end without touching the library (as ``tests/test_joint_kinds.py`` does for a
joint kind).

References: finite differences of the task's error (its Jacobian), numpy's least squares on that Jacobian
(the step of ``ik.solve_velocity``), the point-to-line distance |(p − c) × u| (numpy), and coal's
box–capsule / box–sphere distances for the rounded box (a box ⊕ a ball of radius ρ: its distance is the
box's minus ρ wherever the two are apart).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import Tensor

from diffkin import ik, models
from diffkin.collision import World
from diffkin.collision import pairs as pair_table
from diffkin.collision.boxes import box_box, box_halfspace, capsule_box
from diffkin.collision.broad import box_spheres
from diffkin.errors import ConventionError, ModelError
from diffkin.ik import _native_velocity
from diffkin.ik.tasks import Problem, Task, _per_axis
from diffkin.validation import check_lower_bound
from tests.helpers import fr3_robot

F64 = torch.float64


# ------------------------------------------------------------------------------------------ a new task
class PointOnLineTask(Task):
    """Keep end link ``frame``'s origin p(q) on the line through ``point`` c along the unit ``direction``
    u: e = (I − u uᵀ)(p − c) ``(..., 3)``, J = (I − u uᵀ) J_v (J_v the translational rows of the geometric
    Jacobian (3.30)). Built from the existing pieces: the problem's end-link poses and Jacobians, the
    per-axis cost rule and the task base's (T.1)."""

    __slots__ = ("frame", "point", "direction", "cost", "gain", "lm_damping")

    def __init__(self, frame, point, direction, *, cost=1.0, gain=1.0, lm_damping=0.0):
        self._set(frame=frame, point=point, direction=direction, cost=cost, gain=gain, lm_damping=lm_damping)

    def cost_vector(self, p: Problem, m: int) -> Tensor:
        return _per_axis(p, self.cost, "PointOnLineTask.cost", 3)

    def _projector(self, p: Problem) -> Tensor:
        u = p.like("PointOnLineTask.direction", self.direction, (3,))
        u = u / u.norm(dim=-1, keepdim=True)
        return torch.eye(3, dtype=u.dtype, device=u.device) - u[..., :, None] * u[..., None, :]

    def error(self, p: Problem) -> Tensor:
        T, _ = p.frames()
        k = p.end_index(self.frame, "PointOnLineTask.frame")
        c = p.like("PointOnLineTask.point", self.point, (3,))
        return (self._projector(p) @ (T[..., k, :3, 3] - c).unsqueeze(-1)).squeeze(-1)

    def jacobian(self, p: Problem) -> Tensor:
        _, J = p.frames()
        k = p.end_index(self.frame, "PointOnLineTask.frame")
        return self._projector(p) @ J[..., k, :3, :]


def _line_distance(chain, q, c, u) -> np.ndarray:
    """|(p − c) × u| with numpy, p the end link's origin."""
    p = chain.forward_kinematics(q)[..., :3, 3].detach().double().numpy()
    u = np.asarray(u) / np.linalg.norm(u)
    return np.linalg.norm(np.cross(p - np.asarray(c), u), axis=-1)


@pytest.fixture(scope="module")
def ur5():
    return models.load("ur5", dtype=F64)


C, U = [0.3, -0.2, 0.4], [0.2, 0.5, 0.8]


def test_a_new_task_is_one_subclass(ur5):
    """The task's Jacobian is the central difference of its error; one solve_velocity step is numpy's damped
    least squares (AᵀA + λI)⁻¹ Aᵀ b, A = WJ, b = −α W e (no limits); the C velocity path leaves it
    to torch; iterated with the joint limits it puts the point on the line (batched; float64, float32)."""
    gen = torch.Generator().manual_seed(3)
    q = ur5.random_configuration((5,), generator=gen)
    task = PointOnLineTask(0, torch.tensor(C, dtype=F64), torch.tensor(U, dtype=F64), cost=[1.0, 2.0, 0.5])
    p = Problem(ur5, q, 0.1)
    e, J = task.error(p), task.jacobian(p)
    h = 1e-6
    fd = torch.stack([(task.error(Problem(ur5, q + h * E, 0.1)) - task.error(Problem(ur5, q - h * E, 0.1)))
                      / (2 * h) for E in torch.eye(ur5.nq, dtype=F64)], dim=-1)
    torch.testing.assert_close(J, fd, rtol=0, atol=1e-7)
    assert _native_velocity.route(ur5, q, [task], 0.1, (), 1e-12) is None  # not a C kind: torch path
    qd = ik.solve_velocity(ur5, q, [task], 0.1, damping=1e-3)
    A, b = np.diag([1.0, 2.0, 0.5]) @ J.numpy(), -np.array([1.0, 2.0, 0.5]) * e.numpy()  # W J, −α W e
    At = A.transpose(0, 2, 1)
    ref = np.linalg.solve(At @ A + 1e-3 * np.eye(ur5.nv), At @ b[..., None])[..., 0] / 0.1
    np.testing.assert_allclose(qd.numpy(), ref, rtol=0, atol=1e-9)
    for dtype, tol in ((F64, 1e-9), (torch.float32, 1e-4)):
        chain = models.load("ur5", dtype=dtype)
        qk = q.to(dtype)
        t = PointOnLineTask(0, torch.tensor(C, dtype=dtype), torch.tensor(U, dtype=dtype))
        post = ik.DampingTask(1e-3)  # a second task in the stack (no error: it damps the step only)
        for _ in range(40):
            qk = chain.integrate(qk, ik.solve_velocity(chain, qk, [t, post], 0.1,
                                                       limits=[ik.ConfigurationLimit()]) * 0.1)
        assert _line_distance(chain, qk, C, U).max() < tol
        assert bool(chain.within_limits(qk).all())


def test_a_new_task_in_ik_optimize(ur5):
    """The same task as a cost term of ik.optimize beside a pose FrameTask with orientation cost 0 (its
    orientation rows dropped): the target position p_t chosen on the line c + s u, the one point where both
    weighted errors vanish is p_t (closed form); the orientation is left free. (A FrameTask's cost weighs
    the rows of log(T_f⁻¹T_t), the frame's own axes: a cost (1, 0, 0) frees the frame's y and z, not the
    base's, so a base-frame closed form is not its answer.)"""
    gen = torch.Generator().manual_seed(5)
    q_t = ur5.random_configuration((5,), generator=gen)
    T_t = ur5.forward_kinematics(q_t)
    u = torch.tensor(U, dtype=F64) / torch.tensor(U, dtype=F64).norm()
    c = T_t[..., :3, 3] - 0.3 * u  # the line through every target position
    line = PointOnLineTask(0, c, u, cost=[1.0, 2.0, 0.5])
    frame = ik.FrameTask(0, target=T_t, orientation_cost=0.0)
    q0 = q_t + 0.15 * torch.randn(q_t.shape, dtype=F64, generator=gen)
    res = ik.optimize(ur5, q0=q0, tasks=[frame, line], optimizer="gauss_newton")
    p = ur5.forward_kinematics(res.q)[..., :3, 3]
    torch.testing.assert_close(p, T_t[..., :3, 3], atol=1e-9, rtol=0)
    assert _line_distance(ur5, res.q, c.numpy(), U).max() < 1e-9
    assert float(res.position_error.max()) < 1e-9
    R = ur5.forward_kinematics(res.q)[..., :3, :3].mT @ T_t[..., :3, :3]
    angle = torch.arccos(((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    assert float(angle.min()) > 1e-2  # not asked for: the cost 0 dropped those rows


# ------------------------------------------------------------------------------------ a new primitive
def _rounded_box_spheres(c, R, h, rho):
    centre, radius = box_spheres(c, h)
    return centre, radius + rho


def _check_rounding(c, R, h, rho):
    check_lower_bound(rho, "rounded box radii", cls=ModelError)


@pytest.fixture
def rounded_box(monkeypatch):
    """A box rounded by a ball of radius ρ (``(c, R, h, ρ)``): one KINDS entry (its dims, bounding sphere and
    world layout) and its PAIRS entries, each an existing box function minus ρ; no C entry."""
    monkeypatch.setitem(pair_table.KINDS, "rounded_box", pair_table.Kind(
        (1, 2, 1, 0), _rounded_box_spheres, trailing=((3,), (3, 3), (3,), ()), check=_check_rounding))
    entries = {
        ("capsule", "rounded_box"): lambda a, b, r, c, R, h, rho: capsule_box(a, b, r, c, R, h) - rho,
        ("rounded_box", "halfspace"): lambda c, R, h, rho, n, d: box_halfspace(c, R, h, n, d) - rho,
        ("box", "rounded_box"): lambda c1, R1, h1, c, R, h, rho: box_box(c1, R1, h1, c, R, h) - rho,
    }
    for key, fn in entries.items():
        monkeypatch.setitem(pair_table.PAIRS, key, pair_table.Pair(fn, pair_table._spheres_bound(*key), None))


def _rotations(n, seed):
    """n rotation matrices (the Q factors of Gaussian matrices, det +1)."""
    Q, _ = torch.linalg.qr(torch.randn(n, 3, 3, dtype=F64, generator=torch.Generator().manual_seed(seed)))
    return Q * torch.linalg.det(Q)[:, None, None]


def test_a_new_primitive_is_one_entry(rounded_box):
    """World objects of the new kind beside built-in ones: the FR3's capsule distances to them are coal's
    capsule–box distances minus ρ (where apart); the clearance decision (C for the built-in objects, torch
    for the new kind) agrees with the distances; the C velocity step leaves the world (and one of cylinders,
    which it does not pack) to torch, which steps with the CollisionLimit; World.stack refuses the kind by
    name, World the kinds without a world layout and radii the kind's own check refuses."""
    import collision_reference as ref

    chain, rc = fr3_robot(F64)
    W = 3
    c = torch.tensor([[0.45, 0.2, 0.5], [0.3, -0.35, 0.25], [0.6, 0.0, 0.9]], dtype=F64)
    R = _rotations(W, 7)
    h = torch.tensor([[0.05, 0.08, 0.03], [0.1, 0.02, 0.06], [0.04, 0.04, 0.12]], dtype=F64)
    rho = torch.tensor([0.02, 0.0, 0.05], dtype=F64)
    world = World(spheres=[[0.2, 0.5, 0.3, 0.05]], halfspaces=[[0.0, 0.0, 1.0, -0.3]],
                  objects={"rounded_box": (c, R, h, rho)}, dtype=F64)
    assert len(world) == 5 and world.object_counts == (3,) and "rounded_box=3" in repr(world)
    q = chain.random_configuration((4,), generator=torch.Generator().manual_seed(5))
    D = rc.world_distances(q, world)  # (4, G, 5): sphere, half-space, then the rounded boxes
    a, b, r = rc.placed(q)[:3]
    geom_of = torch.argsort(rc._rows)[: rc._counts[0]]  # capsule k is geom geom_of[k]
    checked = 0
    for i in range(len(q)):
        for k in range(a.shape[-2]):
            cap = ref.capsule(a[i, k].numpy(), b[i, k].numpy(), float(r[k]))
            for w in range(W):
                want = ref.distance(*cap, *ref.box(c[w].numpy(), R[w].numpy(), h[w].numpy())) - float(rho[w])
                got = float(D[i, geom_of[k], 2 + w])
                if want > float(rho[w]):  # apart (coal's EPA depth is not what is checked here)
                    assert abs(got - want) < 1e-7, (i, k, w, got, want)
                    checked += 1
    assert checked > 50
    for margin in (0.0, 0.05, 0.2):
        want_ok = ((rc._distances_at_least(q, world, margin) - margin) >= 0).all(-1)
        assert torch.equal(rc._clear(q, world, margin), want_ok)
        assert torch.equal(rc._clear(q, world, margin), (rc.min_distance(q, world) >= margin))
    # one world per row (batch dims on the new kind's objects): each row's distances are its own world's
    shift = torch.tensor([[[0.0, 0.0, 0.0]], [[0.1, 0.0, 0.0]]], dtype=F64)
    per_row = World(objects={"rounded_box": (c + shift, R, h, rho.expand(2, W))}, dtype=F64)
    Dr = rc.world_distances(q[:2], per_row)
    for i in range(2):
        one = World(objects={"rounded_box": tuple(t[i] for t in per_row.objects["rounded_box"][:1])
                             + (R, h, rho)}, dtype=F64)
        torch.testing.assert_close(Dr[i], rc.world_distances(q[i], one), rtol=0, atol=1e-12)
    assert torch.equal(rc._clear(q[:2], per_row, 0.05), (rc.min_distance(q[:2], per_row) >= 0.05))
    limit = ik.CollisionLimit(rc, world, minimum_distance=0.01, gain=0.5)
    task = ik.FrameTask(0, target=chain.forward_kinematics(q)[0].clone())
    assert _native_velocity.route(chain, q[0], [task], 0.05, [limit], 1e-12) is None
    cyl = World(cylinders=[[0.4, 0.0, 0.2, 0.4, 0.0, 0.6, 0.05]], dtype=F64)  # the C step packs no cylinders
    assert _native_velocity.route(chain, q[0], [task], 0.05, [ik.CollisionLimit(rc, cyl)], 1e-12) is None
    qd = ik.solve_velocity(chain, q[0], [task], 0.05, limits=[limit])
    assert bool(torch.isfinite(qd).all())
    # the motion optimisation's detached copy of the world keeps the new kind (it unpacked 8 built-in tensors)
    from diffkin.motion.optimize import _detached

    grad_world = World(objects={"rounded_box": (c.clone().requires_grad_(True), R, h, rho)}, dtype=F64)
    copy = _detached(grad_world, torch.float32)
    assert list(copy.objects) == ["rounded_box"] and copy.dtype == torch.float32
    for got, want in zip(copy.objects["rounded_box"], grad_world.objects["rounded_box"]):
        assert not got.requires_grad and torch.equal(got, want.detach().float())
    with pytest.raises(ConventionError, match="rounded_box"):
        World.stack([world, world])
    with pytest.raises(ConventionError, match="world layout"):
        World(objects={"box": (c, R, h)})
    with pytest.raises(ModelError, match="rounded box radii"):
        World(objects={"rounded_box": (c, R, h, -rho - 0.1)})
