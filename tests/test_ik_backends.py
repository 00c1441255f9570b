"""One IK algorithm, two backends: the C solve (``dk_solve``, kernels/_native_solve.c) and the torch schedule
(ik/_lm.py, what CUDA runs; here on the CPU under ``native.disabled()``) run the same seeds (ik/_seeds.py)
through the same LM schedule: on the same inputs and generator the same success flags, iteration counts,
seeds tried and q to 1e-6 (float64), on the Panda and on chains with ball and free joints (MuJoCo's joint
kinds, Menagerie's G1). Every success is re-checked by an independent FK (MuJoCo for the MJCF chains).
And ``ik.dls_step`` on ball and free joints: the step integrated on the manifold, equal to MuJoCo's
``mj_integratePos`` of the damped least-squares velocity."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from diffkin import ik, models
from diffkin.ik import _native_solve
from diffkin.kernels import native

mujoco = pytest.importorskip("mujoco")
pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler: only the torch backend")

from diffkin.models import from_mjcf  # noqa: E402
from diffkin.models.mjcf import compile_mjcf  # noqa: E402
from tests.test_native_solve_ball import MODELS, _chain, _errors, _mujoco_errors, _targets  # noqa: E402

TOL_P, TOL_O = 1e-4, 1e-3
SAME_Q = 1e-6  # the contract (float64); measured: below 1e-12 on every case here


def _backends(chain, target, **kw):
    """(the C backend, the torch backend) of one ``ik.solve`` call, each checked to be the one served."""
    with torch.no_grad():
        assert _native_solve.applies(chain, target, False)
        c = ik.solve(chain, target, **kw)
        with native.disabled():
            assert not _native_solve.applies(chain, target, False)
            return c, ik.solve(chain, target, **kw)


def _same(c, t):
    assert torch.equal(c.success, t.success)
    assert torch.equal(c.iterations, t.iterations)
    assert torch.equal(c.seeds_tried, t.seeds_tried)
    torch.testing.assert_close(c.q, t.q, atol=SAME_Q, rtol=0)
    torch.testing.assert_close(c.position_error, t.position_error, atol=1e-9, rtol=0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_panda_backends_agree(seed):
    """60 reachable and 4 unreachable targets (5 m away), pose and position-only: one algorithm."""
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((64,), generator=torch.Generator().manual_seed(100 + seed))
    with torch.no_grad():
        T = chain.forward_kinematics(q).clone()
    T[:4, 0, 3] += 5.0
    c, t = _backends(chain, T, seed=seed, num_seeds=16)
    _same(c, t)
    assert not bool(c.success[:4].any()) and int(c.success[4:].sum()) >= 58  # 16 seeds, not 64
    assert bool((c.seeds_tried[:4] == 16).all())  # every seed of an unreachable target tried
    with native.disabled(), torch.no_grad():  # an independent FK of every answer
        Te = chain.forward_kinematics(c.q)
    pe = (Te[..., :3, 3] - T[..., :3, 3]).norm(dim=-1)
    assert bool((pe[c.success] <= TOL_P).all()) and bool(chain.within_limits(c.q).all())
    cp, tp = _backends(chain, T[4:, :3, 3], seed=seed, position_only=True)
    _same(cp, tp)
    assert bool(cp.success.all())


def test_user_seeds_and_the_generator_are_one_pool():
    """User seeds run first, then the library's nearest poses, then the generator's draws: the same order
    in both backends; another generator state gives other restarts (no library: every seed random)."""
    chain = models.load("panda", dtype=torch.float64)
    g = torch.Generator().manual_seed(7)
    q = chain.random_configuration((24,), generator=g)
    q0 = chain.random_configuration((24, 2), generator=g)
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    _same(*_backends(chain, T, q0=q0, seed=3))
    cfg = ik.LMConfig(library_size=0)
    a = _backends(chain, T, config=cfg, seed=4)  # seed: a fresh generator for each backend's call
    b = _backends(chain, T, config=cfg, seed=5)
    _same(*a)
    _same(*b)
    assert not torch.equal(a[0].q, b[0].q)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("name", list(MODELS))
def test_ball_and_free_joint_backends_agree(name, seed):
    """MuJoCo's joint kinds (free, ball, hinge, slide, a second subtree) and the G1 on its floating base
    (four end links): the same flags, iterations and q; each success re-checked with mj_kinematics."""
    chain = _chain(name, torch.float64)
    path, ends = MODELS[name]
    _, T = _targets(chain, 16, seed=10 + seed, unreachable=2)
    c, t = _backends(chain, T, seed=seed, num_seeds=16)
    _same(c, t)
    assert not bool(c.success[:2].any()) and int(c.success.sum()) >= 8  # 16 seeds (whole body: hard)
    pe, oe = _errors(_mujoco_errors(path, chain, ends, c.q), T)
    assert bool((pe[c.success] <= TOL_P + 1e-9).all()) and bool((oe[c.success] <= TOL_O + 1e-7).all())


# ------------------------------------------------------------------------------ dls_step on the manifold
ONE_END = {"g1": (MODELS["g1"][0], "left_six_link"), "joint_kinds": (MODELS["joint_kinds"][0], "tip")}


def _one_end(name):
    path, end = ONE_END[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # joint_kinds' equality is reported
        return from_mjcf(path, [end], dtype=torch.float64), path, [end]


@pytest.mark.parametrize("name", list(ONE_END))
def test_dls_step_integrates_on_the_manifold(name):
    """A hand of the G1 on its floating base, the joint-kinds tip behind a free and a ball joint: q ⊕ Δ
    with Δ (nv) the DLS velocity (3.59) equals MuJoCo's mj_integratePos of the same velocity, its
    quaternions are unit, and the step contracts toward a nearby target like a Newton step."""
    chain, path, ends = _one_end(name)
    assert chain.nq != chain.nv
    g = torch.Generator().manual_seed(21)
    q = chain.random_configuration((5,), generator=g)
    v = 0.02 * torch.randn(5, chain.nv, generator=g, dtype=torch.float64)
    with torch.no_grad():
        T = chain.forward_kinematics(chain.integrate(q, v))
        T_e, J = chain.forward_kinematics_and_jacobian(q)
    lam = 1e-12  # λ of (3.59), added to JJᵀ's diagonal
    T, T_e, J = T[:, 0], T_e[:, 0], J[:, 0]  # one end link (the chain keeps the K axis)
    q1 = ik.dls_step(chain, q, T[:, None], damping=lam, respect_limits=False)
    assert q1.shape == q.shape == (5, chain.nq)
    for idx in chain.configuration_space.quaternion_index():
        torch.testing.assert_close(q1[..., list(idx)].norm(dim=-1), torch.ones(5, dtype=torch.float64),
                                   atol=1e-12, rtol=0)
    # the reference: MuJoCo integrates the DLS velocity of the pose error [p_d - p_e; θr]
    dp = T[..., :3, 3] - T_e[..., :3, 3]
    R = T[..., :3, :3] @ T_e[..., :3, :3].transpose(-1, -2)
    w = torch.from_numpy(np.stack([_rotvec(r) for r in R.numpy()]))
    delta = ik.dls_delta(J, torch.cat((dp, w), -1), lam)
    m = compile_mjcf(path)[0]
    qpos, qvel = chain.to_qpos(q).numpy(), chain.to_qvel(delta).numpy()
    ref = np.empty_like(qpos)
    for r in range(5):
        x = qpos[r].copy()
        mujoco.mj_integratePos(m, x, qvel[r], 1.0)
        ref[r] = x
    torch.testing.assert_close(chain.to_qpos(q1), torch.from_numpy(ref), atol=1e-10, rtol=0)
    pe0, oe0 = _errors(_mujoco_errors(path, chain, ends, q), T[:, None])
    pe1, oe1 = _errors(_mujoco_errors(path, chain, ends, q1), T[:, None])
    assert bool((pe1 <= 0.1 * pe0).all()) and bool((oe1 <= 0.1 * oe0).all())


def _rotvec(R):
    """The rotation vector of a rotation matrix (scipy, an independent implementation)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def test_dls_step_is_differentiable_on_a_free_joint():
    """gradcheck of the step in the target position (float64) behind a free and a ball joint."""
    chain, _, _ = _one_end("joint_kinds")
    g = torch.Generator().manual_seed(22)
    q = chain.random_configuration((2,), generator=g)
    with torch.no_grad():
        T = chain.forward_kinematics(chain.integrate(q, 0.05 * torch.randn(2, chain.nv, generator=g,
                                                                            dtype=torch.float64)))
    p = T[..., :3, 3].clone().requires_grad_(True)

    def f(p):
        Tp = torch.cat((torch.cat((T[..., :3, :3], p.unsqueeze(-1)), -1), T[..., 3:, :]), -2)
        return ik.dls_step(chain, q, Tp, damping=2.5e-3, respect_limits=False)  # Tp (2, K = 1, 4, 4)

    assert torch.autograd.gradcheck(f, (p,))
