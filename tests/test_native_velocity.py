"""The C differential-IK step (diffkin/kernels/_native_velocity.c, diffkin/ik/_native_velocity.py) against
mink's solve_ik with daqp on the vendored Menagerie Panda and G1: the same tasks and limits must give the
same velocity (mink's SE(3) error and log Jacobian, its posture task on the manifold, its configuration
and velocity limits)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

mink = pytest.importorskip("mink")
pytest.importorskip("daqp")
mujoco = pytest.importorskip("mujoco")

from diffkin.errors import NonFiniteError  # noqa: E402
from diffkin.ik import _native_velocity as nvel  # noqa: E402
from diffkin.kernels import cache, native  # noqa: E402
from diffkin.models import from_mjcf  # noqa: E402
from diffkin.models.mjcf import compile_mjcf  # noqa: E402

pytestmark = pytest.mark.skipif(not nvel.available(), reason="no C compiler: the fused kernel is not built")

PANDA = "tests/data/mjcf/franka_emika_panda/panda.xml"
G1 = "tests/data/mjcf/unitree_g1/g1.xml"
G1_ENDS = [("left_foot", "site"), ("right_foot", "site"), ("left_elbow_roll_link", "body"),
           ("right_elbow_roll_link", "body")]


@pytest.fixture(scope="module")
def panda():
    chain = from_mjcf(PANDA, "hand", dtype=torch.float64).requires_grad_(False)
    model = compile_mjcf(PANDA)[0]
    return chain, model


def _panda_case(rng, model, trial):
    lo, hi = model.jnt_range[:7].T
    q = np.zeros(model.nq)
    q[:7] = rng.uniform(lo, hi)
    if trial % 3 == 0:  # one joint next to its upper limit: the configuration limit binds
        q[3] = hi[3] - 1e-4
    qref = np.zeros(model.nq)
    qref[:7] = rng.uniform(lo, hi)
    scale = (0.3, 1e-6, 1e-7)[trial % 3]  # large errors, and rotations below mink's 1e-5 rad switch
    d = rng.normal(size=6) * scale
    if trial % 4 == 0:
        d[:3] = rng.normal(size=3) * 0.2  # a translation with a tiny rotation: jlog is the identity there
    return q, qref, d


def test_panda_batch_matches_mink(panda):
    chain, model = panda
    cfg = mink.Configuration(model)
    frame = mink.FrameTask("hand", "body", position_cost=[1.0, 2.0, 0.5], orientation_cost=0.5, gain=0.8,
                           lm_damping=0.1)
    posture = mink.PostureTask(model, cost=1e-2, gain=0.5)
    names = [model.joint(i).name for i in range(model.njnt)]
    limits = [mink.ConfigurationLimit(model, gain=0.95, min_distance_from_limits=0.01),
              mink.VelocityLimit(model, {n: 2.0 for n in names})]
    prob = nvel.NativeVelocity(chain, [(0, [1.0, 2.0, 0.5], 0.5, 0.8, 0.1)], posture=(1e-2, 0.5, 0.0),
                               configuration_limit=(0.95, 0.01), velocity_limit=2.0, damping=1e-12)
    rng = np.random.default_rng(0)
    qs, refs, targets, expected = [], [], [], []
    dt = 0.01
    for trial in range(60):
        q, qref, d = _panda_case(rng, model, trial)
        cfg.update(q)
        target = cfg.get_transform_frame_to_world("hand", "body") @ mink.SE3.exp(d)
        frame.set_target(target)
        posture.set_target(qref)
        expected.append(mink.solve_ik(cfg, [frame, posture], dt, "daqp", damping=1e-12, limits=limits)[:7])
        qs.append(q[:7])
        refs.append(qref[:7])
        targets.append(target.as_matrix()[None])
    v, ok = prob.solve(torch.tensor(np.array(qs)), torch.tensor(np.array(targets)),
                       torch.tensor(np.array(refs)), dt)
    expected = np.array(expected)
    assert bool(ok.all())
    np.testing.assert_allclose(v.numpy(), expected, rtol=0, atol=1e-9)
    # the rows exercise the box: velocity bounds active in most rows, the position bound in some
    assert (np.abs(np.abs(expected) - 2.0) < 1e-9).any(axis=1).mean() > 0.5


def test_lean_step_equals_batch_and_integrates(panda):
    chain, _ = panda
    prob = nvel.NativeVelocity(chain, [(0, 1.0, 1.0, 1.0, 0.0)], posture=(1e-2, 1.0, 0.0),
                               configuration_limit=(0.95, 0.0), velocity_limit=2.5)
    g = torch.Generator().manual_seed(3)
    q = chain.random_configuration((), generator=g)
    q_ref = chain.random_configuration((), generator=g)
    T = chain.forward_kinematics(chain.random_configuration((), generator=g))
    target = T[None].contiguous()
    next_q = torch.empty_like(q)
    for _ in range(3):  # the kept work space is reused from the second call on
        v = prob.step(q, target, q_ref, 0.002, next_q=next_q)
    assert v is not None and prob.ok
    vb, ok = prob.solve(q[None], target, q_ref, 0.002)
    torch.testing.assert_close(v, vb[0], rtol=0, atol=1e-14)
    torch.testing.assert_close(next_q, chain.integrate(q, v * 0.002), rtol=0, atol=1e-15)


def test_lean_step_follows_chain_writes(panda):
    chain, _ = panda
    chain = chain.copy().requires_grad_(False)
    prob = nvel.NativeVelocity(chain, [(0, 1.0, 1.0, 1.0, 0.0)], posture=(1e-3, 1.0, 0.0))
    q = torch.tensor([0.1, -0.4, 0.2, -2.0, 0.1, 1.4, 0.6], dtype=torch.float64)
    target = chain.forward_kinematics(q + 0.05)[None].contiguous()
    v0 = prob.step(q, target, q, 0.01).clone()
    with torch.no_grad():
        chain.base_delta.data.add_(torch.tensor([0.01, 0, 0, 0, 0, 0.02], dtype=torch.float64))
    v1 = prob.step(q, target, q, 0.01)
    vb, _ = prob.solve(q[None], target, q, 0.01)
    assert (v1 - v0).abs().max() > 1e-3  # the moved base changed the answer
    torch.testing.assert_close(v1, vb[0], rtol=0, atol=1e-13)


def test_limits_hold_and_infeasible_rows(panda):
    chain, model = panda
    lo, hi = chain.q_limits[:, 0], chain.q_limits[:, 1]
    vmax = torch.linspace(1.0, 2.5, 7, dtype=torch.float64)
    prob = nvel.NativeVelocity(chain, [(0, 1.0, 1.0, 1.0, 0.0)], posture=(1.0, 1.0, 0.0),
                               configuration_limit=(0.95, 0.0), velocity_limit=vmax)
    g = torch.Generator().manual_seed(5)
    B, dt = 256, 0.01
    q = chain.random_configuration(B, generator=g)
    q[:, 1] = hi[1] - 1e-5  # pushed towards the limit by a posture beyond it
    q_ref = chain.random_configuration(B, generator=g)
    q_ref[:, 1] = hi[1] + 1.0
    T = chain.forward_kinematics(chain.random_configuration(B, generator=g))[:, None]
    v, q_next, ok = prob.solve(q, T, q_ref, dt, next_q=True)
    assert bool(ok.all())
    assert bool((v.abs() <= vmax * (1 + 1e-12)).all())
    assert bool((q_next <= hi + 1e-12).all()) and bool((q_next >= lo - 1e-12).all())
    # beyond the upper limit by more than one step at the velocity limit: mink's QP has no solution; the row
    # moves back at the velocity limit and says so
    q_out = q[:4].clone()
    q_out[:, 2] = hi[2] + 0.5
    v, ok = prob.solve(q_out, T[:4], q_ref[:4], dt)
    assert not bool(ok.any())
    torch.testing.assert_close(v[:, 2], -vmax[2].expand(4), rtol=0, atol=1e-12)


def test_float32_close_to_float64(panda):
    chain, _ = panda
    c32 = chain.copy().to(torch.float32).requires_grad_(False)
    args = ([(0, 1.0, 1.0, 1.0, 0.0)],)
    kw = dict(posture=(1e-2, 1.0, 0.0), configuration_limit=(0.95, 0.0), velocity_limit=2.0)
    p64, p32 = nvel.NativeVelocity(chain, *args, **kw), nvel.NativeVelocity(c32, *args, **kw)
    g = torch.Generator().manual_seed(7)
    q = chain.random_configuration(64, generator=g)
    T = chain.forward_kinematics(q + 0.02 * torch.randn(q.shape, generator=g, dtype=q.dtype))[:, None]
    v64, _ = p64.solve(q, T, q, 0.01)
    v32, ok = p32.solve(q.float(), T.float(), q.float(), 0.01)
    assert v32.dtype is torch.float32 and bool(ok.all())
    torch.testing.assert_close(v32.double(), v64, rtol=0, atol=2e-3)


def test_g1_floating_base_matches_mink():
    chain = from_mjcf(G1, [e for e, _ in G1_ENDS], dtype=torch.float64).requires_grad_(False)
    model = compile_mjcf(G1)[0]
    qadr, dofs = chain.qpos_index(), chain.dof_index()  # MuJoCo's qpos / qvel entries of q and v
    cfg = mink.Configuration(model)
    costs = [(1.0, 1.0), (1.0, 1.0), (2.0, 0.5), (2.0, 0.5)]
    tasks = [mink.FrameTask(e, t, position_cost=p, orientation_cost=o, gain=1.0, lm_damping=1.0)
             for (e, t), (p, o) in zip(G1_ENDS, costs)]
    posture = mink.PostureTask(model, cost=1e-1, gain=1.0)
    hinges = [model.joint(i).name for i in range(model.njnt) if model.jnt_type[i] != 0]
    limits = [mink.ConfigurationLimit(model, gain=0.95), mink.VelocityLimit(model, {n: 3.0 for n in hinges})]
    vmax = torch.full((chain.nv,), 3.0, dtype=torch.float64)
    vmax[:6] = math.inf  # the floating base: no velocity limit (mink's VelocityLimit takes none either)
    prob = nvel.NativeVelocity(chain, [(k, p, o, 1.0, 1.0) for k, (p, o) in enumerate(costs)],
                               posture=(1e-1, 1.0, 0.0), configuration_limit=(0.95, 0.0), velocity_limit=vmax)
    rng = np.random.default_rng(1)
    rng_lim = model.jnt_range[1:]
    dt = 0.01
    for _ in range(8):
        q = model.qpos0.copy()
        q[:3] += rng.normal(size=3) * 0.1
        quat = rng.normal(size=4)
        q[3:7] = quat / np.linalg.norm(quat)
        q[7:] = rng.uniform(rng_lim[:, 0], rng_lim[:, 1]) * 0.5
        q_ref = q.copy()
        q_ref[7:] = rng.uniform(rng_lim[:, 0], rng_lim[:, 1]) * 0.5
        cfg.update(q)
        targets = []
        for task, (e, t) in zip(tasks, G1_ENDS):
            target = cfg.get_transform_frame_to_world(e, t) @ mink.SE3.exp(rng.normal(size=6) * 0.05)
            task.set_target(target)
            targets.append(target.as_matrix())
        posture.set_target(q_ref)
        expected = mink.solve_ik(cfg, [*tasks, posture], dt, "daqp", damping=1e-12, limits=limits)[dofs]
        v, ok = prob.solve(torch.tensor(q[qadr])[None], torch.tensor(np.array(targets))[None],
                           torch.tensor(q_ref[qadr]), dt)
        assert bool(ok.all())
        np.testing.assert_allclose(v[0].numpy(), expected, rtol=0, atol=1e-9)


def test_struct_mirrors_library():
    """native.check_layout refuses a dk_vel whose fields, offsets or version differ from Vel's."""
    native.check_layout(native._lib, "vel", nvel.Vel)
    with pytest.raises(native.AbiMismatch, match="vel struct does not match Vel: version"):
        native.check_layout(native._lib, "vel", nvel.Vel, nvel.VERSION + 1)


