"""Exact cylinders (diffkin.collision.cylinders) against coal (GJK / EPA, its own cylinder), finite gradients
in degenerate cases, gradcheck, and World obstacles that are cylinders through the pair table (distances,
broad phase, the decisions that the C pass does not serve).

Tolerances (float64): apart, 1e-7 m against coal with GJK tolerance 1e-10 (the search converges to ~3e-9);
in contact, 2e-6 m against coal's EPA (its default tolerance 1e-6; diffkin's value is a lower bound by
construction, so it may lie below coal's by EPA's tolerance, never above it by more than 1e-8). The
closed forms (point / sphere, half-space) agree to 1e-9.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffkin import collision as C
from diffkin.collision import World, box, cylinders

coal = pytest.importorskip("coal")
F64 = torch.float64


def _tf(R, p):
    T = coal.Transform3s()
    T.setRotation(np.asarray(R, dtype=float))
    T.setTranslation(np.asarray(p, dtype=float))
    return T


def _axis_frame(a, b):
    d = b - a
    L = np.linalg.norm(d)
    z = d / L
    x = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], 1), (a + b) / 2, L


def _coal_cylinder(a, b, r, cls=None):
    R, c, L = _axis_frame(a, b)
    return (cls or coal.Cylinder)(r, L), _tf(R, c)


def _coal_sd(g1, T1, g2, T2):
    req = coal.DistanceRequest()
    req.enable_signed_distance = True
    req.gjk_tolerance = 1e-10
    return coal.distance(g1, T1, g2, T2, req, coal.DistanceResult())


def _random_cylinder(rng):
    c = rng.uniform(-0.3, 0.3, 3)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    L, r = rng.uniform(0.05, 0.5), rng.uniform(0.02, 0.2)
    return c - d * L / 2, c + d * L / 2, r


def _random_box(rng):
    from scipy.spatial.transform import Rotation

    R = Rotation.random(random_state=rng).as_matrix()
    return rng.uniform(-0.3, 0.3, 3), R, rng.uniform(0.02, 0.25, 3)


def _pairs(kind: str, n: int, seed: int):
    """n random pairs (first solid of ``kind``, second a cylinder) as diffkin arguments and coal's d."""
    rng = np.random.default_rng(seed)
    rows, ref = [], []
    for _ in range(n):
        a, b, r = _random_cylinder(rng)
        g2, T2 = _coal_cylinder(a, b, r)
        if kind == "box":
            c, R, h = _random_box(rng)
            g1, T1 = coal.Box(*(2 * h)), _tf(R, c)
            rows.append((c, R, h, a, b, r))
        elif kind == "sphere":
            c, rs = rng.uniform(-0.3, 0.3, 3), rng.uniform(0.0, 0.2)
            g1, T1 = coal.Sphere(rs), _tf(np.eye(3), c)
            rows.append((c, rs, a, b, r))
        else:
            a1, b1, r1 = _random_cylinder(rng)
            g1, T1 = _coal_cylinder(a1, b1, r1, coal.Capsule if kind == "capsule" else coal.Cylinder)
            rows.append((a1, b1, r1, a, b, r))
        ref.append(_coal_sd(g1, T1, g2, T2))
    args = [torch.tensor(np.array([x[k] for x in rows]), dtype=F64) for k in range(len(rows[0]))]
    return args, np.array(ref)


_FN = {"sphere": C.sphere_cylinder, "capsule": C.capsule_cylinder, "box": C.box_cylinder,
       "cylinder": C.cylinder_cylinder}


def _depth_dense(p, a, b, r, k: int = 150):
    """The distance of a point inside a cylinder to its boundary by dense sampling of the boundary (side
    and both faces, ~k² points; independent of the closed form, within ~(h + r)/k)."""
    R, c, L = _axis_frame(a, b)
    t = np.linspace(0.0, 2 * np.pi, k, endpoint=False)
    z = np.linspace(-L / 2, L / 2, k)
    rad = np.linspace(0.0, r, k)
    side = np.stack([r * np.cos(t)[:, None].repeat(k, 1), r * np.sin(t)[:, None].repeat(k, 1),
                     z[None].repeat(k, 0)], -1).reshape(-1, 3)
    disc = np.stack([rad[None] * np.cos(t)[:, None], rad[None] * np.sin(t)[:, None], np.zeros((k, k))], -1)
    disc = disc.reshape(-1, 3)
    pts = np.concatenate([side, disc + [0, 0, L / 2], disc - [0, 0, L / 2]]) @ R.T + c
    return np.linalg.norm(pts - p, axis=-1).min()


