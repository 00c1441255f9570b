"""The search stage of motion.plan in C (diffkin/kernels/_native_plan.c, diffkin.motion._native_search) on
MotionBenchMaker problems (VAMP's files, the spherized Panda): its one-call decisions against the torch
placement, every returned edge re-checked by the torch EdgeChecker, a plan re-checked by Pinocchio + coal,
determinism (a problem alone equals its row in a batch), and the finer resolution near a close start."""

from __future__ import annotations

import copy
import ctypes

import pytest
import torch

from diffkin import models, motion
from diffkin.collision import RobotCollision, World
from diffkin.kernels import native
from diffkin.motion._edges import EdgeChecker
from diffkin.motion._native_search import search_native
from diffkin.motion.plan import ETA_LEVELS, _row_resolution
from diffkin.sampling import random_configuration

pytestmark = pytest.mark.skipif(not native.available(), reason="the C library is not built")
F64 = torch.float64
V = [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]


@pytest.fixture(scope="module")
def panda():
    from benchmarks import motion_problems as mp

    chain = models.from_urdf(mp.PANDA_SPHERIZED_URDF, "panda_hand", dtype=F64)
    rc = RobotCollision.from_urdf(mp.PANDA_SPHERIZED_URDF, chain, mp.PANDA_SRDF).requires_grad_(False)
    probs = {p.name: p for p in mp.load_problems(families=["cage", "box", "bookshelf_small", "table_pick"],
                                                  indices=[1, 19, 41])}
    return chain, rc.allow_collisions(probs["cage/0001"].scene.allowed), probs


def _batch(probs, names):
    ps = [probs[n] for n in names]
    return (torch.tensor([p.start for p in ps], dtype=F64), torch.tensor([p.goal for p in ps], dtype=F64),
            World.stack([p.scene.to_world(dtype=F64) for p in ps]), [p.scene.to_world(dtype=F64) for p in ps])


def _checked(probs, rc, names, dtype=F64):
    """The problems ``names`` batched (one scene each) with an EdgeChecker (margin 0, resolution 5 mm) and
    each problem's resolution: ``(qs, qg, world, worlds, checker, rows, eta, start_ok, goal_ok)``."""
    qs, qg, world, worlds = _batch(probs, names)
    qs, qg, world = qs.to(dtype), qg.to(dtype), world.to(dtype)
    checker = EdgeChecker(rc, world, 0.0, 0.005)
    rows = torch.arange(len(names))
    eta, a, b = _row_resolution(checker, qs, qg, rows)
    return qs, qg, world, worlds, checker, rows, eta, a, b


def test_c_decisions_equal_the_torch_placement(panda):
    """dk_plan_decide (FK, placement and decisions in C) equals RobotCollision._clear (torch FK and
    placement, the C decisions) on random configurations in two scenes, wherever the distance is not
    within rounding of the threshold."""
    chain, rc, probs = panda
    _, _, world, _ = _batch(probs, ["cage/0001", "bookshelf_small/0019"])
    q = random_configuration(chain, (600,), generator=torch.Generator().manual_seed(1)).to(F64)
    wid = torch.arange(600) % 2
    checker = EdgeChecker(rc, world, 0.0, 0.005)
    assert checker.native(q) is not None
    for slack in (0.0, 0.005):
        c = checker.clear(q, wid, slack=slack)
        t = rc._clear(q, world, 0.0, slack, moving_only=True, world_index=wid)
        assert 0 < int(c.sum()) < 600  # both outcomes occur
        differ = c != t
        if bool(differ.any()):  # only at the threshold
            d = torch.stack([rc.min_distance(q[i], world._take(wid[i:i + 1])).reshape(()) for i in
                             differ.nonzero().squeeze(1).tolist()])
            assert ((d - slack).abs() < 1e-9).all()


