"""dk_solve (the whole ik.solve in one C call) on chains with quaternion coordinates: ball and free joints
(Menagerie's G1 with its floating base, tests/data/mjcf_extra/joint_kinds.xml, the URDF G1 with
``floating_base=True``). Against the torch loop on the manifold (ik/_lm.py under native.disabled()): the
same success flags, the same solution from the same seed; every success re-checked with MuJoCo's
``mj_kinematics``; unit quaternions; the seeding rule (ConfigurationSpace.from_uniform on the caller's
generator); the same answers for every thread count; whole-body targets as often solved as by the torch
loop (a merge once stepped floating bases additively and every G1 target failed)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import ik
from diffkin.ik import _native_solve
from diffkin.kernels import native
from diffkin.models import from_mjcf, from_urdf

mujoco = pytest.importorskip("mujoco")
pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler: the torch loop serves")

from diffkin.models.mjcf import compile_mjcf  # noqa: E402
from tests.helpers import c_and_torch_solve  # noqa: E402  (the C solve and the torch loop of one call)

DATA = Path(__file__).parent / "data"
G1 = DATA / "mjcf" / "unitree_g1" / "g1.xml"
G1_ENDS = ["left_ankle_roll_link", "right_ankle_roll_link", "left_six_link", "right_six_link"]
KINDS = DATA / "mjcf_extra" / "joint_kinds.xml"
KINDS_ENDS = ["palm", "tip", "foot"]
G1_URDF = DATA / "urdf" / "g1_29dof_rev_1_0.urdf"
G1_URDF_ENDS = ["left_ankle_roll_link", "right_ankle_roll_link", "left_wrist_yaw_link",
                "right_wrist_yaw_link"]
TOL_P, TOL_O = 1e-4, 1e-3
MODELS = {"g1": (G1, G1_ENDS), "joint_kinds": (KINDS, KINDS_ENDS)}
# the same seed, the same solution: float64 agrees to rounding; in float32 the rounding of the two FKs may
# move the convergence test by one LM step, a step below the tolerance
SAME_Q = {torch.float64: 1e-9, torch.float32: 1e-3}
UNIT = {torch.float64: 1e-12, torch.float32: 1e-6}


def _chain(name, dtype):
    path, ends = MODELS[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # joint_kinds' equality is reported
        return from_mjcf(path, ends, dtype=dtype)


def _targets(chain, n, seed, unreachable=0):
    """Poses of random configurations; the first ``unreachable`` with end link 0 moved 5 m away from the
    others (a floating base reaches any single pose; no limb is 5 m long)."""
    g = torch.Generator().manual_seed(seed)
    q = chain.random_configuration((n,), generator=g)
    with torch.no_grad():
        T = chain.forward_kinematics(q).clone()
    T[:unreachable, 0, 0, 3] += 5.0
    return q, T


def _unit_quaternions(chain, q):
    for idx in chain.configuration_space.quaternion_index():
        norms = q[..., list(idx)].norm(dim=-1)
        torch.testing.assert_close(norms, torch.ones_like(norms), atol=UNIT[q.dtype], rtol=0)


def _mujoco_errors(path, chain, ends, q):
    """The end bodies' or sites' poses ``(B, K, 4, 4)`` from MuJoCo's mj_kinematics at ``q`` (the chain's q
    in the model's qpos)."""
    m = compile_mjcf(path)[0]
    d = mujoco.MjData(m)
    body, site = mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_SITE
    ids = [(mujoco.mj_name2id(m, body, e), mujoco.mj_name2id(m, site, e)) for e in ends]  # -1: not one
    qpos = chain.to_qpos(q.detach()).double().numpy()
    out = np.zeros((len(qpos), len(ends), 4, 4))
    for r, row in enumerate(qpos):
        d.qpos[:] = row
        mujoco.mj_kinematics(m, d)
        for k, (b, st) in enumerate(ids):
            R, p = (d.xmat[b], d.xpos[b]) if b >= 0 else (d.site_xmat[st], d.site_xpos[st])
            out[r, k, :3, :3], out[r, k, :3, 3] = R.reshape(3, 3), p
    return torch.tensor(out)


def _errors(T_reached, T_target):
    pe = (T_reached[..., :3, 3] - T_target[..., :3, 3]).norm(dim=-1).amax(-1)
    R = T_reached[..., :3, :3].transpose(-1, -2) @ T_target[..., :3, :3]
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return pe, torch.arccos(cos).amax(-1)