def _check_against_coal(kind: str, n: int, seed: int) -> None:
    args, ref = _pairs(kind, n, seed)
    d = _FN[kind](*args).numpy()
    if kind == "sphere":  # coal's sphere-cylinder depth is wrong with the centre inside the cylinder (e.g.
        # -0.237 for -0.119): there the reference is the sphere radius plus the centre's sampled depth
        c, rs, a, b, r = (x.numpy() for x in args)
        inside = C.point_cylinder(*(torch.from_numpy(x) for x in (c, a, b, r))).numpy() < 0
        for i in np.flatnonzero(inside):
            ref[i] = -_depth_dense(c[i], a[i], b[i], r[i]) - rs[i]
        assert np.abs(d[inside] - ref[inside]).max() < 5e-3  # the sampling resolution
        ref[inside] = d[inside]
    ok = ref > -1e3  # coal's EPA returns -DBL_MAX on some deep cylinder pairs: no reference there
    apart, contact = ok & (ref > 0), ok & (ref <= 0)
    assert apart.sum() > n // 4 and contact.sum() > n // 20  # both regimes are exercised
    err = d - ref
    assert np.abs(err[apart]).max() < 1e-7, np.abs(err[apart]).max()
    assert np.abs(err[contact]).max() < 2e-6, np.abs(err[contact]).max()
    assert err[ok].max() < 1e-8  # a lower bound of the signed distance: never optimistic


@pytest.mark.parametrize("kind,n", [("sphere", 300), ("capsule", 250), ("box", 250), ("cylinder", 250)])
def test_cylinder_distances_match_coal(kind, n):
    _check_against_coal(kind, n, seed=1)


@pytest.mark.extended
@pytest.mark.parametrize("kind", ["sphere", "capsule", "box", "cylinder"])
def test_cylinder_distances_match_coal_sweep(kind):
    _check_against_coal(kind, 3000, seed=2)


def test_cylinder_halfspace_matches_coal():
    rng = np.random.default_rng(3)
    rows, ref = [], []
    for _ in range(200):
        a, b, r = _random_cylinder(rng)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        off = rng.uniform(-0.3, 0.3)
        g, T = _coal_cylinder(a, b, r)
        ref.append(_coal_sd(g, T, coal.Halfspace(n, off), _tf(np.eye(3), np.zeros(3))))
        rows.append((a, b, r, n, off))
    args = [torch.tensor(np.array([x[k] for x in rows]), dtype=F64) for k in range(5)]
    d = C.cylinder_halfspace(*args).numpy()
    np.testing.assert_allclose(d, ref, atol=1e-9, rtol=0)


def _degenerate_cases():
    """Pairs where the maximiser sits on a kink: parallel and crossing axes, axis-aligned boxes, touching
    solids, coincident centres."""
    z = lambda x: torch.tensor(x, dtype=F64)  # noqa: E731
    cyl = (z([0.0, 0, -0.2]), z([0.0, 0, 0.2]), z(0.1))
    out = [
        ("cylinder", (z([0.3, 0, -0.2]), z([0.3, 0, 0.2]), z(0.1)), cyl),  # parallel, side by side
        ("cylinder", (z([0.0, 0, 0.4]), z([0.0, 0, 0.8]), z(0.1)), cyl),  # coaxial, face to face
        ("cylinder", (z([0.0, 0, 0.2]), z([0.0, 0, 0.6]), z(0.1)), cyl),  # coaxial, touching
        ("cylinder", (z([-0.2, 0.0, 0.0]), z([0.2, 0, 0.0]), z(0.1)), cyl),  # crossing, coincident centres
        ("capsule", (z([0.2, 0, -0.2]), z([0.2, 0, 0.2]), z(0.05)), cyl),  # parallel capsule
        ("capsule", (z([0.0, 0, 0.0]), z([0.0, 0, 0.0]), z(0.05)), cyl),  # a sphere at the centre
        ("box", (z([0.3, 0, 0.0]), torch.eye(3), z([0.1, 0.1, 0.1])), cyl),  # axis-aligned box at the side
        ("box", (z([0.0, 0, 0.35]), torch.eye(3), z([0.2, 0.2, 0.15])), cyl),  # box face on the flat end
        ("box", (z([0.0, 0, 0.0]), torch.eye(3), z([0.1, 0.1, 0.1])), cyl),  # coincident centres
    ]
    return [(k, tuple(t.to(F64) for t in x), tuple(t.to(F64) for t in y)) for k, x, y in out]