def test_c_decisions_by_link_groups_equal_the_torch_kernels(panda):
    """dk_plan_decide culls by link (each link's spheres one group, the self pairs in runs of one pair of
    links, a sphere far from the other link's box skipping its pairs there): its decisions equal the torch
    kernels' alone (no C at all) on 3 000 configurations spread over two scenes, self collisions included,
    blocks of every size from 1 to 256, wherever the distance is not within rounding of the threshold."""
    chain, rc, probs = panda
    _, _, world, _ = _batch(probs, ["cage/0001", "bookshelf_small/0019"])
    g = torch.Generator().manual_seed(5)
    q = random_configuration(chain, (3000,), generator=g).to(F64)
    wid = (torch.arange(3000) // 500) % 2  # runs of one scene: blocks of 256 and the tails
    checker = EdgeChecker(rc, world, 0.0, 0.005)
    c = checker.clear(q, wid, slack=0.005)
    sizes = [1, 2, 3, 4, 5, 6, 7] * 20  # blocks of 1 to 7 configurations, one call each
    starts = torch.tensor([0] + sizes[:-1]).cumsum(0).tolist()
    small = torch.cat([checker.clear(q[k:k + m], wid[k:k + m], slack=0.005) for k, m in zip(starts, sizes)])
    with native.disabled():
        t = rc._clear(q, world, 0.0, 0.005, moving_only=True, world_index=wid)
        self_ok = rc._clear(q, None, 0.0, 0.005, moving_only=True)
    assert int((~self_ok).sum()) > 100 and int((self_ok & ~t).sum()) > 100  # both kinds of collision occur
    assert int(t.sum()) > 100
    for got, want in ((c, t), (small, t[:small.shape[0]])):
        differ = got != want
        if bool(differ.any()):  # only at the threshold
            rows = differ.nonzero().squeeze(1).tolist()
            d = torch.stack([rc.min_distance(q[i], world._take(wid[i:i + 1])).reshape(()) for i in rows])
            assert ((d - 0.005).abs() < 1e-9).all()


def test_c_decisions_at_the_edge_of_a_self_collision(panda):
    """Configurations bisected (by the torch kernels) to within 1e-7 of the boundary of a self collision,
    where one pair of spheres decides: each decided alone by dk_plan_decide (a block of one lane: the boxes
    of the link groups and of each sphere are tight, so they cull the most) is clear on the clear side and
    not on the other."""
    chain, rc, _ = panda
    slack = 0.005
    q = random_configuration(chain, (4000,), generator=torch.Generator().manual_seed(9)).to(F64)
    with native.disabled():
        ok = rc._clear(q, None, 0.0, slack, moving_only=True)
    lo, hi = q[ok][:40], q[~ok][:40]
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        with native.disabled():
            m = rc._clear(mid, None, 0.0, slack, moving_only=True)
        lo, hi = torch.where(m[:, None], mid, lo), torch.where(m[:, None], hi, mid)
    assert float((hi - lo).abs().max()) < 1e-9
    checker = EdgeChecker(rc, None, 0.0, 0.005)
    assert checker.native(q) is not None
    zero = torch.zeros(1, dtype=torch.long)
    for a, b in zip(lo, hi):
        assert bool(checker.clear(a[None], zero, slack=slack))
        assert not bool(checker.clear(b[None], zero, slack=slack))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_c_edges_equal_the_torch_subdivision(panda, dtype):
    """EdgeChecker.edges through dk_plan_edges (each edge's samples decided in C, in blocks, the edge
    leaving at its first colliding one) gives the torch loop's free flags and prefix fractions on random
    edges in two scenes (one per problem, per-problem resolutions), float64 and float32; it decides fewer
    samples (the rest of a colliding block is not read)."""
    chain, rc, probs = panda
    if dtype == torch.float32:  # copies: float() converts a module in place (the fixture is shared)
        rc = copy.deepcopy(rc).float()
        chain = rc.chain.float()
    _, _, world, _ = _batch(probs, ["cage/0001", "bookshelf_small/0019"])
    world = world.to(dtype)
    gen = torch.Generator().manual_seed(2)
    qa = random_configuration(chain, (300,), generator=gen).to(dtype)
    qb = qa + 0.4 * torch.randn(qa.shape, generator=gen, dtype=F64).to(dtype)
    rows = torch.arange(300) % 2
    checker = EdgeChecker(rc, world, 0.0, 0.005)
    checker.set_row_resolution(torch.tensor([0.005, 0.0025], dtype=dtype))
    assert checker.native(qa) is not None
    for prefix in (False, True):
        checker.use_c, before = True, checker.checked
        free_c, reach_c = checker.edges(qa, qb, rows, prefix=prefix)
        checker.use_c, mid = False, checker.checked
        free_t, reach_t = checker.edges(qa, qb, rows, prefix=prefix)
        assert 0 < int(free_c.sum()) < 300  # both outcomes occur
        assert torch.equal(free_c, free_t) and torch.equal(reach_c, reach_t)
        assert 0 < checker.checked - mid - (mid - before) or prefix  # fewer samples read in C
        if prefix:
            assert bool(((reach_c > 0) & (reach_c < 1)).any())  # partial prefixes occur


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_c_short_edges_equal_the_torch_subdivision(panda, dtype):
    """Edges of 1 to 5 sub-steps, whose first block in C has fewer samples than the narrow decision's 4
    lanes (the rest repeat its last sample) or exactly 4: EdgeChecker.edges in C (whole edges: a block
    stops at its first collision in any sample) gives the torch loop's free flags, both outcomes occurring
    at every count of sub-steps."""
    chain, rc, probs = panda
    if dtype == torch.float32:
        rc = copy.deepcopy(rc).float()
        chain = rc.chain.float()
    _, _, world, _ = _batch(probs, ["cage/0001", "box/0019"])
    gen = torch.Generator().manual_seed(3)
    qa = random_configuration(chain, (1200,), generator=gen).to(dtype)
    d = torch.randn(qa.shape, generator=gen, dtype=F64).to(dtype)
    checker = EdgeChecker(rc, world.to(dtype), 0.0, 0.005)
    reach = checker.reach.to(dtype)
    # an edge of k sub-steps: its bound sum_j R_j |dq_j| = (k - 0.5) * 2 eta, k = 1 .. 5
    k = torch.arange(1200) % 5 + 1
    qb = qa + d * ((k - 0.5) * 2 * 0.005 / (d.abs() * reach).sum(-1)).to(dtype)[:, None]
    rows = torch.arange(1200) % 2
    assert torch.equal(checker.steps(qb - qa, rows), k)
    assert checker.native(qa) is not None
    checker.use_c = True
    free_c, _ = checker.edges(qa, qb, rows)
    checker.use_c = False
    free_t, _ = checker.edges(qa, qb, rows)
    assert torch.equal(free_c, free_t)
    for steps in range(1, 6):
        assert 0 < int(free_c[k == steps].sum()) < int((k == steps).sum())  # both outcomes occur


@pytest.mark.parametrize("margin, eta", [(0.0, 0.005), (-0.19, 0.05)])
def test_c_edges_decided_by_covers_of_three_samples(panda, margin, eta):
    """A whole edge of at least 6 sub-steps is decided in runs of three samples, each run's middle at
    margin + 3 η as well (_native_plan.c, DK(plan_edge_cover)): the flags equal those of every sample decided
    by the torch kernels (no C); a clear edge costs exactly one decision a run, steps // 3 + 1, and one more
    for each other sample of a run whose middle is closer than 3 η (both kinds of edge occur). With a
    margin of -19 cm (penetration allowed: every edge is clear) and η = 5 cm, every self pair has a threshold
    r_i + r_j + margin + η <= 0 (never colliding) and most a cover's r_i + r_j + margin + 3 η > 0: those are
    decided for the cover only (the costs above fail where they are skipped)."""
    chain, rc, probs = panda
    _, _, world, _ = _batch(probs, ["cage/0001"])
    if margin < 0:  # (every geom a sphere: capsule k is geom k)
        r, pairs = rc.capsule_radius.detach(), torch.tensor(rc._pair_index)
        s = r[pairs[:, 0]] + r[pairs[:, 1]]
        assert bool(((s + margin + eta <= 0) & (s + margin + 3 * eta > 0)).any())
    gen = torch.Generator().manual_seed(4)
    qa = random_configuration(chain, (400,), generator=gen).to(F64)
    qb = qa + 0.3 * (eta / 0.005) ** 0.5 * torch.randn(qa.shape, generator=gen, dtype=F64)
    rows = torch.zeros(400, dtype=torch.long)
    checker = EdgeChecker(rc, world, margin, eta)
    planner = checker.native(qa)
    reference = EdgeChecker(rc, world, margin, eta)
    reference.use_c = False
    steps = checker.steps(qb - qa, rows)
    first_bad, decided = planner.edges(qa, qb, steps, torch.full((400,), eta, dtype=F64), None, False)
    free_c = first_bad > steps
    far = near = 0
    with native.disabled():  # the reference decisions in torch
        for e in range(400):
            ns = int(steps[e])
            q = qa[e] + torch.arange(ns + 1, dtype=F64)[:, None] / ns * (qb[e] - qa[e])
            zeros = torch.zeros(ns + 1, dtype=torch.long)
            clear1 = reference.clear(q, zeros, slack=eta)
            assert bool(free_c[e]) == bool(clear1.all())
            if bool(clear1.all()) and ns >= 6:  # (shorter edges: every sample decided)
                start = torch.arange(ns // 3 + 1).mul(3)  # run k: samples 3k .. min(3k + 2, ns)
                mids = (start + 1).clamp(max=ns)
                size = (start + 2).clamp(max=ns) - start + 1
                proven = reference.clear(q[mids], zeros[mids], slack=3 * eta)
                extra = int((size - 1)[~proven].sum())
                assert int(decided[e]) == ns // 3 + 1 + extra
                far, near = far + (extra == 0), near + (extra > 0)
    assert 0 < int(free_c.sum()) and (int(free_c.sum()) < 400 or margin < 0) and far > 5 and near > 5


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_c_point_shortcuts_equal_the_torch_rounds(panda, dtype):
    """shortcut_points in C (dk_plan_points, where the checker decides in C: each path's rounds in one
    thread, the same draws, choices and splices) equals the torch rounds on paths the C search found in
    three scenes: the same waypoint counts, the coordinates to rounding; every edge of the shortened paths
    is proven clear again by the torch EdgeChecker, and the paths are shorter than the searched ones."""
    from diffkin.motion._search import row_keys, shortcut_points

    chain, rc, probs = panda
    if dtype == torch.float32:  # copies: float() converts a module in place (the fixture is shared)
        rc = copy.deepcopy(rc).float()
        chain = rc.chain.float()
    qs, qg, _, _, checker, rows, eta, _, _ = _checked(probs, rc, ["cage/0001", "box/0001", "table_pick/0019"],
                                                      dtype)
    checker.set_row_resolution(eta)
    lim = chain.q_limits
    path, n, found, _ = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], rows, eta, max_iterations=20000,
                                      step=0.5, shortcut_tries=32, seed=0)
    assert found.all()
    key = row_keys(qs, qg, 0)
    pc, nc = shortcut_points(checker, path, n, rows, 12, key, tries=8)  # the C rounds (the checker's in C)
    assert pc.shape[1] == path.shape[1] + 12  # (rows of L + rounds: shortcut_points_native's)
    checker.use_c = False
    pt, nt = shortcut_points(checker, path, n, rows, 12, key, tries=8)  # the torch rounds
    checker.use_c = True
    assert torch.equal(nt, nc)
    L = int(nc.max())
    torch.testing.assert_close(pc[:, :L], pt[:, :L], rtol=0, atol=1e-12 if dtype == F64 else 1e-5)
    length = lambda p, k: (p[1:k] - p[:k - 1]).norm(dim=-1).sum()  # noqa: E731
    for b in range(3):
        k = int(nc[b])
        assert length(pc[b], k) < length(path[b], int(n[b]))
        checker.use_c = False
        free, _ = checker.edges(pc[b, :k - 1], pc[b, 1:k], torch.full((k - 1,), b))
        checker.use_c = True
        assert free.all()