# ------------------------------------------------------------------ ik.solve_velocity: the C route vs torch
from diffkin import ik  # noqa: E402


def _problems(chain) -> dict:
    """The C route's problems, kept on the chain's Data (diffkin/kernels/cache.py)."""
    data = chain.__dict__.get(cache.KEY)
    return {} if data is None else data.extra.get("velocity", {})


def _both(chain, q, tasks, dt, limits, damping=1e-12):
    """solve_velocity by the C route and by the torch path (native kernels disabled)."""
    n = len(_problems(chain))
    fast = ik.solve_velocity(chain, q, tasks, dt, limits=limits, damping=damping)
    assert len(_problems(chain)) >= max(n, 1)  # the C route served it
    with native.disabled():
        slow = ik.solve_velocity(chain, q, tasks, dt, limits=limits, damping=damping)
    return fast, slow


def test_solve_velocity_routes_to_c_and_equals_torch_panda(panda):
    chain, _ = panda
    g = torch.Generator().manual_seed(11)
    q = chain.random_configuration(48, generator=g)
    T = chain.forward_kinematics(q + 0.05 * torch.randn(q.shape, generator=g, dtype=q.dtype))
    q_ref = chain.random_configuration((), generator=g)
    tasks = [ik.FrameTask("hand", target=T, position_cost=[1.0, 2.0, 0.5], orientation_cost=0.5, gain=0.8,
                          lm_damping=0.1), ik.PostureTask(q_ref, cost=1e-2, gain=0.5)]
    limits = [ik.ConfigurationLimit(gain=0.95, min_distance_from_limits=0.01), ik.VelocityLimit(2.0)]
    fast, slow = _both(chain, q, tasks, 0.01, limits)
    torch.testing.assert_close(fast, slow, rtol=0, atol=1e-9)
    # one row (the lean path), a target (4, 4), velocity limits by joint name
    one = [ik.FrameTask(0, target=T[3]), ik.PostureTask(q_ref, cost=0.1)]
    lim = [ik.ConfigurationLimit(), ik.VelocityLimit({f"joint{i}": 1.0 + 0.1 * i for i in range(1, 8)})]
    fast, slow = _both(chain, q[3], one, 0.002, lim, damping=1e-6)
    assert fast.shape == (7,)
    torch.testing.assert_close(fast, slow, rtol=0, atol=1e-9)


