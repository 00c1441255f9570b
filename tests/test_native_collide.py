"""The fused C pass of the collision decisions (``native.capsules_clear``, ``_native_collide.c``) against
the closed-form torch distances of ``diffkin.collision.distances`` entry by entry: random capsules with
degenerate ones among them (points, parallel and crossing segments, zero radius), round world objects and
half-spaces, float32 and float64, margins and slacks of both signs, left-out entries."""

from __future__ import annotations

import pytest
import torch

from diffkin.collision.distances import capsule_capsule, capsule_halfspace
from diffkin.kernels import native

pytestmark = pytest.mark.skipif(not native.available(), reason="the native library is not built here")


def _capsules(G: int, N: int, dtype, g):
    """G capsules in N lanes; the first block of 256 lanes clustered (as the samples of one edge), so the
    pass's per-block broad phase skips entries there."""
    A = torch.rand(G, 3, N, dtype=dtype, generator=g) - 0.5
    D = 0.3 * (torch.rand(G, 3, N, dtype=dtype, generator=g) - 0.5)
    near = min(N, 256)
    A[..., :near] = A[..., :1] + 0.02 * (torch.rand(G, 3, near, dtype=dtype, generator=g) - 0.5)
    D[..., :near] = D[..., :1] + 0.02 * (torch.rand(G, 3, near, dtype=dtype, generator=g) - 0.5)
    B = A + D
    B[0] = A[0]  # a point (a sphere)
    B[1] = A[1] + (B[2] - A[2])  # parallel to capsule 2
    r = 0.1 * torch.rand(G, dtype=dtype, generator=g)
    r[3] = 0.0
    return A, B, r


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_every_entry_decides_as_the_torch_distance(dtype):
    g = torch.Generator().manual_seed(3)
    G, N = 6, 700
    A, B, r = _capsules(G, N, dtype, g)
    wa = torch.rand(4, 3, dtype=dtype, generator=g) - 0.5
    wb = wa.clone()
    wb[1:3] += 0.2  # spheres/points (0, 3) and capsules (1, 2)
    wr = torch.tensor([0.05, 0.02, 0.0, 0.0], dtype=dtype)
    hs = torch.tensor([[0.0, 0.0, 1.0, 0.1], [0.6, 0.0, 0.8, -0.2]], dtype=dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    none3, none0 = (A.new_zeros(0, 3),) * 2, A.new_zeros(0)
    checked = 0
    for margin, slack in ((0.0, 0.0), (0.02, 1e-4), (-0.03, 0.0)):
        for i in range(G):
            for j in range(i + 1, G):
                d = capsule_capsule(A[i].T, B[i].T, r[i], A[j].T, B[j].T, r[j])  # (N,)
                ok = torch.ones(N, dtype=torch.bool)
                pair = torch.tensor([[i, j]])
                assert native.capsules_clear(A, B, r, pair, (*none3, none0), A.new_zeros(0, 4), None, None,
                                             margin, slack, ok)
                sure = (d - margin - slack).abs() > tol
                assert torch.equal(ok[sure], (d - margin >= slack)[sure]), (i, j)
                checked += int(sure.sum())
        for w in range(4):
            skip = torch.ones(G, 4, dtype=torch.bool)
            for k in range(G):
                skip[k, w] = False
                d = capsule_capsule(A[k].T, B[k].T, r[k], wa[w], wb[w], wr[w])
                ok = torch.ones(N, dtype=torch.bool)
                assert native.capsules_clear(A, B, r, torch.zeros(0, 2, dtype=torch.long), (wa, wb, wr),
                                             A.new_zeros(0, 4), skip, None, margin, slack, ok)
                sure = (d - margin - slack).abs() > tol
                assert torch.equal(ok[sure], (d - margin >= slack)[sure]), (k, w)
                skip[k, w] = True
        for h in range(2):
            d = capsule_halfspace(A.permute(2, 0, 1), B.permute(2, 0, 1), r, hs[h, :3], hs[h, 3]).amin(-1)
            ok = torch.ones(N, dtype=torch.bool)
            skip_h = torch.ones(G, 2, dtype=torch.bool)
            skip_h[:, h] = False
            assert native.capsules_clear(A, B, r, torch.zeros(0, 2, dtype=torch.long), (*none3, none0), hs,
                                         None, skip_h, margin, slack, ok)
            sure = (d - margin - slack).abs() > tol
            assert torch.equal(ok[sure], (d - margin >= slack)[sure]), h
    assert checked > 10 * N


def test_a_skipped_entry_takes_no_part_and_cuda_is_not_served():
    dtype = torch.float64
    A = torch.zeros(1, 3, 5, dtype=dtype)
    B = A.clone()
    r = torch.tensor([0.1], dtype=dtype)
    inside = (A.new_zeros(1, 3), A.new_zeros(1, 3), A.new_full((1,), 0.1))
    ok = torch.ones(5, dtype=torch.bool)
    native.capsules_clear(A, B, r, torch.zeros(0, 2, dtype=torch.long), inside, A.new_zeros(0, 4), None, None,
                          0.0, 0.0, ok)
    assert not ok.any()
    ok = torch.ones(5, dtype=torch.bool)
    native.capsules_clear(A, B, r, torch.zeros(0, 2, dtype=torch.long), inside, A.new_zeros(0, 4),
                          torch.ones(1, 1, dtype=torch.bool), None, 0.0, 0.0, ok)
    assert ok.all()
    half = A.to(torch.float16)
    assert not native.capsules_clear(half, half, r, torch.zeros(0, 2, dtype=torch.long), inside,
                                     A.new_zeros(0, 4), None, None, 0.0, 0.0, ok)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_boxes_cylinders_and_per_row_worlds_decide_as_the_torch_distances(dtype):
    """Boxes (against spheres at margins of both signs, against proper segments at margin + slack >= 0, the
    contract) and cylinders (against the sphere geoms ``points`` marks; the others take no part), each
    configuration with its own world of a stack of three (``world_index``), entry by entry against
    ``capsule_box`` and ``sphere_cylinder`` of the torch layer."""
    from diffkin.collision import box
    from diffkin.collision.boxes import capsule_box
    from diffkin.collision.cylinders import sphere_cylinder

    g = torch.Generator().manual_seed(5)
    G, N, nw = 6, 600, 3
    A, B, r = _capsules(G, N, dtype, g)
    points = torch.zeros(G, dtype=torch.bool)
    points[0] = True
    B[4] = A[4]
    points[4] = True  # two spheres
    bc = 0.6 * (torch.rand(nw, 2, 3, dtype=dtype, generator=g) - 0.5)
    bR = box(bc, bc.abs(), torch.rand(nw, 2, 3, dtype=dtype, generator=g) * 3).rotation
    bh = 0.05 + 0.2 * torch.rand(nw, 2, 3, dtype=dtype, generator=g)
    bh[1, 1, 2] = 0.0  # a flat box
    ya = 0.6 * (torch.rand(nw, 2, 3, dtype=dtype, generator=g) - 0.5)
    yb = ya + 0.4 * (torch.rand(nw, 2, 3, dtype=dtype, generator=g) - 0.5)
    yr = 0.02 + 0.15 * torch.rand(nw, 2, dtype=dtype, generator=g)
    wid = torch.randint(0, nw, (N,), generator=g)
    wid[:256] = 1  # the clustered block in one world: the broad phase against the objects runs there
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    none3, none0 = (A.new_zeros(nw, 0, 3),) * 2, A.new_zeros(nw, 0)
    no_pairs = torch.zeros(0, 2, dtype=torch.long)
    a, b = A.permute(2, 0, 1), B.permute(2, 0, 1)  # (N, G, 3)
    checked = {"box": 0, "cylinder": 0}
    dist = {("box", w): capsule_box(a, b, r, bc[wid, None, w], bR[wid, None, w], bh[wid, None, w])
            for w in range(2)}  # (N, G)
    for w in range(2):  # cylinders: the sphere geoms only (the closed-form field)
        dist[("cylinder", w)] = sphere_cylinder(a, r, ya[wid, None, w], yb[wid, None, w], yr[wid, None, w])
    for margin, slack in ((0.0, 0.0), (0.02, 1e-4), (-0.03, 0.0)):
        for kind in ("box", "cylinder"):
            for w in range(2):
                d = dist[(kind, w)]
                every = torch.ones(G, dtype=torch.bool)
                serve = points if kind == "cylinder" or margin + slack < 0 else every
                for k in range(G):
                    skip = torch.ones(G, 2, dtype=torch.bool)
                    skip[k, w] = False
                    ok = torch.ones(N, dtype=torch.bool)
                    extra = dict(boxes=(bc, bR, bh), skip_box=skip) if kind == "box" else \
                        dict(cylinders=(ya, yb, yr), skip_cylinder=skip)
                    assert native.capsules_clear(A, B, r, no_pairs, (*none3, none0), A.new_zeros(nw, 0, 4),
                                                 None, None, margin, slack, ok, points=points,
                                                 world_index=wid, **extra)
                    if not serve[k]:
                        if kind == "cylinder":  # proper segments take no part against cylinders
                            assert ok.all()
                        continue
                    sure = (d[:, k] - margin - slack).abs() > tol
                    bad = (ok != (d[:, k] - margin >= slack)) & sure
                    assert not bad.any(), (kind, k, w, margin, d[bad, k], ok[bad])
                    checked[kind] += int(sure.sum())
    assert min(checked.values()) > 4 * N


def test_the_block_broad_phase_keeps_a_near_entry():
    """A block of 256 lanes of one sphere 15 mm from a box, a cylinder, a sphere and another robot sphere
    (each alone), margin 20 mm: the per-block boxes of the pass are close to the entries themselves there, so
    only a bound that stays below the distance keeps these entries (not clear); 25 mm away they are clear."""
    dtype = torch.float64
    g = torch.Generator().manual_seed(2)
    r = torch.tensor([0.05, 0.05], dtype=dtype)
    points = torch.ones(2, dtype=torch.bool)
    no_pairs, pair = torch.zeros(0, 2, dtype=torch.long), torch.tensor([[0, 1]])
    none = (torch.zeros(0, 3, dtype=dtype),) * 2 + (torch.zeros(0, dtype=dtype),)
    hs = torch.zeros(0, 4, dtype=dtype)
    for gap, clear in ((0.015, False), (0.025, True)):
        x = 0.2 + 0.05 + gap
        A = torch.zeros(2, 3, 256, dtype=dtype)
        A[0, 0] = x + 1e-5 * torch.rand(256, dtype=dtype, generator=g)
        A[1, 0] = 5.0  # the second sphere far away, but for the self pair
        cases = [dict(boxes=(torch.zeros(1, 3, dtype=dtype), torch.eye(3, dtype=dtype)[None],
                             torch.full((1, 3), 0.2, dtype=dtype))),
                 dict(cylinders=(torch.tensor([[0.0, 0.0, -0.2]], dtype=dtype),
                                 torch.tensor([[0.0, 0.0, 0.2]], dtype=dtype),
                                 torch.tensor([0.2], dtype=dtype)))]
        for extra in cases:
            ok = torch.ones(256, dtype=torch.bool)
            assert native.capsules_clear(A, A, r, no_pairs, none, hs, None, None, 0.02, 0.0, ok,
                                         points=points, **extra)
            assert bool(ok.all()) == clear and bool(ok.any()) == clear
        ok = torch.ones(256, dtype=torch.bool)  # a round object: a sphere of 0.2 at the origin
        ball = (torch.zeros(1, 3, dtype=dtype),) * 2 + (torch.tensor([0.2], dtype=dtype),)
        assert native.capsules_clear(A, A, r, no_pairs, ball, hs, None, None, 0.02, 0.0, ok, points=points)
        assert bool(ok.all()) == clear and bool(ok.any()) == clear
        B2 = A.clone()
        B2[1, 0] = 0.2 - 0.05 + 1e-5 * torch.rand(256, dtype=dtype, generator=g)  # a robot sphere instead
        ok = torch.ones(256, dtype=torch.bool)
        assert native.capsules_clear(B2, B2, r, pair, none, hs, None, None, 0.02, 0.0, ok, points=points)
        assert bool(ok.all()) == clear and bool(ok.any()) == clear


@pytest.mark.parametrize("N", [64, 4, 3])
def test_a_nan_geom_or_radius_is_never_clear(N):
    """A geom NaN in some lanes of a block (the bounding boxes' min and max drop a NaN), or a NaN radius, is
    never culled as apart: those lanes are not clear, the others decide as without it (a review found NaN
    geoms declared clear by the boxes): 16 spheres (two groups of the broad phase), far from each other, a
    self pair and a box; in a block of 64 lanes and in ones of 4 and 3 (whose boxes are taken without a
    loop), NaN in each lane alone, in the last two and in all."""
    dtype = torch.float64
    G = 16
    r = torch.full((G,), 0.05, dtype=dtype)
    points = torch.ones(G, dtype=torch.bool)
    A = torch.zeros(G, 3, N, dtype=dtype)
    A[:, 0] = torch.arange(G, dtype=dtype)[:, None]  # a metre apart along x
    pairs = torch.tensor([[0, 9], [0, 1], [3, 12]])
    none = (torch.zeros(0, 3, dtype=dtype),) * 2 + (torch.zeros(0, dtype=dtype),)
    hs = torch.zeros(0, 4, dtype=dtype)
    box = dict(boxes=(torch.tensor([[0.0, 5.0, 0.0]], dtype=dtype), torch.eye(3, dtype=dtype)[None],
                      torch.full((1, 3), 0.2, dtype=dtype)))
    for world in ({}, box):
        ok = torch.ones(N, dtype=torch.bool)
        assert native.capsules_clear(A, A, r, pairs, none, hs, None, None, 0.0, 0.0, ok, points=points,
                                     **world)
        assert bool(ok.all())  # all clear without NaN
        for lanes in [[k] for k in range(min(N, 4))] + [[N - 2, N - 1], list(range(N))]:
            B = A.clone()
            B[0, 1, lanes] = float("nan")
            ok = torch.ones(N, dtype=torch.bool)
            assert native.capsules_clear(B, B, r, pairs, none, hs, None, None, 0.0, 0.0, ok, points=points,
                                         **world)
            want = torch.ones(N, dtype=torch.bool)
            want[lanes] = False
            assert torch.equal(ok, want), (world.keys(), lanes)
        bad = r.clone()
        bad[9] = float("nan")
        ok = torch.ones(N, dtype=torch.bool)
        assert native.capsules_clear(A, A, bad, pairs, none, hs, None, None, 0.0, 0.0, ok, points=points,
                                     **world)
        assert not bool(ok.any())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_blocks_of_one_to_four_spheres_decide_as_one_block_of_all(dtype):
    """Sphere models (the planner's: the ends are one tensor) in blocks of 1 to 4 lanes, whose per-sphere
    boxes are taken without a loop (an edge's first block), decide each lane as one block of all 128 lanes
    does, and both as the exact distances: 8 spheres (one group of the broad phase) each moving along a line,
    lanes in a shuffled order of their own; a box, a cylinder and a round object each met by one sphere in
    about a quarter of the lanes (those that move it forward), and two spheres of a self pair head on in
    about an eighth. So in a block the broad phase's boxes decide which entries are tested, and a box that
    missed a lane would change a decision."""
    from diffkin.collision import box
    from diffkin.collision.boxes import capsule_box
    from diffkin.collision.cylinders import sphere_cylinder

    g = torch.Generator().manual_seed(7)
    G, N = 8, 128
    base = 0.3 * torch.arange(G, dtype=dtype)[:, None] * torch.tensor([1.0, 0.5, 0.2], dtype=dtype)
    u = torch.nn.functional.normalize(torch.randn(G, 3, dtype=dtype, generator=g), dim=-1)
    s = torch.stack([torch.linspace(-1, 1, N, dtype=dtype)[torch.randperm(N, generator=g)] for _ in range(G)])
    A = (base[:, :, None] + 0.04 * u[:, :, None] * s[:, None, :]).contiguous()  # (G, 3, N), each on its line
    r = torch.full((G,), 0.03, dtype=dtype)
    points = torch.ones(G, dtype=torch.bool)
    out = 0.03 + 0.04 * 0.5  # each object's near side where its sphere is at s = 0.5: met for s > 0.5 or so
    bh = torch.full((1, 3), 0.02, dtype=dtype)
    bc = base[:1] + (out + 0.02) * u[:1]
    bR = box(bc, bh, torch.zeros(1, 3, dtype=dtype)).rotation
    z = torch.tensor([0.0, 0.0, 0.05], dtype=dtype)
    ya, yb = base[1:2] + (out + 0.02) * u[1:2] - z, base[1:2] + (out + 0.02) * u[1:2] + z
    yr = torch.tensor([0.02], dtype=dtype)
    ball = base[2:3] + (out + 0.02) * u[2:3]
    round_ = (ball, ball, torch.tensor([0.02], dtype=dtype))
    A[7] = base[3, :, None] + (2 * out + 0.04 * s[7]) * u[3, :, None]  # sphere 7 meets sphere 3 head on
    pairs = torch.tensor([[3, 7], [0, 5], [1, 6]])
    hs = torch.zeros(0, 4, dtype=dtype)
    world = dict(boxes=(bc, bR, bh), cylinders=(ya, yb, yr))

    def decide(lanes):
        X = A[:, :, lanes].contiguous()
        ok = torch.ones(len(lanes), dtype=torch.bool)
        assert native.capsules_clear(X, X, r, pairs, round_, hs, None, None, 0.0, 0.0, ok, points=points,
                                     **world)
        return ok

    whole = decide(list(range(N)))
    a = A.permute(2, 0, 1).contiguous()  # (N, G, 3)
    d = torch.cat([capsule_box(a, a, r, bc[None, 0], bR[None, 0], bh[None, 0]),
                   sphere_cylinder(a, r, ya[None, 0], yb[None, 0], yr[0]),
                   capsule_capsule(a, a, r, round_[0][None, 0], round_[1][None, 0], round_[2][0])]
                  + [capsule_capsule(a[:, i], a[:, i], r[i], a[:, j], a[:, j], r[j])[:, None]
                     for i, j in pairs.tolist()], dim=1)
    exact = (d >= 0).all(1)
    sure = (d.abs() > (1e-5 if dtype == torch.float32 else 1e-12)).all(1)
    assert 4 < int(whole.sum()) < N - 4  # both outcomes occur
    assert torch.equal(whole[sure], exact[sure])
    for m in (1, 2, 3, 4):
        blocks = torch.cat([decide(list(range(n0, min(n0 + m, N)))) for n0 in range(0, N, m)])
        assert torch.equal(blocks, whole), m