def test_c_search_paths_without_shortcuts_rechecked_sample_by_sample(panda):
    """Six problems searched in C without shortcuts, so every waypoint is a tree node as the search took it
    (the search decides a node once, as the far end of the edge that made it, and takes it as clear after):
    every waypoint is clear with its row's resolution and every edge's every sample, ends included, is clear
    again in the torch EdgeChecker (torch placement)."""
    chain, rc, probs = panda
    names = ["cage/0001", "box/0019", "table_pick/0019", "bookshelf_small/0001", "box/0041", "cage/0019"]
    qs, qg, _, _, checker, rows, eta, a, b = _checked(probs, rc, names)
    assert (a & b).all()
    checker.set_row_resolution(eta)
    lim = chain.q_limits
    path, n, found, _ = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], rows, eta,
                                      max_iterations=20000, step=0.5, shortcut_tries=0, seed=0)
    assert found.all() and int(n.sum()) > 3 * len(names)  # tree nodes on the paths, not only straight edges
    checker.use_c = False
    for r in range(len(names)):
        k = int(n[r])
        assert checker.clear(path[r, :k], torch.full((k,), r)).all()
        free, _ = checker.edges(path[r, :k - 1], path[r, 1:k], torch.full((k - 1,), r))
        assert free.all()
    checker.use_c = True


def test_c_search_connect_steps_no_edge_longer_than_step(panda):
    """CONNECT steps towards the new node and keeps each clear step (RRT-Connect's, VAMP's): a path searched
    without shortcuts is made of EXTEND's edges and CONNECT's steps, each at most ``step`` long in the bound's
    metric sum_j R_j |dq_j|, where CONNECT by one whole edge joined the trees by an edge of any length; the
    trees hold more nodes than EXTEND alone adds (one an iteration), and every edge is clear again in the
    torch EdgeChecker. The trees' room holds every step: with short steps and a small budget, a problem left
    unfound has run every iteration (a tree filled by CONNECT's steps ended the search early once)."""
    chain, rc, probs = panda
    names = ["cage/0001", "box/0019", "table_pick/0019", "bookshelf_small/0001", "box/0041", "cage/0019"]
    qs, qg, _, _, checker, rows, eta, a, b = _checked(probs, rc, names)
    assert (a & b).all()
    checker.set_row_resolution(eta)
    lim, R = chain.q_limits, checker.reach.to(qs.dtype)
    step = 0.5
    path, n, found, stats = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], rows, eta,
                                          max_iterations=20000, step=step, shortcut_tries=0, seed=0)
    assert found.all() and (stats["iterations"] > 0).all()
    assert (stats["nodes"] > stats["iterations"] + 2).any()  # CONNECT's steps kept as nodes
    checker.use_c = False
    for r in range(len(names)):
        k = int(n[r])
        assert torch.equal(path[r, 0], qs[r]) and torch.equal(path[r, k - 1], qg[r])
        L = ((path[r, 1:k] - path[r, :k - 1]).abs() * R).sum(-1)
        assert float(L.max()) <= step * (1 + 1e-9)
        assert checker.edges(path[r, :k - 1], path[r, 1:k], torch.full((k - 1,), r))[0].all()
    checker.use_c = True
    _, _, found, stats = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], rows, eta, max_iterations=5,
                                       step=0.05, shortcut_tries=0, seed=0)
    assert (~found).any() and (stats["iterations"][~found] == 5).all()
    assert (stats["nodes"][~found] > 5 + 2).any()  # CONNECT's steps past one node an iteration