@pytest.mark.parametrize("position_only", [False, True], ids=["pose", "position"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("name", list(MODELS))
def test_the_c_solve_agrees_with_the_torch_loop(name, dtype, position_only):
    """18 reachable and 2 unreachable targets: the success flags of the torch loop (none of the unreachable
    ones; of the reachable ones at most one apart, their random restarts differing by design: here all),
    each success re-checked by MuJoCo, unit quaternions, scalars within their limits."""
    chain = _chain(name, dtype)
    path, ends = MODELS[name]
    _, T = _targets(chain, 20, seed=1, unreachable=2)
    target = T[..., :3, 3] if position_only else T
    fused, ref = c_and_torch_solve(chain, target, seed=0, position_only=position_only)
    assert not bool(fused.success[:2].any()) and not bool(ref.success[:2].any())
    assert int((fused.success != ref.success).sum()) <= 1 and int(fused.success.sum()) >= 17
    pe, oe = _errors(_mujoco_errors(path, chain, ends, fused.q), T.double())
    slack = 1e-9 if dtype == torch.float64 else 1e-5  # the chain's float32 FK against MuJoCo's float64
    ok = fused.success
    assert bool((pe[ok] <= TOL_P + slack).all()) and bool((pe[~ok] > TOL_P - slack).all())
    torch.testing.assert_close(pe.to(dtype), fused.position_error, atol=slack, rtol=0)
    if not position_only:
        assert bool((oe[ok] <= TOL_O + 100 * slack).all())
    _unit_quaternions(chain, fused.q)
    assert bool(chain.within_limits(fused.q).all()) and bool(torch.isfinite(fused.q).all())


@pytest.mark.parametrize("position_only", [False, True], ids=["pose", "position"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_same_seed_gives_the_same_solution(dtype, position_only):
    """One user seed per target near a solution (q ⊕ 0.05 v, quaternions moved on the sphere): the C solve
    and the torch loop run the same LM steps on the manifold and stop at the same q (SAME_Q)."""
    chain = _chain("g1", dtype)
    g = torch.Generator().manual_seed(2)
    q = chain.random_configuration((12,), generator=g)
    q0 = chain.integrate(q, 0.05 * torch.randn(12, chain.nv, generator=g, dtype=dtype))
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    target = T[..., :3, 3] if position_only else T
    fused, ref = c_and_torch_solve(chain, target, q0=q0, num_seeds=1, seed=0, position_only=position_only)
    assert bool(fused.success.all()) and bool(ref.success.all())
    assert bool((fused.seeds_tried == 1).all()) and bool((ref.seeds_tried == 1).all())
    torch.testing.assert_close(fused.q, ref.q, atol=SAME_Q[dtype], rtol=0)


def test_random_restarts_follow_from_uniform():
    """With one random seed, one evaluation and no library, q is the seed: column t of the pool drawn from
    the caller's generator, mapped by ConfigurationSpace.from_uniform (scalars uniform in their ranges,
    quaternions by Shoemake's map); bounded scalars come back 1e-6 of their half range inside (u_of_q)."""
    chain = _chain("joint_kinds", torch.float64)
    _, T = _targets(chain, 5, seed=3)
    cfg = ik.LMConfig(library_size=0, check_every=1)
    with torch.no_grad():
        res = ik.solve(chain, T, num_seeds=1, max_iterations=1, config=cfg, seed=4)
    space = chain.configuration_space
    lo, hi = (t[list(space.scalar_index())] for t in chain.lower_upper())
    pool = torch.rand(5 * space.n_uniform, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    expected = space.from_uniform(lo, hi, pool.reshape(5, space.n_uniform))
    assert not bool(res.success.any())
    torch.testing.assert_close(res.q, expected, atol=1e-5, rtol=0)


def test_the_same_generator_gives_the_same_answers_for_every_thread_count(monkeypatch):
    chain = _chain("g1", torch.float64)
    _, T = _targets(chain, 300, seed=5, unreachable=2)  # 3 chunks of 128 targets
    with torch.no_grad():
        monkeypatch.setattr(native, "thread_count", lambda *a, **k: 1)
        a = ik.solve(chain, T, generator=torch.Generator().manual_seed(3))
        monkeypatch.setattr(native, "thread_count", lambda *a, **k: 2)
        b = ik.solve(chain, T, generator=torch.Generator().manual_seed(3))
    for f in ("q", "success", "iterations", "seeds_tried", "position_error", "orientation_error"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f
    assert float(a.success.double().mean()) >= 0.95


def test_whole_body_targets_succeed_as_often_as_with_the_torch_loop():
    """The URDF G1 on a floating base, four end links, full poses: the C solve (steps on the manifold)
    solves as many targets as the torch loop (one fewer at most: their random restarts differ by design;
    here as many), and every success is true of an independent FK."""
    chain = from_urdf(G1_URDF, G1_URDF_ENDS, floating_base=True, dtype=torch.float64)
    _, T = _targets(chain, 32, seed=6)
    fused, ref = c_and_torch_solve(chain, T, seed=0)
    assert int(fused.success.sum()) >= int(ref.success.sum()) - 1 and int(ref.success.sum()) >= 30
    with torch.no_grad(), native.disabled():
        pe, oe = _errors(chain.forward_kinematics(fused.q), T)
    assert torch.equal(fused.success, (pe <= TOL_P) & (oe <= TOL_O) & chain.within_limits(fused.q))
    _unit_quaternions(chain, fused.q)


def test_one_target_on_a_ball_chain_through_the_lean_path():
    """A single-end chain with a ball joint (joint_kinds' arm from the torso): solve_one serves it and gives
    the batch solve's answer; a pose target requiring grad gets the implicit gradient at the solution."""
    chain = from_mjcf(KINDS, "palm", root_link="torso", dtype=torch.float64).requires_grad_(False)
    q = chain.random_configuration(4, generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    for i in range(4):
        one = _native_solve.solve_one(chain, T[i].contiguous(), None, 5, num_seeds=64, max_iterations=16,
                                      tol=(TOL_P, TOL_O))
        assert one is not None and one.q.shape == (chain.nq,) and bool(one.success)
        batch = ik.solve(chain, T[i : i + 1], seed=5)
        # the batch path re-orthonormalises the target (as_measured_transform): the same steps to rounding
        torch.testing.assert_close(one.q, batch.q[0], atol=1e-12, rtol=0)
        assert int(one.iterations) == int(batch.iterations[0])
        _unit_quaternions(chain, one.q)
    Tg = T[0].clone().requires_grad_(True)
    res = ik.solve(chain, Tg, seed=0)
    (grad,) = torch.autograd.grad((res.q * torch.arange(chain.nq, dtype=torch.float64)).sum(), Tg)
    assert bool(res.success) and bool(torch.isfinite(grad).all()) and float(grad.abs().sum()) > 0


def test_quaternion_seeds_of_any_norm_and_no_limits():
    """User seeds with quaternions scaled by 3 (normalised as JointMap.u_of_q does) and respect_limits=False
    (every scalar unbounded): the C solve still agrees with the torch loop and returns unit quaternions."""
    chain = _chain("joint_kinds", torch.float64)
    q, T = _targets(chain, 8, seed=8)
    q0 = q.clone()
    for idx in chain.configuration_space.quaternion_index():
        q0[:, list(idx)] *= 3.0
    fused, ref = c_and_torch_solve(chain, T, q0=q0, num_seeds=1, seed=0, respect_limits=False)
    assert bool(fused.success.all()) and bool(ref.success.all())
    torch.testing.assert_close(fused.q, ref.q, atol=1e-9, rtol=0)
    _unit_quaternions(chain, fused.q)


def test_more_rows_than_velocities():
    """Hinge, hinge, ball (nq 6, nv 5) and full poses (6 rows): the step solves the nv x nv normal
    equations (the r > nv branch of lane_delta) and still agrees with the torch loop from the same seed;
    random restarts solve every target, re-checked with MuJoCo."""
    xml = """<mujoco><worldbody><body name="a"><joint name="j1" axis="0 0 1"/><geom size="0.1"/>
      <body name="b" pos="0.3 0 0"><joint name="j2" axis="0 1 0"/><geom size="0.1"/>
      <body name="c" pos="0.3 0 0.1"><joint name="ball" type="ball"/><geom size="0.1"/>
      <site name="tip" pos="0.2 0.1 0"/></body></body></body></worldbody></mujoco>"""
    chain = from_mjcf(xml, "tip", dtype=torch.float64)
    assert (chain.nq, chain.nv) == (6, 5)
    g = torch.Generator().manual_seed(9)
    q = chain.random_configuration((10,), generator=g)
    q0 = chain.integrate(q, 0.1 * torch.randn(10, chain.nv, generator=g, dtype=torch.float64))
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    fused, ref = c_and_torch_solve(chain, T, q0=q0, num_seeds=1, seed=0)
    assert bool(fused.success.all()) and bool(ref.success.all())
    torch.testing.assert_close(fused.q, ref.q, atol=1e-9, rtol=0)
    fused, ref = c_and_torch_solve(chain, T, seed=0)
    assert bool(fused.success.all()) and bool(ref.success.all())
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    reached = torch.eye(4, dtype=torch.float64).repeat(10, 1, 1, 1)
    for r in range(10):
        d.qpos[:] = chain.to_qpos(fused.q[r]).numpy()
        mujoco.mj_kinematics(m, d)
        reached[r, 0, :3, :3], reached[r, 0, :3, 3] = (torch.tensor(d.site_xmat[0].reshape(3, 3)),
                                                        torch.tensor(d.site_xpos[0]))
    pe, oe = _errors(reached, T[:, None])
    assert bool((pe <= TOL_P + 1e-9).all()) and bool((oe <= TOL_O + 1e-7).all())
    _unit_quaternions(chain, fused.q)