def test_cylinder_gradients_are_finite_in_degenerate_cases():
    expect = [0.1, 0.2, 0.0, None, 0.05, None, 0.1, 0.0, None]  # the closed forms where there is one
    for (kind, x, y), want in zip(_degenerate_cases(), expect):
        xs = tuple(t.clone().requires_grad_(True) for t in x)
        ys = tuple(t.clone().requires_grad_(True) for t in y)
        d = _FN[kind](*xs, *ys)
        grads = torch.autograd.grad(d, xs + ys, allow_unused=True)
        assert torch.isfinite(d), (kind, x)
        assert all(g is None or torch.isfinite(g).all() for g in grads), (kind, x, grads)
        if want is not None:
            assert abs(float(d.detach()) - want) < 1e-9, (kind, float(d.detach()), want)
    # the closed forms too: a point on the axis, on the rim, a half-space parallel to the faces
    p = torch.tensor([[0.0, 0, 0], [0.1, 0, 0.2], [0.0, 0, 0.5]], dtype=F64, requires_grad=True)
    a, b, r = (t.to(F64) for t in _degenerate_cases()[0][2])
    d = C.point_cylinder(p, a, b, r)
    (g,) = torch.autograd.grad(d.sum(), p)
    torch.testing.assert_close(d, torch.tensor([-0.1, 0.0, 0.3], dtype=F64), atol=1e-12, rtol=0)
    assert torch.isfinite(g).all()
    n = torch.tensor([0.0, 0, 1], dtype=F64, requires_grad=True)
    h = C.cylinder_halfspace(a, b, r, n, torch.tensor(-0.5, dtype=F64))
    assert abs(float(h) - 0.3) < 1e-12 and torch.isfinite(torch.autograd.grad(h, n)[0]).all()


def test_cylinder_gradcheck():
    """gradcheck (float64, fast mode) of every cylinder function at non-degenerate pairs, apart and in
    contact."""
    for kind, apart in (("sphere", False), ("capsule", False), ("box", True), ("cylinder", False),
                        ("cylinder", True)):
        args, ref = _pairs(kind, 40, seed=5)
        for i in (int(np.argmax(ref > 0.02)) if apart else int(np.argmax(ref < -0.02)),):
            xs = [t[i].clone().requires_grad_(t.dtype == F64) for t in args]
            if kind == "box":  # the rotation through URDF roll-pitch-yaw (differentiable)
                from scipy.spatial.transform import Rotation

                def fn(c, rpy, h, a, b, r):
                    return C.box_cylinder(c, box(c, h, rpy).rotation, h, a, b, r)

                rpy = Rotation.from_matrix(xs[1].detach().numpy()).as_euler("xyz")
                xs[1] = torch.tensor(rpy, dtype=F64, requires_grad=True)
            else:
                fn = _FN[kind]
            assert torch.autograd.gradcheck(fn, tuple(xs), eps=1e-6, atol=1e-5, rtol=1e-4,
                                            fast_mode=True), (kind, i)
    a, b, r = (torch.tensor(x, dtype=F64, requires_grad=True) for x in ([0.1, 0, 0], [0.0, 0.2, 0.3], 0.1))
    n = torch.tensor([0.6, 0.0, 0.8], dtype=F64)
    off = torch.tensor(0.05, dtype=F64)
    assert torch.autograd.gradcheck(lambda a, b, r: C.cylinder_halfspace(a, b, r, n, off), (a, b, r))
    assert torch.autograd.gradcheck(lambda p: C.point_cylinder(p, a.detach(), b.detach(), r.detach()),
                                    (torch.tensor([0.3, -0.1, 0.2], dtype=F64, requires_grad=True),))


def test_cylinder_distances_batch_and_float32():
    """Leading dims broadcast; float32 gives float32 close to the float64 result."""
    args, _ = _pairs("cylinder", 12, seed=6)
    d64 = C.cylinder_cylinder(*args)
    d = C.cylinder_cylinder(*(t.reshape(3, 4, *t.shape[1:]) for t in args))
    assert d.shape == (3, 4)
    torch.testing.assert_close(d.reshape(-1), d64, atol=1e-9, rtol=0)
    d32 = C.cylinder_cylinder(*(t.float() for t in args))
    assert d32.dtype == torch.float32
    torch.testing.assert_close(d32.double(), d64, atol=2e-5, rtol=0)