def test_c_search_edges_rechecked_and_plan_rechecked_by_coal(panda):
    """Three problems in one call (a cage, a box, a bookshelf whose start needs a finer resolution): every
    path found, every edge of every returned path proven clear again by the torch EdgeChecker (torch
    placement, the row's resolution); one whole plan re-checked by Pinocchio's FK and coal."""
    from benchmarks.bench_motion_problems import _CoalPanda

    chain, rc, probs = panda
    names = ["cage/0001", "box/0001", "bookshelf_small/0019"]
    qs, qg, world, worlds, checker, rows, eta, a, b = _checked(probs, rc, names)
    assert (a & b).all() and eta[2] < 0.005 and (eta[:2] == 0.005).all()
    lim = chain.q_limits
    path, n, found, stats = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], rows, eta,
                                          max_iterations=10000, step=0.5, shortcut_tries=64, seed=0)
    assert found.all() and (stats["checked"] > 0).all()
    torch_checker = EdgeChecker(rc, world, 0.0, 0.005)
    torch_checker.use_c = False
    torch_checker.set_row_resolution(eta)
    for r in range(3):
        w = path[r, : int(n[r])]
        assert torch.equal(w[0], qs[r]) and torch.equal(w[-1], qg[r])
        free, _ = torch_checker.edges(w[:-1], w[1:], torch.full((len(w) - 1,), r))
        assert free.all()
    res = motion.plan(chain, qs[:1], qg[:1], collision=rc, world=World.stack(worlds[:1]), velocity_limit=V,
                      acceleration_limit=10.0, max_iterations=10000, step=0.5)
    assert res.success.all(), res.reason
    S = int(float(res.duration[0]) / 0.01) + 1
    assert _CoalPanda().min_distance(res.q[0, :S:2].numpy(), worlds[0]) >= 0


def test_c_search_trees_grow_past_their_first_capacity(panda):
    """The trees start with room for 4096 nodes and double as they fill: short steps (3 mm) make box/0001 end
    with more than 2 · 4096 + 2 nodes in its two balanced trees (the smaller one extends, so each holds more
    than 4096); the path found is traced through the regrown trees and every edge of it proven clear again
    by the torch EdgeChecker. A tree whose root is in collision never grows and, being the smaller, takes
    every iteration: the search runs its whole budget with the start's tree at two nodes."""
    chain, rc, probs = panda
    qs, qg, world, _, checker, rows, eta, _, _ = _checked(probs, rc, ["box/0001"])
    lim = chain.q_limits
    kw = dict(max_iterations=40000, step=0.003, shortcut_tries=0, capacity=4096)
    path, n, found, stats = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], rows, eta, seed=1, **kw)
    assert bool(found[0]) and int(stats["nodes"][0]) > 2 * 4096 + 2
    torch_checker = EdgeChecker(rc, world, 0.0, 0.005)
    torch_checker.use_c = False
    w = path[0, : int(n[0])]
    assert torch.equal(w[0], qs[0]) and torch.equal(w[-1], qg[0])
    assert torch_checker.edges(w[:-1], w[1:], torch.zeros(len(w) - 1, dtype=torch.long))[0].all()
    inside = torch.tensor([[0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0]], dtype=F64)  # not clear in this scene
    assert not checker.clear(inside, rows).any()
    kw.update(max_iterations=12000, step=0.01)
    _, _, found, stats = search_native(checker, qs, inside, lim[:, 0], lim[:, 1], rows, eta, seed=1, **kw)
    assert not found.any() and int(stats["iterations"][0]) == 12000 and int(stats["nodes"][0]) == 3


def test_planner_columns_remembered_for_copies_of_one_robot(panda, monkeypatch):
    """The C planner's capsule-end columns are the robot's alone: found once for the copies
    allow_collisions makes per scene (the same values as computed anew), found again when the geometry
    changes."""
    chain, rc, probs = panda
    q = torch.zeros(1, 7, dtype=F64)
    worlds = [probs[n].scene.to_world(dtype=F64) for n in ("cage/0001", "box/0001")]
    first = EdgeChecker(rc, worlds[0], 0.0, 0.005).native(q)
    calls = []
    placement = RobotCollision._placement

    def counted(self, F):
        calls.append(1)
        return placement(self, F)

    monkeypatch.setattr(RobotCollision, "_placement", counted)
    copy = rc.allow_collisions(probs["box/0001"].scene.allowed)
    again = EdgeChecker(copy, worlds[1], 0.0, 0.005).native(q)
    assert not calls and torch.equal(again.h, first.h) and torch.equal(again.frame, first.frame)
    moved_model = rc.allow_collisions([])
    with torch.no_grad():
        moved_model.capsule_a[0, 2] += 0.01  # another geometry (a sphere moved): its columns found anew
        moved_model.capsule_b[0, 2] += 0.01
    moved = EdgeChecker(moved_model, worlds[1], 0.0, 0.005).native(q)
    assert calls and not torch.equal(moved.h, first.h)  # (joint_reach places it too)
    fresh = EdgeChecker(rc, worlds[0], 0.0, 0.005)  # the first geometry again: its values, computed again
    assert torch.equal(fresh.native(q).h, first.h)


