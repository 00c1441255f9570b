"""The whole ik.solve in one C call (dk_solve, ik/_native_solve.py) and the lean single-call path
(kernels/single.py): against the torch solve and the torch kernels (native.disabled()), an independent FK
check of every solution, the joint limits, the seeding rules and the per-chain cache."""

from __future__ import annotations

import pytest
import torch

from diffkin import ik, models
from diffkin.ik import _native_solve
from diffkin.ik.result import rotation_angle_between
from diffkin.kernels import native, single
from tests.helpers import c_and_torch_solve, native_chain, urdf_path

pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler: the torch kernels serve")

TOL_P, TOL_O = 1e-4, 1e-3


def _targets(chain, n: int, seed: int, unreachable: int = 0):
    q = chain.random_configuration((n,), generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    if unreachable:  # far outside the workspace (a Panda reaches about 1.2 m)
        T = T.clone()
        T[:unreachable, :3, 3] += torch.tensor([5.0, 0.0, 0.0], dtype=T.dtype)
    return q, T


def _check_honest(chain, res, T):
    """Every success flag is true of an independent FK of q, in the limits; the reported errors are it."""
    with torch.no_grad(), native.disabled():
        Te = chain.forward_kinematics(res.q)
    pe = torch.linalg.vector_norm(Te[..., :3, 3] - T[..., :3, 3], dim=-1)
    oe = rotation_angle_between(Te[..., :3, :3], T[..., :3, :3])
    ok = (pe <= TOL_P) & (oe <= TOL_O) & chain.within_limits(res.q)
    assert torch.equal(res.success, ok)
    atol = 1e-9 if chain.dtype == torch.float64 else 1e-5
    torch.testing.assert_close(res.position_error, pe, atol=atol, rtol=0)
    torch.testing.assert_close(res.orientation_error, oe, atol=100 * atol, rtol=0)
    assert bool(chain.within_limits(res.q).all())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_c_solve_agrees_with_the_torch_solve(dtype):
    """60 reachable and 4 unreachable Panda targets: the same success flags (all / none), errors within
    the tolerances, solutions within the limits, both checked by an independent FK."""
    chain = models.load("panda", dtype=dtype)
    _, T = _targets(chain, 64, seed=5, unreachable=4)
    fused, ref = c_and_torch_solve(chain, T, seed=0)
    assert torch.equal(fused.success, ref.success)
    assert not bool(fused.success[:4].any()) and bool(fused.success[4:].all())
    _check_honest(chain, fused, T)
    _check_honest(chain, ref, T)


@pytest.mark.parametrize("kind,position_only", [("allegro", True), ("allegro", False), ("ur5", False),
                                                ("yumi_mimic", False)])
def test_trees_mimic_and_position_only_agree(kind, position_only):
    chain = native_chain(kind, torch.float64)
    _, T = _targets(chain, 20, seed=6)
    fused, ref = c_and_torch_solve(chain, T[..., :3, 3] if position_only else T, position_only=position_only,
                                   seed=1)
    assert bool(ref.success.all()) and torch.equal(fused.success, ref.success)
    with torch.no_grad():
        Te = chain.forward_kinematics(fused.q)
    assert float((Te[..., :3, 3] - T[..., :3, 3]).norm(dim=-1).max()) <= TOL_P
    assert bool(chain.within_limits(fused.q).all())


def _g1_retarget_chain():
    """The floating-base G1 with its 14 retargeting frames (as retarget.clip's stage one solves it)."""
    from diffkin import retarget

    frames = retarget.Mapping.builtin("g1").frames
    return models.from_urdf(urdf_path("g1_29dof_rev_1_0"), frames, floating_base=True,
                            dtype=torch.float64).requires_grad_(False)


@pytest.mark.parametrize("kind", ["g1", "panda"])
def test_a_target_s_answer_does_not_depend_on_the_others_in_the_call(kind):
    """One seed per target, 21 targets (a block of 16 lanes stepping together, then 5) against each solved
    alone (one lane): the same q to the bit. The G1 position-only (42 rows > 35 velocities: the step's
    sums run over each end link's Jacobian support) also agrees with the torch solve to rounding, with
    7 targets moved off the reachable set (the seed stalls: every LM step of a stage-one solve)."""
    chain = _g1_retarget_chain() if kind == "g1" else models.load("panda", dtype=torch.float64)
    q, T = _targets(chain, 21, seed=3)
    q0 = chain.configuration_space.neutral(torch.float64).expand(21, -1)
    if kind == "g1":
        T = T[..., :3, 3].clone()
        gen = torch.Generator().manual_seed(4)
        T[:7] += 0.2 * torch.randn(7, T.shape[1], 3, dtype=T.dtype, generator=gen)
    kw = dict(num_seeds=1, max_iterations=20, position_only=kind == "g1")
    fused, ref = c_and_torch_solve(chain, T, q0=q0, **kw)
    with torch.no_grad():
        alone = torch.stack([ik.solve(chain, T[i : i + 1], q0[:1], **kw).q[0] for i in range(21)])
    assert torch.equal(alone, fused.q)
    assert torch.equal(fused.iterations, ref.iterations) and torch.equal(fused.success, ref.success)
    torch.testing.assert_close(fused.q, ref.q, atol=1e-10, rtol=0)
    if kind == "g1":
        assert bool((fused.iterations[:7] >= 8).all()) and not bool(fused.success[:7].any())


def test_the_same_generator_gives_the_same_answers_for_every_thread_count(monkeypatch):
    chain = models.load("panda", dtype=torch.float64)
    _, T = _targets(chain, 300, seed=7, unreachable=2)  # 3 chunks of 128 targets
    with torch.no_grad():
        monkeypatch.setattr(native, "thread_count", lambda *a, **k: 1)
        a = ik.solve(chain, T, generator=torch.Generator().manual_seed(3), num_seeds=8)
        monkeypatch.setattr(native, "thread_count", lambda *a, **k: 2)
        b = ik.solve(chain, T, generator=torch.Generator().manual_seed(3), num_seeds=8)
        no_library = ik.LMConfig(library_size=0)  # every seed a random restart
        c, d = (ik.solve(chain, T, generator=torch.Generator().manual_seed(s), num_seeds=8, config=no_library)
                for s in (3, 4))
    for f in ("q", "success", "iterations", "seeds_tried", "position_error"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f
    assert not torch.equal(c.q, d.q)


def test_a_target_at_the_seed_converges_at_once():
    chain = models.load("panda", dtype=torch.float64)
    q, T = _targets(chain, 5, seed=8)
    with torch.no_grad():
        res = ik.solve(chain, T, q0=q, seed=0)
    # lanes left idle by 5 targets take their extra seeds in parallel; the first evaluation harvests
    assert bool(res.success.all()) and bool((res.iterations == 1).all())
    assert bool((res.seeds_tried >= 1).all()) and bool((res.seeds_tried <= 4).all())
    torch.testing.assert_close(res.q, q, atol=1e-5, rtol=0)  # u_of_q keeps seeds 1e-6 inside the limits


@pytest.mark.parametrize("num_seeds", [1, 3, 20])
def test_num_seeds_bounds_the_seeds_of_an_unreachable_target(num_seeds):
    chain = models.load("panda", dtype=torch.float64)
    _, T = _targets(chain, 3, seed=9, unreachable=3)
    with torch.no_grad():
        res = ik.solve(chain, T, num_seeds=num_seeds, max_iterations=8, seed=0)
    assert not bool(res.success.any())
    assert bool((res.seeds_tried == num_seeds).all())
    assert bool((res.iterations <= num_seeds * 8).all()) and bool(torch.isfinite(res.q).all())
    assert bool(chain.within_limits(res.q).all())


def test_seeds_outside_the_limits_give_solutions_within_them():
    chain = models.load("panda", dtype=torch.float64)
    _, T = _targets(chain, 10, seed=10)
    lo, hi = chain.lower_upper()
    q0 = hi + 0.5 + torch.zeros(10, 7, dtype=torch.float64)
    with torch.no_grad():
        res = ik.solve(chain, T, q0=q0, seed=0)
    assert bool(res.success.all()) and bool(chain.within_limits(res.q).all())


# ------------------------------------------------------------------------------ the lean single-call path
@pytest.mark.parametrize("kind", ["panda", "panda_base_tool", "allegro", "yumi_mimic"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_one_configuration_fk_and_jacobian_equal_the_torch_kernels(kind, dtype):
    chain = native_chain(kind, dtype)
    q = chain.random_configuration((1,), generator=torch.Generator().manual_seed(11))[0]
    with torch.no_grad():
        assert single.fk(chain, q) is not None  # the lean path serves it
        T, (T2, J) = chain.forward_kinematics(q), chain.forward_kinematics_and_jacobian(q)
        with native.disabled():
            Tr, (Tr2, Jr) = chain.forward_kinematics(q), chain.forward_kinematics_and_jacobian(q)
    atol = 1e-12 if dtype == torch.float64 else 2e-5
    assert T.shape == Tr.shape and J.shape == Jr.shape
    for a, b in ((T, Tr), (T2, Tr2), (J, Jr)):
        torch.testing.assert_close(a, b, atol=atol, rtol=0)


def test_the_lean_cache_follows_the_parameters():
    chain = models.load("panda", dtype=torch.float64)
    q = chain.random_configuration((1,), generator=torch.Generator().manual_seed(12))[0]
    with torch.no_grad():
        T0 = chain.forward_kinematics(q)
        chain.d.add_(0.01)  # in place: a new version
        T1 = chain.forward_kinematics(q)
        with native.disabled():
            ref = chain.forward_kinematics(q)
    assert not torch.allclose(T0, T1)
    torch.testing.assert_close(T1, ref, atol=1e-12, rtol=0)


def test_the_lean_path_leaves_gradients_and_bad_input_to_the_general_path():
    chain = models.load("panda", dtype=torch.float64, learnable=True)
    q = chain.random_configuration((1,), generator=torch.Generator().manual_seed(13))[0]
    assert single.fk(chain, q) is None  # parameters requiring grad, grad mode on
    assert chain.forward_kinematics(q).requires_grad
    with torch.no_grad():
        assert single.fk(chain, q[None]) is None and single.fk(chain, q.float()) is None
        with pytest.raises(Exception, match="NaN|finite"):
            chain.forward_kinematics(torch.full((7,), float("nan"), dtype=torch.float64))


def test_one_target_through_the_lean_path_is_the_batch_solve():
    chain = models.load("panda", dtype=torch.float64).requires_grad_(False)
    _, T = _targets(chain, 3, seed=14, unreachable=1)
    for i in range(3):
        one = _native_solve.solve_one(chain, T[i].contiguous(), None, 5, num_seeds=64, max_iterations=16,
                                      tol=(TOL_P, TOL_O))
        assert one is not None and one.q.shape == (7,) and one.success.shape == ()
        batch = ik.solve(chain, T[i : i + 1], seed=5)
        assert torch.equal(one.q, batch.q[0]) and bool(one.success) == bool(batch.success[0])
        assert int(one.iterations) == int(batch.iterations[0])
    assert not bool(ik.solve(chain, T[0], seed=5).success) and bool(ik.solve(chain, T[1], seed=5).success)


def test_one_target_falls_back_where_the_lean_path_does_not_apply():
    chain = models.load("panda", dtype=torch.float64)
    _, T = _targets(chain, 1, seed=15)
    T = T[0]
    res = ik.solve(chain, T.clone().requires_grad_(True), seed=0)  # gradients: the implicit layer
    assert res.q.requires_grad and bool(res.success)
    bent = T.clone()
    bent[0, 0] += 1e-6  # not exactly rigid: re-orthonormalised by the general path
    chain.requires_grad_(False)
    assert _native_solve.solve_one(chain, bent, None, 0, num_seeds=64, max_iterations=16,
                                   tol=(TOL_P, TOL_O)) is None
    assert bool(ik.solve(chain, bent, seed=0).success)
    with pytest.raises(Exception, match="NaN|finite"):
        ik.solve(chain, torch.full((4, 4), float("nan"), dtype=torch.float64))


def test_disabled_keeps_the_torch_loop_after_a_c_solve(monkeypatch):
    """A chain's Data (its lean state) must not let the C solve run inside native.disabled() (the torch
    side of every comparison here, and of tests/test_native_solve_ball.py, ran through C before)."""
    chain = models.load("panda", dtype=torch.float64)
    _, T = _targets(chain, 4, seed=16)
    with torch.no_grad():
        assert bool(ik.solve(chain, T, seed=0).success.all()) and _native_solve.applies(chain, T, False)

        def refuse(args):
            raise AssertionError("dk_solve ran inside native.disabled()")

        monkeypatch.setattr(native, "solve_call", refuse)
        with native.disabled():
            assert not _native_solve.applies(chain, T, False)
            assert bool(ik.solve(chain, T, seed=0).success.all())


# ------------------------------------------------------------------------------ library ranks: no clamp
def test_library_ranks_at_the_limit_are_served_fully_and_beyond_it_refused():
    """library_ranks = MAX_RANKS (64) is served: the C solve and the torch solve agree on targets that try
    every seed (unreachable: the best of 64 library seeds decides q). Beyond it LMConfig refuses (an
    OptionError naming the limit), and dk_solve itself refuses lib_ranks > MAX_RANKS (DK_RANGE_ERROR, no
    clamp) if asked without LMConfig's check."""
    from diffkin.errors import OptionError
    from diffkin.ik import numerical
    from diffkin.ik._lm import LMConfig

    limit = native.CONSTANTS["MAX_RANKS"]
    chain = models.load("panda", dtype=torch.float64)
    _, T = _targets(chain, 3, seed=41, unreachable=3)
    cfg = LMConfig(library_ranks=limit, library_size=limit + 16)
    fused, ref = c_and_torch_solve(chain, T, seed=0, config=cfg, num_seeds=limit, max_iterations=6)
    assert not fused.success.any() and bool((fused.seeds_tried == limit).all())
    assert torch.equal(fused.seeds_tried, ref.seeds_tried)
    torch.testing.assert_close(fused.q, ref.q, atol=1e-9, rtol=0)
    torch.testing.assert_close(fused.position_error, ref.position_error, atol=1e-9, rtol=0)
    with pytest.raises(OptionError, match=rf"library_ranks as an integer in \[0, {limit}\], got {limit + 1}"):
        LMConfig(library_ranks=limit + 1)
    with pytest.raises(OptionError, match="library_ranks"):
        ik.solve(chain, T, config=LMConfig(library_ranks=-1))
    over = LMConfig(library_size=limit + 16)
    object.__setattr__(over, "library_ranks", limit + 1)  # past the Python check: the C entry refuses
    prep = _native_solve.prepared(chain, T, torch.float64, True, over.library_size)
    tg = numerical._targets(chain, T, False, torch.float64)[2]
    with pytest.raises(OptionError, match=f"library ranks above {limit}"):
        _native_solve.run(prep, _native_solve.columns(tg), 3, over, torch.Generator().manual_seed(0),
                          tol=(TOL_P, TOL_O), num_seeds=limit + 1, max_iterations=6, user_u=None)