def test_solve_velocity_routes_to_c_and_equals_torch_g1():
    """The floating base. (Below mink's 1e-5 rad switch, a translation error with no rotation error, the
    torch path's exact log Jacobian and the C path's mink identity differ by O(|v|): the C path follows mink
    there, test_panda_batch_matches_mink.)"""
    chain = from_mjcf(G1, [e for e, _ in G1_ENDS], dtype=torch.float64).requires_grad_(False)
    g = torch.Generator().manual_seed(2)
    q = chain.neutral_configuration().expand(6, -1).clone()
    q[:, 7:] = 0.3 * torch.randn(6, chain.nq - 7, generator=g, dtype=torch.float64)
    q = chain.clamp_to_limits(q)
    q[:, 3:7] = torch.nn.functional.normalize(torch.randn(6, 4, generator=g, dtype=torch.float64), dim=-1)
    T = chain.forward_kinematics(q)
    T[..., 2:, :3, 3] += 0.03
    c, s = math.cos(0.05), math.sin(0.05)  # hands turned too: a rotation error above mink's 1e-5 rad switch
    turn = torch.tensor([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.float64)
    T[..., 2:, :, :] = T[..., 2:, :, :] @ turn
    tasks = [ik.FrameTask(k, target=T[:, k], lm_damping=1.0) for k in range(4)]
    tasks.append(ik.PostureTask(chain.neutral_configuration(), cost=0.1))
    vmax = {name: 3.0 for name, kind in zip(chain.joint_names, chain.joint_kinds) if kind != "free"}
    fast, slow = _both(chain, q, tasks, 0.01, [ik.ConfigurationLimit(), ik.VelocityLimit(vmax)])
    torch.testing.assert_close(fast, slow, rtol=0, atol=1e-9)


def test_solve_velocity_keeps_the_torch_path_outside_the_subset(panda):
    chain, _ = panda
    q = torch.tensor([0.1, -0.4, 0.2, -2.0, 0.1, 1.4, 0.6], dtype=torch.float64)
    T = chain.forward_kinematics(q + 0.02).clone().requires_grad_(True)
    v = ik.solve_velocity(chain, q, [ik.FrameTask(0, target=T)], 0.01, limits=[ik.VelocityLimit(1.0)])
    assert v.grad_fn is not None  # a gradient wanted: the torch path (KKT gradients)
    v.sum().backward()
    assert T.grad is not None and bool(torch.isfinite(T.grad).all())
    twist = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.2], dtype=torch.float64)
    with torch.no_grad():
        v = ik.solve_velocity(chain, q, [ik.FrameTask(0, twist=twist)], 0.01)
    assert v.shape == (7,)  # twists: the torch path
    with pytest.raises(NonFiniteError, match="q contains NaN"):  # the torch path's own error for a bad q
        ik.solve_velocity(chain, torch.full((7,), float("nan"), dtype=torch.float64),
                          [ik.FrameTask(0, target=T.detach())], 0.01)