def test_c_search_deterministic_and_a_problem_alone_equals_its_row(panda):
    chain, rc, probs = panda
    names = ["cage/0001", "box/0001", "cage/0019"]
    qs, qg, world, _ = _batch(probs, names)
    lim = chain.q_limits
    kw = dict(max_iterations=10000, step=0.5, shortcut_tries=64, seed=3)

    def run(rows):
        checker = EdgeChecker(rc, world, 0.0, 0.005)
        eta = torch.full((len(rows),), 0.005, dtype=F64)
        return search_native(checker, qs[rows], qg[rows], lim[:, 0], lim[:, 1], rows, eta, **kw)

    every = torch.arange(3)
    p1, n1, f1, s1 = run(every)
    p2, n2, f2, s2 = run(every)
    assert f1.all() and torch.equal(p1, p2) and torch.equal(n1, n2)
    assert torch.equal(s1["checked"], s2["checked"])
    for r in range(3):
        pa, na, fa, sa = run(torch.tensor([r]))
        k = int(na[0])
        assert bool(fa[0]) and k == int(n1[r]) and torch.equal(pa[0, :k], p1[r, :k])
        assert int(sa["iterations"][0]) == int(s1["iterations"][r])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_c_search_hints_change_no_verdict(panda, dtype):
    """The collisions the C search remembers between blocks (sphere-box and sphere-cylinder, decided first in
    an edge's first block) only make a colliding block found sooner: with and without them the same paths,
    iterations, decisions and trees, on problems in scenes of boxes and cylinders (bookshelf, table, box),
    float64 and float32."""
    chain, rc, probs = panda
    if dtype == torch.float32:  # copies: float() converts a module in place (the fixture is shared)
        rc = copy.deepcopy(rc).float()
        chain = rc.chain.float()
    names = ["bookshelf_small/0001", "bookshelf_small/0019", "bookshelf_small/0041", "table_pick/0001",
             "table_pick/0019", "box/0019"]
    qs, qg, world, _ = _batch(probs, names)
    qs, qg, world = qs.to(dtype), qg.to(dtype), world.to(dtype)
    assert world.cylinders.shape[-2] > 0
    lim = chain.q_limits
    rows = torch.arange(len(names))
    runs = []
    for hints in (True, False):
        checker = EdgeChecker(rc, world, 0.0, 0.005)
        runs.append(search_native(checker, qs, qg, lim[:, 0], lim[:, 1], rows, None, max_iterations=20000,
                                  step=1.0, shortcut_tries=32, seed=5, rungs=4, hints=hints))
    (p1, n1, f1, s1), (p2, n2, f2, s2) = runs
    assert f1.all() and torch.equal(f1, f2) and torch.equal(n1, n2) and torch.equal(p1, p2)
    for key in ("iterations", "checked", "nodes"):
        assert torch.equal(s1[key], s2[key]), key
    assert int(s1["iterations"].max()) > 20  # refused edges, where the hints are read, occur
    assert int(s1["hinted"].sum()) > 0 and int(s2["hinted"].sum()) == 0  # and the hints were read


def test_close_start_planned_at_a_finer_resolution_and_a_start_in_collision_reported(panda):
    """bookshelf_small/0019 starts closer than 5 mm to a shelf (clear of 0.3 mm): planned at η / 16, it
    succeeds; table_pick/0041 starts or ends in collision (VAMP's one invalid problem): its reason says
    so, in the same call, and nothing is raised."""
    chain, rc, probs = panda
    qs, qg, world, _ = _batch(probs, ["bookshelf_small/0019", "table_pick/0041"])
    res = motion.plan(chain, qs, qg, collision=rc, world=world, velocity_limit=V, acceleration_limit=10.0,
                      max_iterations=10000, step=0.5)
    assert res.success.tolist() == [True, False]
    assert "in collision" in res.reason[1]


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_c_search_decides_starts_and_goals_as_the_torch_ladder(panda, dtype):
    """search_native with ``rungs`` decides each start and goal in C: the resolution, start_ok and goal_ok
    equal _row_resolution's (torch) on a start needing η / 16 (bookshelf_small/0019), VAMP's invalid
    problem (table_pick/0041), a goal moved into collision and a start moved into collision; the rows
    with both clear return the paths and counts of a search given that resolution, the others no path
    (status START_BAD / GOAL_BAD), and each problem's C clock is positive."""
    chain, rc, probs = panda
    if dtype == torch.float32:  # copies: float() converts a module in place (the fixture is shared)
        rc = copy.deepcopy(rc).float()
        chain = rc.chain.float()
    names = ["bookshelf_small/0019", "table_pick/0041", "cage/0001", "box/0001", "box/0001"]
    qs, qg, world, _ = _batch(probs, names)
    inside = torch.tensor([0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0], dtype=F64)  # collides in box/0001
    qg[3], qs[4] = inside, inside
    qs, qg, world = qs.to(dtype), qg.to(dtype), world.to(dtype)
    checker = EdgeChecker(rc, world, 0.0, 0.005)
    rows = torch.arange(len(names))
    eta, a, b = _row_resolution(checker, qs, qg, rows)
    lim = chain.q_limits
    kw = dict(max_iterations=10000, step=0.5, shortcut_tries=8, seed=2)
    path, n, found, stats = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], rows, None,
                                          rungs=ETA_LEVELS + 1, **kw)
    assert a.tolist() == stats["start_ok"].tolist() == [True, a[1].item(), True, True, False]
    assert b.tolist() == stats["goal_ok"].tolist() and not b[3] and b[4] and not (a[1] & b[1])
    assert torch.equal(stats["eta"], eta.to(dtype)) and eta[0] < 0.005
    both = a & b
    assert both.tolist() == [True, False, True, False, False] and found.tolist() == both.tolist()
    assert (stats["nanoseconds"] > 0).all()
    v = both.nonzero().squeeze(1)
    given = search_native(checker, qs[v], qg[v], lim[:, 0], lim[:, 1], v, eta[v], **kw)
    assert torch.equal(given[1], n[v]) and torch.equal(given[0], path[v])
    assert torch.equal(given[3]["iterations"], stats["iterations"][v])


