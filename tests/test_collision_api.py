"""The collision API's boundary: the collision model must belong to the chain it is used with, it holds the
chain by reference (its parameters and conversions are the geometry's only), input checks of ``World``,
``from_urdf`` and the exported distance functions, q-independent geoms in IK and sampling, and the
collision-free sampler's early stop."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import diffkin
import diffkin.sampling
from diffkin import ik, models
from diffkin.collision import RobotCollision, World
from diffkin.errors import DTypeError, ModelError

DATA = Path(__file__).parent / "data"
FR3 = DATA / "urdf" / "fr3.urdf"
F64 = torch.float64
SRDF = '<robot><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" reason="Default"/></robot>'


def _fr3(dtype=F64):
    chain = models.from_urdf(FR3, "fr3_link8", dtype=dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's meshes are not shipped
        return chain, RobotCollision.from_urdf(FR3, chain, srdf=SRDF)


def _targets(chain, n=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return chain.forward_kinematics(chain.random_configuration((n,), generator=g)).detach()


# ------------------------------------------------------------------ 1. the collision model's chain
def test_a_collision_model_of_another_chain_is_refused():
    chain, rc = _fr3()
    panda = models.load("panda").double()  # the Panda's DH chain: another chain of 7 joints
    T = _targets(panda)
    with pytest.raises(ModelError, match=r"built for URDFChain.*fr3_joint1.*chain given is DHChain"):
        ik.solve(panda, T, collision=rc)
    with pytest.raises(ModelError, match="random_configuration"):
        diffkin.sampling.random_configuration(panda, (3,), collision=rc)
    with pytest.raises(ModelError, match="ik"):
        ik.optimize(panda, T, torch.zeros(4, 7, dtype=F64), collision=rc, max_iterations=2)
    with pytest.raises(ModelError, match="CollisionCost"):
        ik.optimize(panda, T, torch.zeros(4, 7, dtype=F64), max_iterations=2,
                    costs=[ik.CollisionCost(collision=rc)])
    # another copy of the same robot is another chain too (its parameters may differ): rebind to use it
    twin = models.from_urdf(FR3, "fr3_link8", dtype=F64)
    with pytest.raises(ModelError, match="rebind"):
        ik.solve(twin, _targets(twin), collision=rc)
    rc.chain = twin
    assert rc.chain is twin and "chain" not in dict(rc.named_children())
    res = ik.solve(twin, _targets(twin), collision=rc, seed=0)
    assert res.success.any()


def test_the_chain_is_held_by_reference():
    chain, rc = _fr3(torch.float32)
    names = {n for n, _ in rc.named_parameters()}
    assert names == {"capsule_a", "capsule_b", "capsule_radius", "box_center", "box_rpy", "box_half_extents",
                     "convex_vertices"}
    assert not any(p is c for p in rc.parameters() for c in chain.parameters())
    rc.double()
    assert chain.dtype == torch.float32 and rc.capsule_radius.dtype == F64  # the user's chain untouched
    q = torch.zeros(7)
    with pytest.raises(DTypeError, match=r"geometry is torch.float64, the chain is torch.float32"):
        rc.self_distances(q)
    chain.double()
    d = rc.self_distances(q.double())
    assert d.dtype == F64
    # an optimiser over rc.parameters() moves the geometry, never the robot
    before = [p.detach().clone() for p in chain.parameters()]
    opt = torch.optim.SGD(rc.parameters(), lr=0.1)
    (-rc.min_distance(torch.rand(5, 7, dtype=F64))).sum().backward()
    opt.step()
    assert all(torch.equal(a, b) for a, b in zip(before, chain.parameters()))


# ------------------------------------------------------------------ 2. input checks at the boundary
def test_world_rejects_negative_radii():
    with pytest.raises(ModelError, match=r"spheres radii \(last column\) >= 0, got 1 negative value\(s\) "
                       r"\(smallest -1\)"):
        World(spheres=[[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, -1.0]])
    with pytest.raises(ModelError, match="capsules radii"):
        World(capsules=torch.tensor([[0.0, 0, 0, 1, 0, 0, -0.1]]))
    assert len(World(spheres=[[0.0, 0.0, 0.0, 0.0]], capsules=[[0.0, 0, 0, 1, 0, 0, 0.0]])) == 2  # 0 is fine


def test_world_cylinders_argument():
    """cylinders (..., W_y, 7): axis end points and radius, like capsules; their columns come last."""
    from diffkin.errors import ShapeError

    w = World(spheres=[[0.0, 0.0, 1.0, 0.1]], cylinders=[[0.5, 0.0, 0.0, 0.5, 0.0, 0.4, 0.05]],
              dtype=torch.float64)
    assert w.counts == (1, 0, 0, 0, 0, 1) and len(w) == 2 and w.cylinders.dtype == torch.float64
    assert w.to(torch.float32).cylinders.dtype == torch.float32
    with pytest.raises(ModelError, match=r"cylinders radii \(last column\) >= 0, got 1 negative value\(s\)"):
        World(cylinders=[[0.0, 0, 0, 0, 0, 1, -0.1]])
    with pytest.raises(ShapeError, match="cylinders"):
        World(cylinders=[[0.0, 0, 0, 0, 0, 1]])


def test_from_urdf_of_another_robot_raises():
    chain = models.from_urdf(FR3, "fr3_link8", dtype=F64)
    with pytest.raises(ModelError, match=r"none of the chain.s links \(the chain: fr3_link0, .*: base_link"):
        RobotCollision.from_urdf(DATA / "urdf" / "ur10.urdf", chain)


@pytest.mark.parametrize("name", ["capsule_capsule", "sphere_sphere", "capsule_box", "box_box",
                                  "capsule_halfspace", "segment_closest_parameters"])
def test_exported_distance_functions_check_their_input(name):
    from diffkin import collision
    from diffkin.collision import boxes, distances
    from diffkin.errors import DTypeError, ShapeError

    fn = getattr(collision, name)
    raw = getattr(distances, name, None) or getattr(boxes, name)
    g = torch.Generator().manual_seed(1)
    kinds = [(3,) if "pts" in k else (3, 3) if k == "rot" else () for k in _ARGS[name]]
    args = [torch.rand(5, *k, generator=g, dtype=F64) + (0.1 if k == () else 0.0) for k in kinds]
    args = [_rotation(a) if k == "rot" else a for a, k in zip(args, _ARGS[name])]
    out = fn(*args)
    torch.testing.assert_close(out, raw(*args), rtol=0, atol=0)  # the kernel itself, unchanged
    bad = list(args)
    bad[0] = args[0][..., :2]  # a point of two coordinates
    with pytest.raises(ShapeError, match=r"expected \w+ of shape \(\.\.\., 3\), got \(5, 2\)"):
        fn(*bad)
    with pytest.raises(DTypeError, match="float32 or float64"):
        fn(*[a.long() if i == 0 else a for i, a in enumerate(args)])
    with pytest.raises(DTypeError):  # mixed dtypes
        fn(*[a.float() if i == 0 else a for i, a in enumerate(args)])
    with pytest.raises(ShapeError, match="broadcast"):
        fn(*[a[:4] if i == 0 else a for i, a in enumerate(args)])


def test_every_exported_distance_function_wraps_its_own_kernel():
    from diffkin import collision
    from diffkin.collision import _checked

    names = [n for n in collision.__all__ if hasattr(_checked, n)]
    assert len(names) == 25  # (the five convex-mesh functions: tests/test_collision_convex.py)
    for n in names:
        fn = getattr(collision, n)
        assert fn.__wrapped__.__name__ == n and fn.__wrapped__.__module__.endswith(
            ("distances", "boxes", "cylinders", "convex"))


def _rotation(x):
    from diffkin.kernels.joints import origin_transform

    return origin_transform(torch.zeros(x.shape[0], 3, dtype=x.dtype), x[..., 0, :])[..., :3, :3]


_ARGS = {  # pts: a point (..., 3); rot: a rotation (..., 3, 3); r: a scalar (...)
    "capsule_capsule": ("pts", "pts", "r", "pts", "pts", "r"),
    "sphere_sphere": ("pts", "r", "pts", "r"),
    "capsule_box": ("pts", "pts", "r", "pts", "rot", "pts"),
    "box_box": ("pts", "rot", "pts", "pts", "rot", "pts"),
    "capsule_halfspace": ("pts", "pts", "r", "pts", "r"),
    "segment_closest_parameters": ("pts", "pts", "pts", "pts"),
}


def test_capsule_capsule_pairs_checks_its_indices():
    from diffkin.collision import capsule_capsule, capsule_capsule_pairs
    from diffkin.errors import DTypeError, ShapeError

    a, b, r = torch.rand(2, 4, 3, dtype=F64), torch.rand(2, 4, 3, dtype=F64), torch.full((4,), 0.1, dtype=F64)
    i, j = torch.tensor([0, 1]), torch.tensor([2, 3])
    d = capsule_capsule_pairs(a, b, r, i, j)
    torch.testing.assert_close(d, capsule_capsule(a[:, i], b[:, i], r[i], a[:, j], b[:, j], r[j]))
    with pytest.raises(ShapeError, match=r"in \[0, 4\)"):
        capsule_capsule_pairs(a, b, r, i, torch.tensor([2, 4]))
    with pytest.raises(DTypeError, match="torch.long"):
        capsule_capsule_pairs(a, b, r, i.float(), j)
    with pytest.raises(ShapeError, match=r"r \(\.\.\., G\)"):
        capsule_capsule_pairs(a, b, r[:3], i, j)


# ------------------------------------------------------------------ 3. geoms fixed to the base
def test_a_floor_touching_the_base_leaves_ik_and_sampling_feasible():
    """The FR3's base spheres reach 3 cm below z = 0: a floor there touches them at every q. IK and the
    sampler leave those q-independent entries out (world_distances still reports them); the moving geoms'
    clearance from the floor is re-checked by coal with the geoms placed by Pinocchio."""
    pytest.importorskip("pinocchio")
    import collision_reference as ref
    from test_collision_robot import _Pinocchio

    chain, rc = _fr3()
    chain.requires_grad_(False)
    floor = World(halfspaces=[[0.0, 0.0, 1.0, 0.0]], dtype=F64)
    assert [g.link for g, f in zip(rc.geoms, rc.fixed) if f] == ["fr3_link0_sc"] * 3
    dropped = set(rc._distance_names(floor)) - set(rc._distance_names(floor, moving_only=True))
    # link 0 is fixed, link 1 turns about the floor's normal
    assert dropped == {f"fr3_link{k}_sc/{i} × world halfspace 0" for k in (0, 1) for i in range(3)}
    q = torch.zeros(2, 7, dtype=F64)
    d = rc.world_distances(q, floor)
    assert d.shape == (2, len(rc.geoms), 1) and bool((d[:, torch.tensor(rc.fixed), 0] < -0.02).all())
    margin = 0.005
    g = torch.Generator().manual_seed(4)
    q = diffkin.sampling.random_configuration(chain, (12,), g, collision=rc, world=floor, margin=0.02)
    T = chain.forward_kinematics(q)
    res = ik.solve(chain, T, collision=rc, world=floor, margin=margin, seed=0)
    assert res.success.float().mean() >= 0.8
    pref = _Pinocchio(FR3.read_text(), chain, rc.geoms)
    (plane,) = ref.world_objects(floor)
    left_out = [g.name for g in rc.geoms if g.link in ("fr3_link0_sc", "fr3_link1_sc")]
    checked = [g.name for g in rc.geoms if g.name not in left_out]
    constant = []
    for qq in (*res.q[res.success].numpy(), *q.numpy()):
        pref.place(qq)
        assert min(ref.distance(*pref.shape(n), *plane) for n in checked) >= margin - 1e-7
        constant.append([ref.distance(*pref.shape(n), *plane) for n in left_out])
    constant = torch.tensor(constant)  # the entries left out are the same at every q (by coal), and touch
    assert float((constant - constant[0]).abs().max()) < 1e-9 and float(constant.min()) < 0
    # the explicit option: check the fixed geoms too, and nothing is feasible any more
    rc.skip_fixed = False
    assert not ik.solve(chain, T[:3], collision=rc, world=floor, margin=margin, seed=0).success.any()
    q2, ok = diffkin.sampling.random_configuration(chain, (3,), collision=rc, world=floor, return_mask=True)
    assert not ok.any()


# ------------------------------------------------------------------ 4. the collision-free sampler
class _Exact:
    """The same model seen only through the exact ``min_distance`` (the sampler's duck-typed path), with the
    fixed entries left out as the model's own path does."""

    def __init__(self, rc, world):
        self.rc, self.world = rc, world

    def min_distance(self, q, world=None):
        d = self.rc._distances_at_least(q, world, None, moving_only=True)  # threshold None: exact
        return d.amin(-1)


def test_the_broad_phase_sampler_draws_what_the_exact_one_draws():
    chain, rc = _fr3()
    world = World(spheres=[[0.45, 0.0, 0.45, 0.12], [0.0, 0.4, 0.3, 0.08]], halfspaces=[[0, 0, 1, 0.0]],
                  dtype=F64)
    kw = dict(world=world, margin=0.02, return_mask=True)
    q1, ok1 = diffkin.sampling.random_configuration(chain, (300,), torch.Generator().manual_seed(2),
                                                    collision=rc, **kw)
    q2, ok2 = diffkin.sampling.random_configuration(chain, (300,), torch.Generator().manual_seed(2),
                                                    collision=_Exact(rc, world), **kw)
    assert bool(ok1.all()) and torch.equal(q1, q2) and torch.equal(ok1, ok2)


def test_zero_acceptance_stops_early_and_names_the_pairs():
    from diffkin.errors import SamplingError

    chain = models.from_urdf(FR3, "fr3_link8", dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = RobotCollision.from_urdf(FR3, chain)  # no SRDF: link 1 and link 3 always overlap
    with pytest.raises(SamplingError) as e:
        diffkin.sampling.random_configuration(chain, (200,), collision=rc)
    msg = str(e.value)
    assert "in 2 rounds (stopped early" in msg and "fr3_link1_sc/0 × fr3_link3_sc/0 (100 %)" in msg, msg
    drawn = int(msg.split(" % of the ")[1].split(" draws")[0])
    assert diffkin.sampling.GIVE_UP <= drawn < 32 * diffkin.sampling.GIVE_UP
    q, ok = diffkin.sampling.random_configuration(chain, (5,), collision=rc, return_mask=True)
    assert q.shape == (5, 7) and not ok.any()


def test_ur5e_shoulder_over_a_floor_is_left_out_and_ik_succeeds():
    """Menagerie's UR5e (MJCF): the shoulder capsule turns about the vertical 3 mm above z = 0, so with a
    floor there and a 5 mm margin every target failed (0/20). Its floor distance is constant by MuJoCo's own
    kinematics (the lowest point of the geom MuJoCo places), so IK leaves it out and solves the targets."""
    mujoco = pytest.importorskip("mujoco")
    from mjcf_util import compile_without_assets

    path = DATA / "mjcf" / "universal_robots_ur5e" / "ur5e.xml"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        chain = models.from_mjcf(path, "wrist_3_link", dtype=F64).requires_grad_(False)
        rc = RobotCollision.from_mjcf(path, chain)
    floor = World(halfspaces=[[0.0, 0.0, 1.0, 0.0]], dtype=F64)
    dropped = set(rc._distance_names(floor)) - set(rc._distance_names(floor, moving_only=True))
    assert dropped == {"shoulder_link/0 × world halfspace 0"}
    m = compile_without_assets(path)
    d = mujoco.MjData(m)
    gid = [g for g in range(m.ngeom) if m.body(m.geom_bodyid[g]).name == "shoulder_link"
           and m.geom_contype[g] + m.geom_conaffinity[g] > 0]
    assert len(gid) == 1
    q = chain.random_configuration((40,), generator=torch.Generator().manual_seed(1))
    low = []
    for row in q.numpy():
        d.qpos[:6] = row
        mujoco.mj_kinematics(m, d)
        axis, half = d.geom_xmat[gid[0]].reshape(3, 3)[:, 2], m.geom_size[gid[0]][1]
        ends = d.geom_xpos[gid[0]] + np.outer([-half, half], axis)
        low.append(ends[:, 2].min() - m.geom_size[gid[0]][0])
    assert max(low) - min(low) < 1e-12 and 0 < min(low) < 0.005
    g = torch.Generator().manual_seed(0)
    q = diffkin.sampling.random_configuration(chain, (10,), g, collision=rc, world=floor, margin=0.02)
    res = ik.solve(chain, chain.forward_kinematics(q), collision=rc, world=floor, margin=0.005, seed=0)
    assert res.success.float().mean() >= 0.8


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_world_rejects_zero_length_cylinders(dtype):
    """A cylinder without length has no axis (the kernel would take an arbitrary one for its flat faces):
    refused at the boundary, in a batch of worlds too; a short one, above the normalisation floor, is kept."""
    good = [0.0, 0.0, 0.0, 0.0, 0.0, 0.2, 0.05]
    with pytest.raises(ModelError, match=r"cylinders lengths \|b - a\| \(columns 0-5\) > .*, got 1 value"):
        World(cylinders=[good, [0.3, 0.1, 0.2, 0.3, 0.1, 0.2, 0.05]], dtype=dtype)
    batched = torch.tensor([[good], [[1.0, 0, 0, 1.0, 0, 0, 0.0]]], dtype=dtype)  # (2 worlds, 1, 7)
    with pytest.raises(ModelError, match="cylinders lengths"):
        World(cylinders=batched)
    short = 1e-3 if dtype == torch.float32 else 1e-8
    w = World(cylinders=[good, [0.0, 0.0, 0.0, short, 0.0, 0.0, 0.01]], dtype=dtype)
    assert w.counts[-1] == 2
    stacked = World.stack([w, World(dtype=dtype)])  # its padding cylinders have a length too
    assert stacked.cylinders.shape == (2, 2, 7)