def test_lean_step_from_threads(panda):
    """Calls of one problem from several threads get their own rows (the call struct is copied in C and the
    kept work space is used by one call at a time)."""
    import threading

    chain, _ = panda
    prob = nvel.NativeVelocity(chain, [(0, 1.0, 1.0, 1.0, 0.0)], posture=(1e-2, 1.0, 0.0), velocity_limit=2.0)
    g = torch.Generator().manual_seed(9)
    qs = chain.random_configuration(4, generator=g)
    T = chain.forward_kinematics(chain.random_configuration(4, generator=g))[:, None].contiguous()
    expected, _ = prob.solve(qs, T, qs, 0.01)
    bad = []

    def work(i):
        for _ in range(200):
            v = prob.step(qs[i], T[i], qs[i], 0.01)
            if v is None or not torch.equal(v, expected[i]):
                bad.append(i)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not bad


def test_one_row_non_finite_target_or_posture(panda):
    """A NaN / inf target or q_ref of one row: the C step computes nothing (None) and solve_velocity's torch
    path names the bad input; finite inputs are served."""
    chain, _ = panda
    prob = nvel.NativeVelocity(chain, [(0, 1.0, 1.0, 1.0, 0.0)], posture=(1e-2, 1.0, 0.0), velocity_limit=2.0)
    q = torch.tensor([0.1, -0.4, 0.2, -2.0, 0.1, 1.4, 0.6], dtype=torch.float64)
    T = chain.forward_kinematics(q + 0.05).detach()
    bad_T, bad_q = T.clone(), q.clone()
    bad_T[1, 3], bad_q[2] = float("nan"), float("inf")
    with torch.no_grad():
        assert prob.step(q, T[None].contiguous(), q, 0.01) is not None
        assert prob.step(q, bad_T[None].contiguous(), q, 0.01) is None
        assert prob.step(q, T[None].contiguous(), bad_q, 0.01) is None
        for tgt, ref in ((bad_T, q), (T, bad_q)):
            with pytest.raises(NonFiniteError, match="target|q_ref"):  # the torch path's validator
                ik.solve_velocity(chain, q, [ik.FrameTask(0, target=tgt), ik.PostureTask(ref)], 0.01)