def test_plan_struct_layout_checked_and_another_version_refused(panda):
    """dk_plan's version, size and field offsets equal PlanArgs' (check_layout); a struct of another
    version is refused by the C entry points (DK_ABI_ERROR), nothing computed."""
    import ctypes

    from diffkin.motion import _native_search as ns

    native.check_layout(native._lib, "plan", ns.PlanArgs)
    with pytest.raises(native.AbiMismatch):
        native.check_layout(native._lib, "plan", ns.PlanArgs, ns.VERSION + 1)
    chain, rc, probs = panda
    qs, qg, world, _ = _batch(probs, ["box/0001"])
    planner = EdgeChecker(rc, world, 0.0, 0.005).native(qs)
    ok = torch.full((1,), 7, dtype=torch.uint8)
    a = planner.args(nthreads=1, N=1, q=qs.contiguous(), slack=0.0, ok=ok)
    a.version = ns.VERSION + 1
    search, decide, edges, points = ns._functions()
    assert decide(ctypes.byref(a)) == native.CONSTANTS["DK_ABI_ERROR"] and int(ok[0]) == 7
    for entry in (search, edges, points):
        assert entry(ctypes.byref(a)) == native.CONSTANTS["DK_ABI_ERROR"]


def test_goal_bias_validated_and_used(panda):
    """goal_bias outside [0, 1], and a seed that is not an int64, are OptionErrors naming them; goal_bias 0.5
    still solves (the other tree's root as the sample half the time)."""
    from diffkin.errors import OptionError

    chain, rc, probs = panda
    qs, qg, world, _ = _batch(probs, ["box/0001"])
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(OptionError, match="goal_bias"):
            motion.plan(chain, qs, qg, collision=rc, world=world, velocity_limit=V, acceleration_limit=10.0,
                        goal_bias=bad)
    for bad in (1 << 63, -(1 << 63) - 1, 1.5, True):  # the seed: an int64 (the C streams' and row_keys')
        with pytest.raises(OptionError, match="seed"):
            motion.plan(chain, qs, qg, collision=rc, world=world, velocity_limit=V, acceleration_limit=10.0,
                        seed=bad)
    res = motion.plan(chain, qs, qg, collision=rc, world=world, velocity_limit=V, acceleration_limit=10.0,
                      max_iterations=10000, step=0.5, goal_bias=0.5)
    assert res.success.all(), res.reason


def test_benchmark_vamp_crossings_and_path_proof(panda):
    """The --compare helpers of benchmarks/bench_motion_problems.py. vamp_crossings flags a path whose clear
    waypoints are joined through an obstacle (box/0001's start and goal: some of 4 000 samples of the segment
    collide in the torch placement), not a path the C search proved clear, nor one that comes closer than the
    resolution to the obstacle without touching it (the segment's clear prefix up to its last sample before
    the first colliding one: decided at margin 0, not at the search's slack), and leaves unsolved answers
    out. _path_proof decides the found path's edges alone at the problem's resolution (as many decisions as
    the edge checker's own C edges there) and gives None where no path was found (no iterations, the
    direct edge refused)."""
    from benchmarks import bench_motion_problems as bench

    chain, rc, probs = panda
    p = probs["box/0001"]
    model, world = rc.allow_collisions(p.scene.allowed), p.scene.to_world(dtype=F64)
    a, b = torch.tensor(p.start, dtype=F64), torch.tensor(p.goal, dtype=F64)
    reference = EdgeChecker(model, world, 0.0, 0.005)
    reference.use_c = False
    q = a + torch.linspace(0, 1, 4000, dtype=F64)[:, None] * (b - a)
    zeros = torch.zeros(4000, dtype=torch.long)
    with native.disabled():
        touching = ~reference.clear(q, zeros, slack=0.0)
        within = ~reference.clear(q, zeros, slack=0.005)
    assert not touching[0] and not touching[-1] and touching.any()
    near = int(touching.nonzero()[0]) - 1  # the last sample before the first colliding one
    assert within[near]  # closer than the resolution, clear at margin 0
    qs, qg = a[None], b[None]
    checker = bench.prepared_scene(model, world, qs)
    lim = chain.q_limits
    found_path = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], torch.arange(1), None,
                               max_iterations=20000, step=1.0, shortcut_tries=0, seed=0, rungs=ETA_LEVELS + 1)
    assert found_path[2].all()
    n = int(found_path[1][0])
    solved = found_path[0][0, :n]
    cases = (([p.start, p.goal], True), (solved.tolist(), False), ([p.start, q[near].tolist()], False))
    for path, crossing in cases:
        answers = {p.name: {"name": p.name, "solved": True, "path": path},
                   "box/0019": {"name": "box/0019", "solved": False, "path": []}}
        assert bench.vamp_crossings([p, probs["box/0019"]], answers) == {p.name: crossing}
    seconds, decided = bench._path_proof(chain, checker, qs, qg, 20000, 1.0, 0)
    fresh = EdgeChecker(model, world, 0.0, 0.005)
    fresh.set_row_resolution(found_path[3]["eta"])
    free, _ = fresh.edges(solved[:-1], solved[1:], torch.zeros(n - 1, dtype=torch.long))
    assert free.all() and decided == fresh.checked and 0 <= seconds < float("inf")
    assert bench._path_proof(chain, checker, qs, qg, 0, 1.0, 0) is None


def _gaps(rc, i, j, q, rows=False):
    """Surface distances of capsules ``i`` and ``j`` (index tensors ``(P,)``) at configurations ``q (N, nq)``,
    ``(N, P)``; with ``rows`` one pair per configuration (``P = N``), ``(N,)``."""
    from diffkin.collision.distances import capsule_capsule

    nc, r = rc._counts[0], rc.capsule_radius.detach()
    cols = rc._columns(q).transpose(-1, -2)  # (N, C, 3)
    n = torch.arange(q.shape[0]) if rows else slice(None)
    return capsule_capsule(cols[n, i], cols[n, nc + i], r[i], cols[n, j], cols[n, nc + j], r[j])


def _descent_keeps(rc, pairs, apart, q, d, gap, lo, hi, starts: int, steps: int):
    """Projected gradient descent (within lo .. hi) on each proven pair's own distance from its ``starts``
    closest samples of ``q (N, nq)`` (distances ``d (N, P)``): it stays at least ``gap`` at every step."""
    i, j = pairs[:, 0], pairs[:, 1]
    p = apart.nonzero().squeeze(1)
    closest = d[:, p].topk(starts, dim=0, largest=False).indices  # (starts, Pa)
    x = q[closest].reshape(-1, q.shape[-1]).clone().requires_grad_(True)
    which = p.repeat(starts)
    opt = torch.optim.Adam([x], lr=0.02)
    for _ in range(steps):
        got = _gaps(rc, i[which], j[which], x, rows=True)
        assert (got.detach() >= gap).all()
        opt.zero_grad()
        got.sum().backward()
        opt.step()
        with torch.no_grad():
            x.copy_(torch.maximum(torch.minimum(x, hi), lo))


