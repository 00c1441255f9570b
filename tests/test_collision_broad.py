"""The broad phase of the IK's collision decisions (``RobotCollision._distances_at_least``, diffkin/collision/
broad.py) against the exact public distances, the closed-form segment–box distance against coal, and the
memos of the placement and of the collision-free seed library against fresh models."""

from __future__ import annotations

import copy
import warnings

import collision_reference as ref
import numpy as np
import pytest
import torch
from test_collision_robot import BOXY, FR3

import diffkin
from diffkin import ik
from diffkin.collision import RobotCollision, World, box
from diffkin.collision.boxes import capsule_box
from diffkin.kernels.joints import origin_transform

SRDF = ('<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" reason="Default"/>'
        '</robot>')


def _robot(name, dtype):
    source, end, srdf = (FR3, "fr3_link8", SRDF) if name == "fr3" else (BOXY, "l3", None)
    chain = diffkin.models.from_urdf(source, end, dtype=dtype).requires_grad_(False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's meshes are not shipped
        return chain, RobotCollision.from_urdf(source, chain, srdf=srdf).requires_grad_(False)


def _world(dtype):
    """Every kind of object, placed where the arms reach: spheres, a capsule, two rotated boxes (one flat),
    a half-space (the floor) and points."""
    t = lambda x: torch.tensor(x, dtype=dtype)  # noqa: E731
    boxes = box(center=t([[0.45, 0.0, 0.2], [0.0, 0.35, 0.45]]), half_extents=t([[0.1, 0.3, 0.02],
                [0.05, 0.08, 0.12]]), rpy=t([[0.0, 0.0, 0.3], [0.4, -0.2, 1.0]]), dtype=dtype)
    return World(spheres=t([[0.4, 0.2, 0.5, 0.1], [0.1, -0.3, 0.3, 0.05]]),
                 capsules=t([[0.3, -0.3, 0.2, 0.3, 0.3, 0.7, 0.04]]), boxes=boxes,
                 halfspaces=t([[0.0, 0.0, 1.0, -0.02]]), points=t([[0.3, 0.1, 0.6], [0.0, 0.0, 0.9]]),
                 dtype=dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", ["fr3", "boxy"])
def test_broad_phase_is_exact_below_the_threshold_and_above_it_elsewhere(name, dtype):
    chain, rc = _robot(name, dtype)
    w = _world(dtype)
    lo, hi = chain.q_limits.T
    g = torch.Generator().manual_seed(0)
    q = lo + (hi - lo) * torch.rand(3000, chain.n_joints, dtype=dtype, generator=g)
    with torch.no_grad():
        exact = torch.cat((rc.self_distances(q), rc.world_distances(q, w).flatten(-2)), -1)
        assert torch.equal(rc._distances_at_least(q, w), exact)  # no threshold: the exact distances
        for threshold in (-0.01, 0.0, 1e-4, 0.05):
            d = rc._distances_at_least(q, w, threshold)
            below = (exact < threshold) | (d < threshold)
            assert below.any() and (~below).any()
            assert torch.equal(d[below], exact[below])  # bit for bit: the same decisions
            assert bool((d[~below] >= threshold).all())
            assert bool((d <= exact + 1e-5 * (1 + exact.abs())).all())  # a lower bound where it differs
            assert bool((d != exact).any())  # the bounds did skip exact evaluations
            # the decisions of the IK: every distance >= threshold, per row
            assert torch.equal((d >= threshold).all(-1), (exact >= threshold).all(-1))
    if name == "boxy":  # capsule-box and box-box self pairs exist here
        assert rc._pairs_01.numel() and rc._pairs_11.numel()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", ["fr3", "boxy"])
def test_clear_decides_as_the_exact_distances(name, dtype):
    """``RobotCollision._clear`` (the three-stage broad phase of the IK's decisions; boxes on the robot go
    through ``_distances_at_least``) against every exact public distance, per row, with and without a world
    of every kind of object, for margins and slacks of both signs; batch dims kept."""
    chain, rc = _robot(name, dtype)
    lo, hi = chain.q_limits.T
    g = torch.Generator().manual_seed(4)
    q = lo + (hi - lo) * torch.rand(3000, chain.n_joints, dtype=dtype, generator=g)
    tol = 1e-5 if dtype == torch.float32 else 1e-12  # rounding of two layouts of the same formulas
    mixed = 0
    with torch.no_grad():
        for w in (None, _world(dtype)):
            exact = rc.self_distances(q)
            if w is not None:
                exact = torch.cat((exact, rc.world_distances(q, w).flatten(-2)), -1)
            for margin, slack in ((0.0, 0.0), (0.01, 1e-4), (-0.01, 0.0), (0.03, 0.0)):
                ok = rc._clear(q, w, margin, slack)
                g = (exact - margin - slack).amin(-1)
                sure = g.abs() > tol
                assert torch.equal(ok[sure], (g >= 0)[sure])
                assert int((~sure).sum()) <= 3
                mixed += bool(ok.any() and (~ok).any())
            assert torch.equal(rc._clear(q[:12].reshape(3, 4, -1), w), rc._clear(q[:12], w).reshape(3, 4))
            assert rc._clear(q[:0], w).shape == (0,)
    assert mixed >= 4  # the decisions are not all alike


@pytest.mark.parametrize("name", ["fr3", "boxy"])
def test_clear_leaves_out_what_moving_only_leaves_out(name):
    """With ``moving_only`` (the IK's default, ``skip_fixed``) the broad phase decides as the exact
    distances of the columns ``_distances_at_least(moving_only=True)`` keeps: a floor through the base and a
    sphere on it (geoms fixed to the base against them are left out, and geoms whose joints turn about the
    floor's normal against the floor), margins of both signs."""
    chain, rc = _robot(name, torch.float64)
    q = chain.random_configuration((2000,), generator=torch.Generator().manual_seed(9))
    w = World(spheres=torch.tensor([[-0.2, 0.0, 0.05, 0.08], [0.5, 0.2, 0.4, 0.1]], dtype=torch.float64),
              halfspaces=torch.tensor([[0.0, 0.0, 1.0, 0.02]], dtype=torch.float64), dtype=torch.float64)
    kept, skipped = 0, 0
    with torch.no_grad():
        full = rc._distances_at_least(q, w)
        moving = rc._distances_at_least(q, w, moving_only=True)
        assert moving.shape[-1] < full.shape[-1]  # something is left out
        for margin in (0.0, 0.01, -0.01):
            ok = rc._clear(q, w, margin, 0.0, moving_only=True)
            g = (moving - margin).amin(-1)
            sure = g.abs() > 1e-12
            assert torch.equal(ok[sure], (g >= 0)[sure])
            kept += int(ok.sum())
            skipped += int((ok & ((full - margin).amin(-1) < 0)).sum())
    assert kept > 0 and skipped > 0  # the left-out entries decided some rows


def test_native_link_frames_match_the_torch_frames():
    """The link frames of the collision geometry from one fused C FK call (no gradient, CPU) against the
    torch all-frames FK (the path taken with a gradient), batch dims kept."""
    if not diffkin.kernels.native.available():
        pytest.skip("the native library is not built here")
    chain, rc = _robot("fr3", torch.float64)
    q = chain.random_configuration((4, 25), generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        native = rc._frames._native_frames(chain, q)
        assert native is not None
        assert torch.equal(rc._frames.frames(chain, q), native)
    torch_frames = rc._frames.frames(chain, q.clone().requires_grad_(True))
    assert torch_frames.requires_grad
    torch.testing.assert_close(native, torch_frames.detach(), rtol=0, atol=1e-12)


def test_broad_phase_gradients_match_the_exact_ones_where_exact():
    chain, rc = _robot("fr3", torch.float64)
    w = _world(torch.float64)
    q = chain.random_configuration((64,), generator=torch.Generator().manual_seed(2)).requires_grad_(True)
    exact = torch.cat((rc.self_distances(q), rc.world_distances(q, w).flatten(-2)), -1)
    d = rc._distances_at_least(q, w, 0.05)
    near = (exact.detach() < 0.05).nonzero()[:20]
    for r, k in near.tolist():
        ge, = torch.autograd.grad(exact[r, k], q, retain_graph=True)
        gd, = torch.autograd.grad(d[r, k], q, retain_graph=True)
        torch.testing.assert_close(gd, ge)


def test_segment_box_closed_form_against_coal():
    """Random segments (degenerate ones, ones parallel to a face) against random oriented boxes (flat ones):
    the capsule-box distance of radius 0.01 against coal's capsule-box distance."""
    g = torch.Generator().manual_seed(5)
    n = 400
    a = torch.randn(n, 3, dtype=torch.float64, generator=g)
    b = a + torch.randn(n, 3, dtype=torch.float64, generator=g)
    b[:40] = a[:40]  # spheres
    b[40:80, 2] = a[40:80, 2]  # parallel to the boxes' xy faces (axis-aligned boxes below)
    c = 0.3 * torch.randn(n, 3, dtype=torch.float64, generator=g)
    rpy = torch.randn(n, 3, dtype=torch.float64, generator=g)
    rpy[40:80] = 0.0
    R = origin_transform(torch.zeros_like(rpy), rpy)[..., :3, :3]
    h = 0.05 + 0.4 * torch.rand(n, 3, dtype=torch.float64, generator=g)
    h[80:120, 1] = 1e-3  # flat
    r = torch.full((n,), 0.01, dtype=torch.float64)
    d = capsule_box(a, b, r, c, R, h)
    want = np.array([ref.distance(*ref.capsule(a[i].numpy(), b[i].numpy(), 0.01),
                                  *ref.box(c[i].numpy(), R[i].numpy(), h[i].numpy())) for i in range(n)])
    apart = want > 1e-6
    assert apart.sum() > 200
    np.testing.assert_allclose(d.numpy()[apart], want[apart], atol=1e-9)


def test_placement_memo_follows_in_place_edits_of_the_geometry_and_the_chain():
    chain, rc = _robot("fr3", torch.float64)
    q = chain.random_configuration((50,), generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        rc.self_distances(q)  # remembered
        rc.capsule_a.add_(0.01)
        chain.origin_xyz[2].add_(0.02)
        fresh = copy.deepcopy(rc)  # new tensors: nothing remembered applies
        fresh.__dict__.pop("_placement_memo", None)
        torch.testing.assert_close(rc.self_distances(q), fresh.self_distances(q), rtol=0, atol=0)
        assert not torch.equal(rc.self_distances(q), _robot("fr3", torch.float64)[1].self_distances(q))


def test_seed_library_memo_gives_the_solve_of_a_fresh_model():
    chain, rc = _robot("fr3", torch.float32)
    full = _world(torch.float32)
    w = World(spheres=full.spheres, capsules=full.capsules, boxes=full.boxes)  # (the floor touches the base)
    q = chain.random_configuration((200,), generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        q = q[rc.min_distance(q, w) >= 0.01][:40]
    assert len(q) >= 20
    T = chain.forward_kinematics(q)
    kw = dict(seed=0, collision=rc, position_tolerance=1e-4, orientation_tolerance=1e-3)
    first = ik.solve(chain, T, world=w, **kw)
    assert hasattr(rc, "_free_library_memo")
    again = ik.solve(chain, T, world=w, **kw)  # the memo serves
    assert torch.equal(first.q, again.q) and torch.equal(first.success, again.success)
    w2 = World(spheres=torch.tensor([[0.3, 0.0, 0.5, 0.15]]), boxes=w.boxes)  # a new world: no memo applies
    with torch.no_grad():
        rc.capsule_radius.add_(0.005)  # and the model changed in place
    got = ik.solve(chain, T, world=w2, **kw)
    fresh = copy.deepcopy(rc)
    fresh.chain = chain  # the copy's geometry on the chain solved (a deep copy copies the chain too)
    for k in ("_free_library_memo", "_placement_memo", "_kept_memo"):
        fresh.__dict__.pop(k, None)
    want = ik.solve(chain, T, world=w2, **{**kw, "collision": fresh})
    assert torch.equal(got.q, want.q) and torch.equal(got.success, want.success)
    with torch.no_grad():
        assert bool((rc.min_distance(got.q[got.success], w2) >= 0).all())


@pytest.mark.parametrize("name", ["fr3", "boxy"])
def test_broad_phase_with_leading_dims_and_one_world_per_row(name):
    chain, rc = _robot(name, torch.float64)
    w = _world(torch.float64)
    g = torch.Generator().manual_seed(6)
    q = chain.random_configuration((4, 50), generator=g)
    jitter = 0.05 * torch.randn(4, 1, *w.spheres.shape, dtype=torch.float64, generator=g).clamp(-1, 1)
    wb = World(spheres=w.spheres + jitter, capsules=w.capsules, boxes=w.boxes, halfspaces=w.halfspaces,
               points=w.points)
    with torch.no_grad():
        exact = torch.cat((rc.self_distances(q).expand(4, 50, -1), rc.world_distances(q, wb).flatten(-2)), -1)
        d = rc._distances_at_least(q, wb, 0.01)
    below = (exact < 0.01) | (d < 0.01)
    assert d.shape == exact.shape and below.any()
    assert torch.equal(d[below], exact[below]) and bool((d[~below] >= 0.01).all())
