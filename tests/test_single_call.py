"""The lean single-call path (kernels/single.py, dk_fk_one): its per-chain cache must never serve stale
constants. Every way a user changes a chain (in place with and without a version bump, an optimizer step,
a replaced or re-materialised tensor, a base set, a dtype move, copies) is followed by a lean call that is
compared with the torch kernels (native.disabled(), an independent encoding); errors and gradients stay the
general path's."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest
import torch
from torch import nn

from diffkin import models
from diffkin.errors import DTypeError, NonFiniteError, ShapeError
from diffkin.kernels import native, single
from tests.helpers import in_threads

pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler: the torch kernels serve")


def _q(chain, seed=0, n=1):
    q = chain.random_configuration((n,), generator=torch.Generator().manual_seed(seed))
    return q[0] if n == 1 else q


def _check_fresh(chain, q):
    """The lean FK and FK + Jacobian of q equal the torch kernels' and the batched call's row."""
    with torch.no_grad():
        assert single.fk(chain, q) is not None, "the lean path should serve this call"
        T, (T2, J) = chain.forward_kinematics(q), chain.forward_kinematics_and_jacobian(q)
        Tb = chain.forward_kinematics(torch.stack([q, q]))[0]
        with native.disabled():
            Tr, (_, Jr) = chain.forward_kinematics(q), chain.forward_kinematics_and_jacobian(q)
    atol = 1e-12 if q.dtype == torch.float64 else 2e-5
    for a, b in ((T, Tr), (T2, Tr), (J, Jr), (Tb, Tr)):
        torch.testing.assert_close(a, b, atol=atol, rtol=0)
    return T


@pytest.mark.parametrize("name", ["a", "alpha", "d", "theta", "base_delta", "tool_delta"])
def test_a_write_through_data_is_seen(name):
    """p.data.add_() bumps no version counter: the bytes are compared (dk_unchanged)."""
    chain = models.load("panda", dtype=torch.float64)
    q = _q(chain, 1)
    T0 = _check_fresh(chain, q)
    p = getattr(chain, name)
    version = p._version
    p.data.add_(0.05)
    assert p._version == version  # the case the version key misses
    T1 = _check_fresh(chain, q)
    assert (T1 - T0).abs().max() > 1e-3


def test_memory_shared_with_numpy_is_seen():
    chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
    q = _q(chain, 2)
    T0 = _check_fresh(chain, q)
    chain.d.numpy()[2] += 0.1  # no torch op at all
    assert (_check_fresh(chain, q) - T0).abs().max() > 1e-3


def test_an_optimizer_step_on_a_learnable_chain_is_seen():
    chain = models.load("panda", dtype=torch.float64, learnable=True)
    q = _q(chain, 3)
    T0 = _check_fresh(chain, q)
    opt = torch.optim.SGD(chain.parameters(), lr=0.1)
    for _ in range(2):
        opt.zero_grad()
        T = chain.forward_kinematics(q)  # autograd: the general path
        assert T.requires_grad
        T[:3, 3].sum().backward()
        opt.step()
        T1 = _check_fresh(chain, q)
        assert (T1 - T0).abs().max() > 1e-4
        T0 = T1


def test_replaced_and_rematerialised_tensors_are_seen():
    chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
    q = _q(chain, 4)
    T0 = _check_fresh(chain, q)
    chain.a.data = chain.a.data + 0.02  # set_data: a new storage, no version bump
    T1 = _check_fresh(chain, q)
    chain.d = nn.Parameter(chain.d.detach() + 0.03, requires_grad=False)  # a new parameter object
    T2 = _check_fresh(chain, q)
    chain.base = torch.tensor([[1.0, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0.2], [0, 0, 0, 1]],
                              dtype=torch.float64)  # a buffer from None to a tensor
    T3 = _check_fresh(chain, q)
    torch.testing.assert_close(T3[:3, 3], T2[:3, 3] + torch.tensor([0.5, 0, 0.2], dtype=torch.float64),
                               atol=1e-12, rtol=0)
    assert (T1 - T0).abs().max() > 1e-3 and (T2 - T1).abs().max() > 1e-3


def test_a_dtype_move_and_back():
    chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
    q = _q(chain, 5)
    T64 = _check_fresh(chain, q)
    chain.to(torch.float32)
    with torch.no_grad():
        assert single.fk(chain, q) is None  # float64 q on a float32 chain: the general path's error
        with pytest.raises(DTypeError):
            chain.forward_kinematics(q)
    T32 = _check_fresh(chain, q.float())
    torch.testing.assert_close(T32.double(), T64, atol=1e-5, rtol=0)
    chain.to(torch.float64)
    torch.testing.assert_close(_check_fresh(chain, q), T64, atol=1e-6, rtol=0)


def test_copies_and_pickles_of_a_used_chain():
    chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
    q = _q(chain, 6)
    T0 = _check_fresh(chain, q)
    for other in (copy.deepcopy(chain), pickle.loads(pickle.dumps(chain))):
        torch.testing.assert_close(_check_fresh(other, q), T0, atol=0, rtol=0)
        other.d.data.add_(0.05)  # its own tensors: the original is unchanged
        assert (_check_fresh(other, q) - T0).abs().max() > 1e-3
        torch.testing.assert_close(_check_fresh(chain, q), T0, atol=0, rtol=0)


def test_errors_and_non_finite_input_stay_the_general_paths():
    chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
    q = _q(chain, 7)
    with torch.no_grad():
        _check_fresh(chain, q)
        for bad, err in ((torch.zeros(8, dtype=torch.float64), ShapeError), (q.float(), DTypeError),
                         (q.to(torch.int64), DTypeError)):
            with pytest.raises(err):
                chain.forward_kinematics(bad)
            with pytest.raises(err):
                chain.forward_kinematics_and_jacobian(bad)
        for v in (float("nan"), float("inf")):
            q2 = q.clone()
            q2[3] = v
            with pytest.raises(NonFiniteError):
                chain.forward_kinematics(q2)
            with pytest.raises(NonFiniteError):
                chain.forward_kinematics_and_jacobian(q2)
            assert chain.forward_kinematics(q2, check=False).shape == (4, 4)  # unchecked: no error
        strided = torch.stack([q, q], dim=1)[:, 0]  # not contiguous: the general path serves it
        assert single.fk(chain, strided) is None
        torch.testing.assert_close(chain.forward_kinematics(strided), chain.forward_kinematics(q),
                                   atol=0, rtol=0)


def test_gradients_are_the_general_paths():
    chain = models.load("panda", dtype=torch.float64, learnable=True)
    q = _q(chain, 8).requires_grad_(True)
    assert single.fk(chain, q) is None and single.fk(chain, q.detach()) is None  # parameters need grad
    T = chain.forward_kinematics(q)
    (gq, gd) = torch.autograd.grad(T[:3, 3].sum(), (q, chain.d))
    with native.disabled():
        Tr = chain.forward_kinematics(q)
        (rq, rd) = torch.autograd.grad(Tr[:3, 3].sum(), (q, chain.d))
    torch.testing.assert_close(gq, rq, atol=1e-12, rtol=0)
    torch.testing.assert_close(gd, rd, atol=1e-12, rtol=0)
    chain.requires_grad_(False)
    assert single.fk(chain, q) is None  # q wants a gradient
    _, J = chain.forward_kinematics_and_jacobian(q)
    assert J.requires_grad


def test_calls_from_several_threads_agree():
    """Concurrent calls share the entry: the work space is taken by one call at a time, the others make
    their own (dk_fk_one's busy flag)."""
    chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
    qs = _q(chain, 9, n=64)
    with torch.no_grad(), native.disabled():
        ref_T, ref_J = chain.forward_kinematics_and_jacobian(qs)

    def work(_):
        errors = []
        for _ in range(20):
            for i in range(len(qs)):
                T, J = chain.forward_kinematics_and_jacobian(qs[i])
                errors.append(max(float((T - ref_T[i]).abs().max()), float((J - ref_J[i]).abs().max())))
        return errors

    errors = [e for part in in_threads(work) for e in part]
    assert len(errors) == 4 * 20 * len(qs) and max(errors) < 1e-12


def test_a_fresh_chains_first_calls_from_several_threads_agree():
    """The first calls of a fresh chain from several threads fill its Data once: a pack made twice and
    replaced freed the packed constants another thread's C call was reading (wrong poses, a refused struct,
    a crash; seen on a slow CI machine). Calls that all get the same, right answer."""
    from diffkin import ik

    ref_chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
    qs = _q(ref_chain, 11, n=4)
    with torch.no_grad(), native.disabled():
        ref_T, ref_J = ref_chain.forward_kinematics_and_jacobian(qs)
    T_goal = ref_T[0].contiguous()
    ref_ik = ik.solve(ref_chain, T_goal, seed=3)
    for _ in range(6):  # fresh chains: the race is in the first calls
        chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
        fk = in_threads(lambda k, c=chain: c.forward_kinematics_and_jacobian(qs[k]) + (k,))
        assert len(fk) == 4
        for T, J, k in fk:
            assert torch.allclose(T, ref_T[k], atol=1e-12, rtol=0) and torch.allclose(J, ref_J[k], atol=1e-12,
                                                                                      rtol=0)
        chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
        solved = in_threads(lambda k, c=chain: ik.solve(c, T_goal, seed=3))
        assert len(solved) == 4
        assert all(torch.equal(r.q, ref_ik.q) and bool(r.success) for r in solved)


def test_the_watch_sees_every_byte():
    t = torch.zeros(5, dtype=torch.float64)
    u = torch.arange(3, dtype=torch.int32)
    w = single.Watch([t, u])
    assert w.unchanged()
    u.numpy()[2] = 7
    assert not w.unchanged()
    u.numpy()[2] = 2
    assert w.unchanged()
    t.view(torch.int64)[4] ^= 1  # the lowest bit of the last double
    assert not w.unchanged()
    assert np.array_equal(u.numpy(), [0, 1, 2])


def test_the_benchmarks_batch_one_rows_run():
    """benchmarks/bench_single_call.py's batch-1 rows (the peers' where installed) on a few calls."""
    from benchmarks import bench_single_call

    rows = bench_single_call.batch_one_kinematics(n=60)
    cases = [r["case"] for r in rows]
    assert cases[:2] == ["FK, 1 configuration", "FK + Jacobian, 1 configuration"]
    assert all(r["median_us"] > 0 for r in rows)


def test_one_target_seed_draws_as_a_fresh_generator():
    """ik.solve of one target with seed=s (the lean front reseeds a per-thread generator) gives what a fresh
    torch.Generator().manual_seed(s) gives, call after call, and fresh output tensors each time."""
    from diffkin import ik

    chain = models.load("panda", dtype=torch.float64)
    g = torch.Generator().manual_seed(4)
    T = chain.forward_kinematics(chain.random_configuration(3, generator=g))
    first = None
    for i in range(3):
        a = ik.solve(chain, T[i].contiguous(), seed=10 + i)
        b = ik.solve(chain, T[i].contiguous(), generator=torch.Generator().manual_seed(10 + i))
        assert torch.equal(a.q, b.q) and bool(a.success) == bool(b.success)
        assert int(a.iterations) == int(b.iterations) and int(a.seeds_tried) == int(b.seeds_tried)
        if first is None:
            first = a
    assert first.q.data_ptr() != a.q.data_ptr()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_one_target_pool_drawn_in_c_is_torchs_stream(dtype):
    """With seed=s and no generator, dk_solve_one draws the random seeds itself (MT19937 as ATen's CPU
    generator, 53-bit doubles / 24-bit floats): unreachable targets use all 64 seeds, so the whole pool is
    compared with torch.rand's through the solve (q, flags, iterations); seeds beyond C's range (>= 2**63,
    negative) take torch's generator. The low 32 bits of a seed are MT19937's (as torch's manual_seed)."""
    from diffkin import ik

    chain = models.load("panda", dtype=dtype)
    g = torch.Generator().manual_seed(5)
    T = chain.forward_kinematics(chain.random_configuration(4, generator=g)).to(dtype)
    T[2:, :3, 3] += 2.0  # out of reach: every seed runs
    for seed in (0, 7, 2**32 + 7, 2**63 - 1):
        for t in range(4):
            a = ik.solve(chain, T[t].contiguous(), seed=seed)
            b = ik.solve(chain, T[t].contiguous(), generator=torch.Generator().manual_seed(seed))
            assert torch.equal(a.q, b.q) and bool(a.success) == bool(b.success) == (t < 2)
            assert int(a.iterations) == int(b.iterations) and int(a.seeds_tried) == int(b.seeds_tried)
            if t >= 2:
                assert int(a.seeds_tried) == 64
    seven = ik.solve(chain, T[3].contiguous(), seed=7).q
    assert torch.equal(seven, ik.solve(chain, T[3].contiguous(), seed=2**32 + 7).q)  # low 32 bits
    assert not torch.equal(seven, ik.solve(chain, T[3].contiguous(), seed=8).q)
    for seed in (2**63, -3):  # torch's generator serves these
        a = ik.solve(chain, T[3].contiguous(), seed=seed)
        b = ik.solve(chain, T[3].contiguous(), generator=torch.Generator().manual_seed(seed))
        assert torch.equal(a.q, b.q)


def test_one_target_solve_sees_a_write_through_data():
    """dk_solve_one compares the packed constants' bytes: after p.data.add_() (no version bump) the lean
    solve answers for the new geometry, as a freshly loaded chain with the same change."""
    from diffkin import ik

    chain, fresh = (models.load("panda", dtype=torch.float64) for _ in range(2))
    T = chain.forward_kinematics(_q(chain, 11))
    before = ik.solve(chain, T, seed=3)
    chain.d.data.add_(0.02)
    fresh.d.data.add_(0.02)
    after, ref = ik.solve(chain, T, seed=3), ik.solve(fresh, T, seed=3)
    assert torch.equal(after.q, ref.q) and bool(after.success) and bool(ref.success)
    assert not torch.equal(after.q, before.q)
    # with a caller's generator the stale entry is repacked and the call redone from the pool already
    # drawn: the generator advances once, as on a chain whose entry was never stale
    chain.d.data.add_(0.01)
    unused = models.load("panda", dtype=torch.float64)  # no entry yet: nothing to find stale
    unused.d.data.add_(0.02).add_(0.01)  # the same additions as the chain's: the same bits
    g_chain, g_unused = torch.Generator().manual_seed(9), torch.Generator().manual_seed(9)
    a, b = ik.solve(chain, T, generator=g_chain), ik.solve(unused, T, generator=g_unused)
    assert torch.equal(a.q, b.q) and torch.equal(g_chain.get_state(), g_unused.get_state())
    chain.d.data.sub_(0.01)
    reached = chain.forward_kinematics(after.q)  # within 0.1 mm and 1 mrad, the default tolerances
    torch.testing.assert_close(reached[:3, 3], T[:3, 3], atol=1e-4, rtol=0)
    torch.testing.assert_close(reached[:3, :3], T[:3, :3], atol=1e-3, rtol=0)