def test_pairs_apart_never_closer_in_samples_nor_after_descent(panda, monkeypatch):
    """pairs_apart's proof (branch and bound on the distance's joint-space speed bound): every pair it
    proves 15 mm apart stays at least that far in 40 000 random configurations within the limits and after
    projected gradient descent on its distance from its 16 closest samples; it proves most pairs whose
    distance only two or three joints change and whose samples keep 20 mm (the bound is tight enough to
    pay), and remembers its verdicts for the copies one robot makes per scene."""
    from diffkin.motion import _reach

    chain, rc, probs = panda
    gap = 0.015
    pairs = rc._pairs_00
    i, j = pairs[:, 0], pairs[:, 1]
    apart, lo, hi = _reach.pairs_apart(rc, pairs, gap)
    lim = chain.q_limits
    assert torch.equal(lo, lim[:, 0]) and torch.equal(hi, lim[:, 1])
    g = torch.Generator().manual_seed(3)
    q = lo + (hi - lo) * torch.rand(40_000, 7, generator=g, dtype=F64)
    d = torch.cat([_gaps(rc, i, j, x) for x in q.split(5000)])  # (N, P)
    sampled = d.amin(0)
    assert int(apart.sum()) >= 250  # of 690 (264 on this model)
    assert (sampled[apart] >= gap).all()
    _descent_keeps(rc, pairs, apart, q, d, gap, lo, hi, starts=16, steps=60)
    # the pairs of few joints whose samples keep 20 mm: nearly all proven (the bound is not vacuous)
    M = _reach._column_reach(rc)[1][:, : rc._counts[0]]
    easy = ((M[:, i] ^ M[:, j]).sum(0) <= 3) & (sampled >= gap + 0.005)
    assert int((easy & ~apart).sum()) <= int(easy.sum()) // 20
    # remembered for the copies of one robot: no second proof
    calls = []
    prove = _reach._prove_apart
    monkeypatch.setattr(_reach, "_prove_apart", lambda *a: calls.append(1) or prove(*a))
    again, _, _ = _reach.pairs_apart(rc.allow_collisions(probs["box/0001"].scene.allowed), pairs, gap)
    assert not calls and torch.equal(again, apart)


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_c_search_and_decisions_equal_without_the_pairs_proven_apart(panda, dtype):
    """The C decisions leave out the self pairs proven apart only where the proof covers what they decide
    (configurations within the limits, slacks up to 3 eta): the same paths, iterations, decisions and trees
    as with every pair, the same verdicts on random configurations and edges, and every pair's decisions for a
    configuration outside the limits or a larger slack."""
    chain, rc, probs = panda
    if dtype == torch.float32:
        rc = copy.deepcopy(rc).float()
        chain = rc.chain.float()
    names = ["cage/0001", "box/0019", "bookshelf_small/0041", "table_pick/0019"]
    qs, qg, world, _ = _batch(probs, names)
    qs, qg, world = qs.to(dtype), qg.to(dtype), world.to(dtype)
    lim = chain.q_limits
    rows = torch.arange(len(names))
    q = random_configuration(chain, (2000,), generator=torch.Generator().manual_seed(4)).to(dtype)
    wid = torch.arange(2000) % len(names)
    runs = []
    for left_out in (True, False):
        checker = EdgeChecker(rc, world, 0.0, 0.005)
        planner = checker.native(qs)
        if not left_out:
            planner.pruned = None  # every pair's decisions in every call
        if left_out:
            full = ctypes.addressof(planner.collide)
            assert planner.collide_for(q, 0.015) != full  # within the limits: the pairs left out
            assert planner.collide_for(q, 0.016) == full  # a larger slack than the proof's
            out = q.clone()
            out[0, 3] = lim[3, 1] + 0.01
            assert planner.collide_for(out, 0.005) == full  # a configuration past a limit
        search = search_native(checker, qs, qg, lim[:, 0], lim[:, 1], rows, None, max_iterations=20000,
                               step=1.0, shortcut_tries=16, seed=2, rungs=4)
        verdict = checker.clear(q, wid)
        edges = checker.edges(q[:200], q[200:400], wid[:200])
        runs.append((search, verdict, edges))
    (s1, v1, e1), (s2, v2, e2) = runs
    assert s1[2].all() and torch.equal(s1[0], s2[0]) and torch.equal(s1[1], s2[1])
    for key in ("iterations", "checked", "nodes"):
        assert torch.equal(s1[3][key], s2[3][key]), key
    assert torch.equal(v1, v2) and 0 < int(v1.sum()) < 2000
    assert torch.equal(e1[0], e2[0]) and 0 < int(e1[0].sum()) < 200


def test_pair_distance_bound_holds_in_random_boxes(panda):
    """The bound under pairs_apart, checked alone, every pair however many joints move it: in 4 000 random
    boxes of joint space (half-widths up to 0.5 rad), at 32 random configurations of each box, the distance is
    never below the distance at the centre less the bound's terms, and each joint's speed bound (Siciliano
    (3.30): a point turns about an axis no faster than its distance from it) holds: that distance at the
    configuration (the term of a box of width 1e-9 there) within its bound at the centre plus the change the
    joints between allow."""
    from diffkin.motion._reach import _PairBound

    chain, rc, _ = panda
    pairs = rc._pairs_00
    bound = _PairBound(rc, pairs)
    g = torch.Generator().manual_seed(5)
    lim = chain.q_limits
    N, S, eps = 4000, 32, 1e-9
    which = torch.randint(pairs.shape[0], (N,), generator=g)
    c = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * torch.rand(N, 7, generator=g, dtype=F64)
    h = 0.5 * torch.rand(N, 7, generator=g, dtype=F64)
    with torch.no_grad():
        d, term = bound(which, c, h)
        q = (c[:, None] + h[:, None] * (2 * torch.rand(N, S, 7, generator=g, dtype=F64) - 1)).reshape(-1, 7)
        dq, speed = bound(which.repeat_interleave(S), q, torch.full((N * S, 7), eps, dtype=F64))
    low = (d - term.sum(-1)).repeat_interleave(S)
    assert (dq >= low - 1e-12).all()
    moving = bound.J[which].repeat_interleave(S, 0)  # (N S, nq)
    most = (term / h).repeat_interleave(S, 0)
    assert (speed[moving] / eps <= most[moving] + 1e-9).all()
    assert float((speed / eps - most)[moving].amax()) > -0.05  # the speed bound comes close somewhere
    assert float((dq - low).reshape(N, S).amin(1).median()) < 0.15  # and the bound within 15 cm at the median