def test_world_cylinders_through_the_pair_table(monkeypatch):
    """World obstacles that are cylinders: World.distances against the kernels, and the broad-phase and C
    decisions (which serve cylinders against sphere geoms only: the FR3's capsules go to torch) against the
    exact distances."""
    from diffkin import models
    from diffkin.collision import RobotCollision
    from tests.test_collision_robot import FR3

    chain = models.from_urdf(FR3, "fr3_link8", dtype=F64)
    rc = RobotCollision.from_urdf(FR3, chain).requires_grad_(False).world_only()
    rc.skip_fixed = False  # every (geom, object) entry is checked: the decisions against d's minimum
    world = World(cylinders=[[0.45, -0.3, 0.4, 0.45, 0.3, 0.4, 0.06], [0.3, 0.3, 0.3, 0.3, 0.3, 0.9, 0.05]],
                  spheres=[[0.0, 0.5, 0.5, 0.05]], boxes=box([0.6, 0.0, 0.2], [0.1, 0.3, 0.02], dtype=F64),
                  dtype=F64)
    q = chain.random_configuration((12,), generator=torch.Generator().manual_seed(0))
    d = rc.world_distances(q, world)  # (12, G, W)
    assert d.shape == (12, len(rc.geoms), 4)  # sphere, box, the cylinders last
    a, b, r, *_ = rc.placed(q)
    y = world.cylinders
    ref = C.capsule_cylinder(a[:, :, None], b[:, :, None], r[:, None], y[:, :3], y[:, 3:6], y[:, 6])
    cap = [i for i, g in enumerate(rc.geoms) if g.shape == "capsule"]
    torch.testing.assert_close(d[:, cap, 2:], ref, atol=1e-12, rtol=0)
    from diffkin.collision.pairs import NATIVE_CLEAR, NATIVE_CLEAR_SPHERES, PAIRS
    from diffkin.ik.residuals import DistanceConstraint
    from diffkin.kernels import native

    # the table: the C decisions serve capsules against round objects, half-spaces and boxes; cylinders
    # against the robot's spheres only (the FR3's proper capsules go to torch)
    assert PAIRS[("capsule", "cylinder")].native == NATIVE_CLEAR_SPHERES
    assert PAIRS[("capsule", "capsule")].native == PAIRS[("capsule", "box")].native == NATIVE_CLEAR
    exact = d.flatten(1).amin(-1)
    for margin in (0.0, 0.05):
        clear = exact >= margin
        assert 0 < int(clear.sum()) < 12  # some clear, some not
        # the C pass (where built) for the round objects, torch for the cylinders and the box
        assert torch.equal(DistanceConstraint(rc, world, margin).satisfied(q), clear)
        with monkeypatch.context() as mp:  # without the C pass: every kind through the torch broad phase
            mp.setattr(native, "capsules_clear", lambda *args, **kw: False)
            assert torch.equal(DistanceConstraint(rc, world, margin).satisfied(q), clear)


def test_a_nan_row_is_nan_and_leaves_the_other_rows():
    """One row of NaN input among finite ones: that row's distance is NaN (as the capsule and sphere forms
    give), the other rows equal their values alone; no error for the batch."""
    t = lambda *x: torch.tensor(x, dtype=torch.float64)  # noqa: E731
    a0 = torch.stack([t(0, 0, 0), t(math.nan, 0, 0)])
    a1, ra = torch.stack([t(0, 0, 1), t(0, 0, 1)]), t(0.1, 0.1)
    b0, b1, rb = torch.stack([t(1, 0, 0), t(1, 0, 0)]), torch.stack([t(1, 0, 1), t(1, 0, 1)]), t(0.1, 0.1)
    for fn in (cylinders.cylinder_cylinder, cylinders.capsule_cylinder):
        d = fn(a0, a1, ra, b0, b1, rb)
        assert torch.isnan(d[1]) and d[0] == fn(a0[:1], a1[:1], ra[:1], b0[:1], b1[:1], rb[:1])[0]
    centre, R = torch.stack([t(0, 0, 0), t(math.nan, 0, 0)]), torch.eye(3).double().expand(2, 3, 3)
    d_box = cylinders.box_cylinder(centre, R, t(0.1, 0.1, 0.1).expand(2, 3), b0, b1, rb)
    assert torch.isnan(d_box[1]) and torch.isfinite(d_box[0])


def test_pair_table_names_the_kinds_it_has():
    from diffkin.collision.pairs import pair
    from diffkin.errors import ConventionError

    assert pair("cylinder", "capsule")[1]  # stored the other way round
    with pytest.raises(ConventionError, match=r"expected two geom kinds of the pair table \(capsule, box, .*"
                                              r"got 'capsule' and 'cone'"):
        pair("capsule", "cone")
