"""benchmarks/peers.py: the optional peers (Pinocchio, Robotics Toolbox) compute the same FK and Jacobian as
diffkin, so the speed rows compare like with like. Agreement, and that each reported rate is what it says
(configurations per second of the timed loop: an exact value under a scripted clock, and consistent with the
call's own wall time); no speed thresholds (the machine may be busy)."""

from __future__ import annotations

import itertools
import time
import types

import numpy as np
import pytest
import torch

from benchmarks import peers
from diffkin import DHChain, models

B = 64


def _panda_q(n: int = B, seed: int = 0):
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((n,), generator=torch.Generator().manual_seed(seed))
    return chain, q.detach()


def _timed(fn, *args, **kwargs):
    """``(fn's result, wall seconds of the call)``."""
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


def _assert_rate(fn, q, monkeypatch, **kwargs):
    """``fn(q, repeats=...)`` reports configurations per second of its timed loop: B / rate is at most the
    call's wall time (the loop runs inside it), and with a clock that advances 0.25 s per read (each timed
    repetition then lasts 0.25 s) the rate is exactly B / 0.25. Returns the real call's result."""
    (rate, out), wall = _timed(fn, q, repeats=2, **kwargs)
    B = len(q)
    assert B / rate <= wall, f"{B} configurations in {B / rate:.3g} s, within a call of {wall:.3g} s"
    ticks = itertools.count(0.0, 0.25)
    with monkeypatch.context() as m:
        m.setattr(peers, "time", types.SimpleNamespace(perf_counter=lambda: next(ticks)))
        scripted, _ = fn(q, repeats=3, **kwargs)
    assert scripted == B / 0.25
    return out


def _diffkin_fk_jac(chain, q):
    with torch.no_grad():
        return chain.forward_kinematics(q).numpy(), chain.geometric_jacobian(q).numpy()


def test_available_peers_and_skip():
    avail = peers.available_peers()
    assert set(avail) == {"pinocchio", "rtb"}
    assert all(isinstance(v, bool) for v in avail.values())
    assert issubclass(peers.SkipPeer, RuntimeError)
    with pytest.raises(peers.SkipPeer, match="pip install"):
        peers._import("surely_not_a_module_diffkin", "surely-not")


def test_pinocchio_fk_jacobian_match_diffkin(monkeypatch):
    pytest.importorskip("pinocchio")
    chain, q = _panda_q()
    T_ref, J_ref = _diffkin_fk_jac(chain, q)
    T = _assert_rate(peers.pinocchio_fk_rate, q.numpy(), monkeypatch)
    assert T.shape == (B, 4, 4)
    np.testing.assert_allclose(T, T_ref, atol=1e-9, rtol=0)
    T_bare = _assert_rate(peers.pinocchio_fk_rate, q.numpy(), monkeypatch, copy_out=False)
    np.testing.assert_allclose(T_bare, T_ref, atol=1e-9, rtol=0)
    J = _assert_rate(peers.pinocchio_jacobian_rate, q.numpy(), monkeypatch)
    assert J.shape == (B, 6, 7)
    np.testing.assert_allclose(J, J_ref, atol=1e-9, rtol=0)


@pytest.mark.parametrize("name", ["panda", "ur5", "kuka_iiwa14"])
def test_rtb_fk_jacobian_match_diffkin(name, monkeypatch):
    pytest.importorskip("roboticstoolbox")
    chain = models.load(name, dtype=torch.float64)
    q = chain.random_configuration((B,), generator=torch.Generator().manual_seed(1)).detach()
    T_ref, J_ref = _diffkin_fk_jac(chain, q)
    ets = peers.rtb_panda() if name == "panda" else peers.rtb_from_chain(chain).ets()
    T = _assert_rate(peers.rtb_fk_rate, q.numpy(), monkeypatch, ets=ets)
    assert T.shape == (B, 4, 4)
    np.testing.assert_allclose(T, T_ref, atol=1e-9, rtol=0)
    for public in (False, True):
        J = _assert_rate(peers.rtb_jacobian_rate, q.numpy(), monkeypatch, ets=ets, public_api=public)
        np.testing.assert_allclose(J, J_ref, atol=1e-9, rtol=0)


def test_rtb_from_chain_prismatic_base_tool():
    """Random standard and modified DH tables with a prismatic joint, base and tool."""
    rtb = pytest.importorskip("roboticstoolbox")
    g = torch.Generator().manual_seed(3)
    n = 4
    for convention in ("standard", "modified"):
        a, alpha, d = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5 for _ in range(3))
        base = models.load("panda", dtype=torch.float64).forward_kinematics(torch.full((7,), 0.3).double())
        tool = models.load("ur5", dtype=torch.float64).forward_kinematics(torch.full((6,), -0.4).double())
        theta = torch.zeros(n, dtype=torch.float64)
        chain = DHChain(a, alpha, d, theta, joint_types="RPRR", convention=convention, base=base.detach(),
                        tool=tool.detach())
        robot = peers.rtb_from_chain(chain)
        assert isinstance(robot, rtb.DHRobot)
        q = (torch.rand(8, n, generator=g, dtype=torch.float64) - 0.5) * 2
        T_ref, J_ref = _diffkin_fk_jac(chain, q)
        _, T = peers.rtb_fk_rate(q.numpy(), repeats=1, ets=robot.ets())
        _, J = peers.rtb_jacobian_rate(q.numpy(), repeats=1, ets=robot.ets())
        np.testing.assert_allclose(T, T_ref, atol=1e-9, rtol=0)
        np.testing.assert_allclose(J, J_ref, atol=1e-9, rtol=0)


def _check_ik(chain, res, T):
    with torch.no_grad():
        Te = chain.forward_kinematics(torch.from_numpy(res.q)).numpy()
    pe = np.linalg.norm(Te[:, :3, 3] - T[:, :3, 3], axis=1)
    cos = (np.trace(np.swapaxes(T[:, :3, :3], 1, 2) @ Te[:, :3, :3], axis1=1, axis2=2) - 1) / 2
    return pe, np.arccos(np.clip(cos, -1, 1))


def test_rtb_ik_lm_flags_are_honest():
    pytest.importorskip("roboticstoolbox")
    chain, q = _panda_q(8, seed=5)
    T = _diffkin_fk_jac(chain, q)[0]
    res, wall = _timed(peers.rtb_ik_lm, T)
    assert res.q.shape == (8, 7) and res.converged.dtype == bool
    assert res.seconds <= wall and res.solves_per_s == pytest.approx(8 / res.seconds)
    assert res.converged.sum() >= 6
    pe, ang = _check_ik(chain, res, T)
    assert np.all(pe[res.converged] <= 1e-4) and np.all(ang[res.converged] <= 1e-3)
    assert bool(chain.within_limits(torch.from_numpy(res.q[res.converged])).all())


def test_pinocchio_dls_ik_converges():
    pytest.importorskip("pinocchio")
    chain, q = _panda_q(4, seed=6)
    T = _diffkin_fk_jac(chain, q)[0]
    seeds = (q + 0.2).numpy()  # near the answer: the documented loop is slow from far away
    res = peers.pinocchio_dls_ik(T, seeds, eps=1e-6)
    assert res.converged.all()
    pe, ang = _check_ik(chain, res, T)
    assert np.all(pe <= 1e-5) and np.all(ang <= 1e-5)