def _mjcf_capsules(name: str, end: str):
    """A Menagerie MJCF arm (capsule geoms, proper segments) as (chain, RobotCollision), float64."""
    import warnings
    from pathlib import Path

    path = Path(__file__).parent / "data" / "mjcf" / name
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        chain = models.from_mjcf(path, end, dtype=F64).requires_grad_(False)
        rc = RobotCollision.from_mjcf(path, chain).requires_grad_(False)
    return chain, rc


@pytest.mark.parametrize("name", ["universal_robots_ur5e/ur5e.xml", "universal_robots_ur10e/ur10e.xml"])
def test_pairs_apart_and_its_bound_on_capsules(name):
    """The bound and the proof on arms of proper capsules (segments, where the moved geom's two ends differ:
    the spherized Panda has none): in random boxes of joint space the distance never falls below the
    bound, each joint's speed term holds at sampled configurations, and every pair proven 15 mm apart stays so
    in 20 000 random configurations and after gradient descent on its distance."""
    from diffkin.motion._reach import _PairBound, pairs_apart

    chain, rc = _mjcf_capsules(name, "wrist_3_link")
    pairs = rc._pairs_00
    assert bool((rc.capsule_a != rc.capsule_b).any(-1).all())  # all 9 proper segments
    i, j = pairs[:, 0], pairs[:, 1]
    bound = _PairBound(rc, pairs)
    g = torch.Generator().manual_seed(6)
    lim = chain.q_limits
    N, S, eps = 2000, 16, 1e-9
    which = torch.randint(pairs.shape[0], (N,), generator=g)
    c = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * torch.rand(N, chain.nq, generator=g, dtype=F64)
    h = 0.5 * torch.rand(N, chain.nq, generator=g, dtype=F64)
    with torch.no_grad():
        d, term = bound(which, c, h)
        q = (c[:, None] + h[:, None] * (2 * torch.rand(N, S, chain.nq, generator=g, dtype=F64) - 1))
        dq, speed = bound(which.repeat_interleave(S), q.reshape(-1, chain.nq),
                          torch.full((N * S, chain.nq), eps, dtype=F64))
    assert (dq >= (d - term.sum(-1)).repeat_interleave(S) - 1e-12).all()
    moving = bound.J[which].repeat_interleave(S, 0)
    assert (speed[moving] / eps <= (term / h).repeat_interleave(S, 0)[moving] + 1e-9).all()
    gap = 0.015
    apart, lo, hi = pairs_apart(rc, pairs, gap)
    assert 0 < int(apart.sum()) < pairs.shape[0]  # (6 of 21 on the UR5e)
    x = lo + (hi - lo) * torch.rand(20_000, chain.nq, generator=g, dtype=F64)
    dd = _gaps(rc, i, j, x)  # (N, P)
    assert (dd[:, apart].amin(0) >= gap).all()
    _descent_keeps(rc, pairs, apart, x, dd, gap, lo, hi, starts=8, steps=40)


def test_c_calls_leave_out_the_proven_pairs_only_where_the_proof_covers_them(panda, monkeypatch):
    """Each C call (search, decisions, edges, point shortcuts) gets the decisions without the pairs proven
    apart only where every configuration it decides lies within the limits and no slack passes 3 eta: a
    sampling box, a start or an edge end past a limit, a resolution or a slack larger than the checker's
    get every pair's."""
    from diffkin.motion import _native_search as ns
    from diffkin.motion._search import row_keys

    chain, rc, probs = panda
    qs, qg, world, _ = _batch(probs, ["box/0019", "table_pick/0019"])
    checker = EdgeChecker(rc, world, 0.0, 0.005)
    planner = checker.native(qs)
    full, pruned = ctypes.addressof(planner.collide), ctypes.addressof(planner.pruned[0])
    seen = []
    run = ns._run
    monkeypatch.setattr(ns, "_run", lambda which, a, what: seen.append(a.collide) or run(which, a, what))
    lim = chain.q_limits
    lo, hi = lim[:, 0].clone(), lim[:, 1].clone()
    rows = torch.arange(2)

    def search(qs=qs, lo=lo, hi=hi, eta=None, rungs=4):
        seen.clear()
        ns.search_native(checker, qs, qg, lo, hi, rows, eta, max_iterations=200, step=1.0, shortcut_tries=0,
                         seed=0, rungs=rungs)
        return seen[-1]

    assert search() == pruned
    wide = lo.clone()
    wide[2] -= 0.1
    assert search(lo=wide) == full  # a sampling box past a limit
    out = qs.clone()
    out[0, 3] = lim[3, 1] + 0.01
    assert search(qs=out) == full  # a start past a limit
    assert search(eta=torch.full((2,), 0.005, dtype=F64), rungs=0) == pruned
    assert search(eta=torch.full((2,), 0.006, dtype=F64), rungs=0) == full  # a coarser resolution
    q = random_configuration(chain, (64,), generator=torch.Generator().manual_seed(7)).to(F64)
    for slack, want in ((0.015, pruned), (0.0151, full)):
        seen.clear()
        planner.decide(q, None, slack)
        assert seen[-1] == want
    steps = torch.full((32,), 8, dtype=torch.long)
    past = out[:1].expand(32, 7)  # edge ends past a limit
    for slack, end, want in ((0.005, q[32:], pruned), (0.0051, q[32:], full), (0.005, past, full)):
        seen.clear()
        planner.edges(q[:32], end, steps, torch.full((32,), slack, dtype=F64), None, False)
        assert seen[-1] == want
    path = torch.stack((qs, (qs + qg) / 2, qg), 1)
    checker.set_row_resolution(torch.full((2,), 0.005, dtype=F64))
    seen.clear()
    ns.shortcut_points_native(checker, path, torch.full((2,), 3), rows, 1, row_keys(qs, qg, 0), 2, 1)
    assert seen[-1] == pruned
