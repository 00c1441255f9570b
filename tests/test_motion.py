"""motion.plan on the Franka FR3 (the Panda's successor; Franka's capsule collision model) among spheres and a
box: the reach bound the subdivision rests on, the per-row failure reasons, and successful plans re-checked
densely by Pinocchio's FK + coal (never by the code under test) and against their limits."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch

from diffkin import models, motion
from diffkin.collision import RobotCollision, World, box
from diffkin.errors import ShapeError
from diffkin.motion._edges import EdgeChecker
from diffkin.sampling import random_configuration
from tests.helpers import BOX, SPHERES, CoalCheck, fr3_robot

pytest.importorskip("pinocchio")
V = [2.0, 1.0, 1.5, 1.25, 3.0, 1.5, 3.0]  # fr3.urdf's <limit velocity=> (plan's default velocity limits)
A = [10.0, 5.0, 8.0, 10.0, 12.0, 15.0, 15.0]
J = [500.0, 250.0, 400.0, 500.0, 600.0, 750.0, 750.0]


@pytest.fixture(scope="module")
def robot():
    d = torch.float64
    chain, rc = fr3_robot(d)
    world = World(spheres=torch.tensor(SPHERES, dtype=d),
                  boxes=box(center=torch.tensor(BOX[0], dtype=d), half_extents=torch.tensor(BOX[1], dtype=d),
                            dtype=d), dtype=d)
    return chain, rc, world


def _points(rc, q):
    """Every capsule end and box corner of the robot at q (..., nq) -> (..., P, 3)."""
    a, b, _, c, R, h = rc.placed(q)
    return torch.cat((a, b), -2) if c.shape[-2] == 0 else torch.cat((a, b, c), -2)


def test_joint_reach_bounds_the_travel_of_every_geom(robot):
    chain, rc, _ = robot
    R = motion.joint_reach(rc)
    assert R.shape == (7,) and (R > 0).all()
    g = torch.Generator().manual_seed(0)
    lo, hi = chain.q_limits[:, 0], chain.q_limits[:, 1]
    q = lo + (hi - lo) * torch.rand(3000, 7, generator=g, dtype=torch.float64)
    dq = (torch.rand(3000, 7, generator=g, dtype=torch.float64) - 0.5) * 2e-3
    travel = (_points(rc, q + dq) - _points(rc, q)).norm(dim=-1).amax(-1)
    bound = (dq.abs() * R).sum(-1)
    ratio = travel / bound
    assert ratio.max() <= 1.0 and ratio.max() > 0.3  # a bound, and not a vacuous one
    # one joint at a time: the farthest geom point from its axis is within R_j
    for j in range(7):
        e = torch.zeros(7, dtype=torch.float64)
        e[j] = 1e-4
        assert ((_points(rc, q[:200] + e) - _points(rc, q[:200])).norm(dim=-1).amax() <= R[j] * 1e-4 * 1.0001)


@pytest.mark.parametrize("scale", [2e-3, 0.1, 1.0])
def test_self_distances_change_by_at_most_the_travel_bound(robot, scale):
    """The subdivision's robot–robot claim (motion._edges): along a straight edge Δq every distance between
    two robot geoms changes by at most Σ_j R_j |Δq_j|, the bound on one point's travel (not twice it), for
    small and large steps alike."""
    chain, rc, _ = robot
    R = motion.joint_reach(rc)
    g = torch.Generator().manual_seed(1)
    lo, hi = chain.q_limits[:, 0], chain.q_limits[:, 1]
    q = lo + (hi - lo) * torch.rand(3000, 7, generator=g, dtype=torch.float64)
    dq = (torch.rand(3000, 7, generator=g, dtype=torch.float64) - 0.5) * 2 * scale
    change = (rc.self_distances(q + dq) - rc.self_distances(q)).abs().amax(-1)
    ratio = change / (dq.abs() * R).sum(-1)
    assert ratio.max() <= 1.0 and ratio.max() > 0.2  # a bound, and not a vacuous one


def test_joint_reach_bounds_mjcf_joints_off_their_body_origin():
    """MJCF joints whose pos lies off their body's origin: the body origins then turn about the axes and
    their distances change, so R_j walks the joints' axis points instead (a 3-hinge arm, the second hinge
    1 m from its body's origin: the travel of every capsule end per radian stays within R_j)."""
    from diffkin.models import from_mjcf

    xml = """<mujoco><worldbody>
    <body name="b1"><joint name="j1" type="hinge" axis="0 0 1" range="-3 3" limited="true"/>
     <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.02"/>
     <body name="b2" pos="0.5 0 0"><joint name="j2" type="hinge" axis="0 0 1" pos="1.0 0 0" range="-3 3"
      limited="true"/><geom type="capsule" fromto="0 0 0 0.1 0 0" size="0.02"/>
      <body name="b3" pos="0 0 0"><joint name="j3" type="hinge" axis="0 0 1" pos="0.5 0 0" range="-3 3"
       limited="true"/><geom type="capsule" fromto="0 0.0 0 0.0 0.1 0" size="0.02"/>
    </body></body></body></worldbody></mujoco>"""
    chain = from_mjcf(xml, "b3", dtype=torch.float64)
    rc = RobotCollision.from_mjcf(xml, chain).requires_grad_(False)
    R = motion.joint_reach(rc)
    q = (torch.rand(300, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5) * 6
    for j in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[j] = 1e-6
        travel = (_points(rc, q + e) - _points(rc, q)).norm(dim=-1).amax() / 1e-6
        assert travel <= R[j] and travel > 0.9 * R[j]  # j1 reaches 2.5 m: 0.7 m before this bound


def test_joint_reach_refuses_mimic_joints():
    """One coordinate turning two fingers on separate branches (a URDF <mimic>) moves both ends of a
    robot-robot distance at once: the bound does not hold (about 1.8x it here), so planning refuses it."""
    import warnings

    from diffkin.errors import ModelError

    urdf = """<robot name="g"><link name="base"/>
    <link name="left"><collision><origin xyz="0.1 0.05 0"/><geometry><sphere radius="0.01"/></geometry>
    </collision></link>
    <link name="right"><collision><origin xyz="0.1 -0.05 0"/><geometry><sphere radius="0.01"/></geometry>
    </collision></link>
    <joint name="jl" type="revolute"><parent link="base"/><child link="left"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
    <joint name="jr" type="revolute"><parent link="base"/><child link="right"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/><mimic joint="jl" multiplier="-1"/></joint>
    </robot>"""
    chain = models.from_urdf(urdf, ["left", "right"], dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = RobotCollision.from_urdf(urdf, chain)
    assert chain.nq == 1 and len(rc.pairs)
    with pytest.raises(ModelError, match="mimic"):
        motion.joint_reach(rc)


def _reach_loop(rc) -> torch.Tensor:
    """joint_reach's sum as it was first written (a Python loop per joint and geom, walking the parent frames
    one by one, in Python floats), from the same intermediate quantities: the reference the batched walk
    must reproduce bit for bit."""
    chain, frames = rc.chain, rc._frames
    dt = rc.capsule_a.dtype
    q0 = (torch.rand(chain.nq, generator=torch.Generator().manual_seed(0), dtype=torch.float64) - 0.5).to(dt)
    F0 = frames.frames(chain, q0)
    K, nq = F0.shape[-3], chain.nq
    Fp = frames.frames(chain, q0 + 1e-3 * torch.eye(nq, dtype=dt))
    moved = (Fp - F0).abs().flatten(-2).amax(-1) > 1e-7
    o = F0[..., :3, 3]
    first = torch.where(moved, torch.arange(K), K).amin(1)
    movers = moved.T
    anc = ((movers[:, None, :] & ~movers[None, :, :]).any(-1) == 0) & movers.any(1)[:, None]
    parent = [max([m for m in range(k) if bool(anc[m, k])], default=-1) for k in range(K)]
    ref = o.clone()  # each frame's reference point: its joint's axis point, else its origin
    ref[first.clamp(max=K - 1)] = chain.joint_axes_origins(q0)[1]
    link = [float((ref[k] - ref[parent[k]]).norm()) if parent[k] >= 0 else 0.0 for k in range(K)]
    nc, nb = rc._counts
    pts = rc._columns(q0)[:, : 2 * nc + nb].T
    a_pts = rc._col_anchor[: 2 * nc + nb]
    ext = torch.cat((rc.capsule_radius, rc.capsule_radius, rc.box_half_extents.norm(dim=-1)))
    own = (pts - ref[a_pts]).norm(dim=-1) + ext
    R = torch.zeros(nq, dtype=dt)
    for j in range(nq):
        for c in range(pts.shape[0]):
            k = int(a_pts[c])
            if not bool(moved[j, k]):
                continue
            total, m = float(own[c]), k
            while m != int(first[j]) and m >= 0:
                total += link[m]
                m = parent[m]
            R[j] = max(float(R[j]), total)
    return R


def test_joint_reach_remembered_for_the_same_geometry(robot):
    """joint_reach is found once for the copies allow_collisions makes (the same geometry and chain: the
    same values, not recomputed) and found anew when the geometry's values change."""
    import diffkin.motion._reach as reach

    _, rc, _ = robot
    first = reach.joint_reach(rc)
    calls = []
    compute = reach._joint_reach

    def counted(collision):
        calls.append(1)
        return compute(collision)

    reach._joint_reach = counted
    try:
        copy = rc.allow_collisions([])
        assert torch.equal(reach.joint_reach(copy), first) and not calls
        with torch.no_grad():
            copy.capsule_radius.add_(0.01)  # a copy's own parameters: the original keeps its values
        grown = reach.joint_reach(copy)
        assert len(calls) == 1 and bool((grown >= first).all()) and bool((grown > first).any())
        assert torch.equal(reach.joint_reach(rc), first) and len(calls) == 2  # the first geometry again
    finally:
        reach._joint_reach = compute


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_a_copy_takes_its_sources_geometry_key(dtype):
    """allow_collisions' copy takes its source's geometry key without reading its values (the same key
    object), equal to the key read afresh from the copy's own tensors; a change of the copy's geometry or of
    the chain gives a new key, equal to a fresh read, and leaves the source's unchanged where it is."""
    from diffkin.collision._values import geometry_key
    from tests.helpers import fr3_robot

    _, rc = fr3_robot(dtype)
    rc.requires_grad_(False)
    source = geometry_key(rc)
    i, j = rc._pair_index[0]
    copy = rc.allow_collisions([(rc.geoms[i].link, rc.geoms[j].link)])  # a checked pair of links allowed
    assert len(copy.pairs) < len(rc.pairs)
    assert geometry_key(copy) is source
    fresh = lambda m: (m.__dict__.pop("_geometry_key"), geometry_key(m))[1]  # noqa: E731
    assert fresh(copy) == source and fresh(copy) is not source
    with torch.no_grad():
        copy.capsule_radius.add_(0.01)
    grown = geometry_key(copy)
    assert grown != source and grown == fresh(copy) and geometry_key(rc) is source
    p = next(rc.chain.parameters())
    with torch.no_grad():
        p.add_(1e-3)
        try:
            moved = geometry_key(copy)
            assert moved != grown and moved == fresh(copy) and geometry_key(rc) != source
        finally:
            p.sub_(1e-3)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_joint_reach_batched_walk_equals_the_loop(robot, dtype):
    """The batched walk up the frame tree gives the per-joint, per-geom loop's R exactly, on the FR3 (a chain)
    and on the G1 (a tree of 29 joints, five end links, its URDF's primitive geoms)."""
    import warnings

    from diffkin import models
    from diffkin.collision import RobotCollision
    from tests.helpers import DATA, fr3_robot

    g1 = DATA / "urdf" / "g1_29dof_rev_1_0.urdf"
    ends = ["left_ankle_roll_link", "right_ankle_roll_link", "left_rubber_hand", "right_rubber_hand",
            "head_link"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # meshes not shipped: skipped
        chain = models.from_urdf(g1, ends, dtype=dtype).requires_grad_(False)
        rcs = [fr3_robot(dtype)[1], RobotCollision.from_urdf(g1, chain).requires_grad_(False)]
    for rc in rcs:
        got = motion.joint_reach(rc)
        assert got.dtype == dtype and got.shape == (rc.chain.nq,) and (got > 0).any()
        assert torch.equal(got, _reach_loop(rc))


def _four_pairs(robot, eta: float, seed: int, margin: float):
    """An EdgeChecker of the robot in its world (margin 0, resolution ``eta``) and four pairs of random
    configurations clear of ``margin``: ``(checker, q_a (4, nq), q_b (4, nq), rows (4,))``."""
    chain, rc, world = robot
    q = random_configuration(chain, (8,), torch.Generator().manual_seed(seed), collision=rc, world=world,
                             margin=margin)
    return EdgeChecker(rc, world, 0.0, eta), q[:4], q[4:], torch.arange(4)


def test_edges_subdivision_proves_the_continuous_edge(robot):
    chain, rc, world = robot
    eta = 0.01
    checker, qa, qb, rows = _four_pairs(robot, eta, seed=1, margin=0.03)
    free, _ = checker.edges(qa, qb, rows)
    assert free.any() and (~free).any()
    # every free edge, sampled 2x finer than the subdivision, keeps d >= 0 (exact distances, torch path)
    f = torch.linspace(0, 1, 2 * int(checker.steps(qb - qa).max()) + 1, dtype=torch.float64)
    qs = qa[free, None] + f[:, None] * (qb - qa)[free, None]
    assert (rc.min_distance(qs, world) >= 0).all()
    # a blocked edge: some configuration on it is closer than the slack η
    qs = qa[~free, None] + f[:, None] * (qb - qa)[~free, None]
    assert (rc.min_distance(qs, world).amin(-1) < eta).all()
    # the prefix decision: the reached part is clear, the part just after it is not provably so
    free_p, lam = checker.edges(qa, qb, rows, prefix=True)
    assert (free_p == free).all() and (lam[free] == 1).all() and (lam[~free] < 1).all()
    part = qa + lam[:, None] * (qb - qa)
    assert checker.clear(part, rows).all()


def test_plan_joint_goals_rechecked_by_coal(robot):
    chain, rc, world = robot
    g = torch.Generator().manual_seed(3)
    q = random_configuration(chain, (6,), g, collision=rc, world=world, margin=0.02)
    qs, qg = q[:3], q[3:]
    margin = 0.005
    res = motion.plan(chain, qs, qg, collision=rc, world=world, margin=margin, acceleration_limit=A,
                      jerk_limit=J, dt=0.01, resolution=0.01, max_iterations=300)
    assert res.success.all(), res.reason
    B, S, nq = res.q.shape
    assert res.t.shape == (B, S) and res.qd.shape == res.qdd.shape == (B, S, nq)
    assert torch.equal(res.q[:, 0], qs)  # the start exactly
    assert torch.equal(res.q[:, -1], qg)  # the goal exactly, held
    for x in (res.qd, res.qdd):  # at rest at both ends
        assert x[:, 0].abs().max() == 0 and x[:, -1].abs().max() == 0
    end = res.state(res.duration[:, None])
    assert end.velocity.abs().max() < 1e-9 and end.acceleration.abs().max() < 1e-9
    assert torch.equal(end.position, qg[:, None])
    # limits on dense samples (1 ms)
    t = torch.arange(0, float(res.duration.max()) + 0.02, 1e-3, dtype=torch.float64)
    st = res.state(t)
    assert (st.velocity.abs() <= torch.tensor(V) * (1 + 1e-9)).all()
    assert (st.acceleration.abs() <= torch.tensor(A) * (1 + 1e-9)).all()
    jerk = torch.cat([tp.jerk(t) for _, tp in res._timing])
    assert (jerk.abs() <= torch.tensor(J) * (1 + 1e-9)).all()
    assert (st.position[:, 0] == qs).all() and res.sample(t).shape == (B, t.numel(), nq)
    lim = chain.q_limits.to(st.position)  # the joint limits along the whole motion (a spline overshoots)
    assert ((st.position >= lim[:, 0]) & (st.position <= lim[:, 1])).all()
    # clearance: exact distances at the 10 ms samples (torch path), coal + Pinocchio at 20 instants per row
    assert (rc.min_distance(res.q, world) >= margin).all()
    ref_check = CoalCheck(rc, moving_only=True)
    for b in range(B):
        idx = torch.linspace(0, int(res.duration[b] / 1e-3), 20).long()
        d = [ref_check.min_distance(st.position[b, i].numpy()) for i in idx]
        assert min(d) >= margin - 1e-9


def test_plan_reports_bad_rows(robot):
    chain, rc, world = robot
    g = torch.Generator().manual_seed(5)
    q = random_configuration(chain, (8,), g, collision=rc, world=world, margin=0.02)
    qs, qg = q[:4].clone(), q[4:].clone()
    qs[0] = qs[1]
    qs[0, 3] = chain.q_limits[3, 1] + 0.1  # start outside the limits
    qg[1] = chain.q_limits[:, 1] + 0.2  # goal outside the limits
    v = torch.tensor(V, dtype=torch.float64).repeat(4, 1)
    v[2, 0] = 0.0  # infeasible limits
    a, b, *_ = rc.placed(qg[3])
    k = len(rc.geoms) - 3  # a capsule on the forearm / wrist: a sphere on it puts the goal in collision
    centre = ((a[k] + b[k]) / 2).tolist()
    ball = World(spheres=torch.tensor(SPHERES + [[*centre, 0.03]], dtype=torch.float64), dtype=torch.float64)
    res = motion.plan(chain, qs, qg, collision=rc, world=ball, velocity_limit=v, acceleration_limit=A,
                      max_iterations=50, resolution=0.02)
    assert res.success.tolist() == [False, False, False, False]
    assert "start outside" in res.reason[0] and "goal outside" in res.reason[1]
    assert "limits" in res.reason[2] and "goal in collision" in res.reason[3]
    assert (res.q == qs[:, None]).all() and (res.duration == 0).all()


def test_plan_pose_goals(robot):
    chain, rc, world = robot
    g = torch.Generator().manual_seed(7)
    q = random_configuration(chain, (6,), g, collision=rc, world=world, margin=0.02)
    T = chain.forward_kinematics(q[3:])
    T[2, :3, 3] = torch.tensor([3.0, 0.0, 0.5], dtype=torch.float64)  # out of reach
    res = motion.plan(chain, q[:3], T, collision=rc, world=world, acceleration_limit=A, jerk_limit=J,
                      resolution=0.01, max_iterations=300)
    assert res.success.tolist() == [True, True, False], res.reason
    assert "unreachable" in res.reason[2]
    Tend = chain.forward_kinematics(res.q[:2, -1])
    assert (Tend[:, :3, 3] - T[:2, :3, 3]).norm(dim=-1).max() < 1e-4
    assert torch.equal(res.q[:2, -1], res.q_goal[:2])


@pytest.mark.extended
def test_plans_rechecked_densely_by_coal(robot):
    """Every successful plan of a larger batch, every 10 ms sample, by Pinocchio + coal (about a minute)."""
    chain, rc, world = robot
    g = torch.Generator().manual_seed(11)
    q = random_configuration(chain, (16,), g, collision=rc, world=world, margin=0.02)
    res = motion.plan(chain, q[:8], q[8:], collision=rc, world=world, margin=0.002, acceleration_limit=A,
                      jerk_limit=J, resolution=0.005)
    assert res.success.float().mean() >= 0.75, res.reason
    ref_check = CoalCheck(rc, moving_only=True)
    for b in res.success.nonzero().squeeze(1).tolist():
        S = int(res.duration[b] / 0.01) + 2
        assert min(ref_check.min_distance(x.numpy()) for x in res.q[b, :S]) >= 0.002 - 1e-9


def test_plan_float32_and_empty_batch():
    chain, rc = fr3_robot(torch.float32)
    world = World(spheres=torch.tensor(SPHERES, dtype=torch.float32), dtype=torch.float32)
    q = random_configuration(chain, (4,), torch.Generator().manual_seed(3), collision=rc, world=world,
                             margin=0.02)
    res = motion.plan(chain, q[:2], q[2:], collision=rc, world=world, acceleration_limit=10.0,
                      resolution=0.01, max_iterations=200)
    assert res.success.all(), res.reason
    assert res.q.dtype == res.t.dtype == res.duration.dtype == torch.float32
    assert torch.equal(res.q[:, 0], q[:2]) and torch.equal(res.q[:, -1], q[2:])
    assert (res.qd.abs() <= torch.tensor(V) * (1 + 1e-6)).all() and (res.qdd.abs() <= 10.0 * (1 + 1e-6)).all()
    empty = motion.plan(chain, q[:0], q[:0], collision=rc, world=world, acceleration_limit=10.0)
    assert empty.success.shape == (0,) and empty.q.shape[0] == 0


def test_a_spline_leaving_the_limits_is_not_taken():
    """The cubic through waypoints that touch a limit overshoots it; _spline_clear refuses it (the planner
    then times the polyline, which stays inside)."""
    from diffkin.motion._spline import _spline_clear

    class Clear:  # every configuration collision-free: only the limits decide
        reach = torch.ones(1, dtype=torch.float64)
        eta = 0.01

        def clear(self, q, problem):
            return torch.ones(q.shape[:-1], dtype=torch.bool)

        def eta_of(self, problem):
            return torch.full(problem.shape, self.eta, dtype=torch.float64)

    path = torch.tensor([[[0.0], [1.0], [1.0], [0.2]]], dtype=torch.float64)
    knots = torch.tensor([[0.0, 1.0, 2.0, 3.0]], dtype=torch.float64)
    from scipy.interpolate import CubicSpline

    spline = CubicSpline(knots[0].numpy(), path[0, :, 0].numpy(), bc_type="clamped")
    top = spline(np.linspace(0, 3, 30001)).max()
    assert top > 1.0 + 1e-3  # scipy's clamped cubic through the same points: it overshoots the waypoints
    lo = torch.tensor([-2.0], dtype=torch.float64)
    for hi, inside in ((1.0, False), (top - 1e-4, False), (top + 1e-4, True)):
        limit = torch.tensor([hi], dtype=torch.float64)
        one = torch.zeros(1, dtype=torch.long)
        assert bool(_spline_clear(Clear(), path, knots, lo, limit, one)) == inside


@pytest.mark.parametrize("search_in_c", [True, False])
def test_plan_one_scene_per_problem_in_one_call(search_in_c):
    """Two MotionBenchMaker problems (VAMP's files, the spherized Panda) in one call with their scenes
    stacked (``World.stack``, the C decisions with one world per configuration), searched in C or in torch
    (the same success semantics): both succeed, and every
    10 ms sample keeps d >= 0 in its own scene by the closed-form torch distances (boxes, cylinders)."""
    from benchmarks import motion_problems as mp
    from diffkin.collision.boxes import sphere_box
    from diffkin.collision.cylinders import sphere_cylinder

    probs = mp.load_problems(families=["table_pick"], indices=[1, 2])
    chain = models.from_urdf(mp.PANDA_SPHERIZED_URDF, "panda_hand", dtype=torch.float64)
    rc = RobotCollision.from_urdf(mp.PANDA_SPHERIZED_URDF, chain, mp.PANDA_SRDF).requires_grad_(False)
    rc = rc.allow_collisions(probs[0].scene.allowed)
    worlds = [p.scene.to_world(dtype=torch.float64) for p in probs]
    qs = torch.tensor([p.start for p in probs], dtype=torch.float64)
    qg = torch.tensor([p.goal for p in probs], dtype=torch.float64)
    v = [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]
    res = motion.plan(chain, qs, qg, collision=rc, world=World.stack(worlds), velocity_limit=v,
                      acceleration_limit=10.0, max_iterations=300, search_in_c=search_in_c)
    assert res.success.all(), res.reason
    moving = ~torch.tensor(rc.fixed)
    for b, w in enumerate(worlds):  # the closed-form sphere-box and sphere-cylinder fields of the torch layer
        a, _, r, *_ = rc.placed(res.q[b])  # (S, G, 3): the robot's 59 spheres
        a, r = a[:, moving, None], r[moving, None]
        bx, y = w.boxes, w.cylinders
        d_box = sphere_box(a, r, bx.center, bx.rotation, bx.half_extents)
        d_cyl = sphere_cylinder(a, r, y[:, :3], y[:, 3:6], y[:, 6])
        assert d_box.numel() and d_cyl.numel() and min(d_box.min(), d_cyl.min()) >= 0
    with pytest.raises(ShapeError):  # a world per problem: batch (B,), not another
        motion.plan(chain, qs, qg, collision=rc, world=World.stack(worlds * 2), velocity_limit=v,
                    acceleration_limit=10.0)


def test_split_keeps_the_polyline():
    """plan._split inserts the midpoints of the cut segments (rows with fewer cuts padded by _pad): every new
    waypoint lies on its row's old polyline, the old waypoints are kept in order, and the ends unchanged."""
    from diffkin.motion.plan import _split

    g = torch.Generator().manual_seed(0)
    path = torch.randn(3, 5, 2, generator=g, dtype=torch.float64)
    cut = torch.tensor([[True, False, True, False], [False] * 4, [False, True, True, True]])
    out = _split(path, cut)
    assert out.shape == (3, 8, 2)
    assert torch.equal(out[:, 0], path[:, 0]) and torch.equal(out[:, -1], path[:, -1])
    assert torch.equal(out[2, [0, 1, 3, 5, 7]], path[2])  # the row with the most cuts: no padding
    assert torch.allclose(out[2, 2], path[2, 1:3].mean(0)) and torch.allclose(out[2, 6], path[2, 3:].mean(0))
    for b in range(3):  # the old waypoints in order among the new ones
        j = 0
        for x in out[b]:
            j += bool(j < 5 and torch.equal(x, path[b, j]))
        assert j == 5
    assert any(torch.allclose(x, path[0, :2].mean(0)) for x in out[0])
    for b in range(3):  # on the polyline: each new point between two consecutive old waypoints
        a, c = path[b, :-1], path[b, 1:]
        for x in out[b]:
            f = ((x - a) * (c - a)).sum(-1) / ((c - a) ** 2).sum(-1)
            d = (a + f.clamp(0, 1)[:, None] * (c - a) - x).norm(dim=-1)
            assert float(d.min()) < 1e-12


def test_shortcut_points_shortens_proven_paths(robot):
    """shortcut_points on searched paths: the ends kept, no path longer, clear on dense samples by the exact
    torch distances (its new pieces are parts of proven edges or checked edges), and a path's draws its own
    (the same path alone as in the batch)."""
    from diffkin.motion._search import row_keys, search, shortcut_points

    chain, rc, world = robot
    eta = 0.01
    checker, qs, qg, rows = _four_pairs(robot, eta, seed=3, margin=0.02)
    lim = chain.q_limits.to(torch.float64)
    path, n, found = search(checker, qs, qg, lim[:, 0], lim[:, 1], rows, max_iterations=300, step=0.3,
                            generator=torch.Generator().manual_seed(0))
    assert found.all() and (n > 2).any()
    key = row_keys(qs, qg, 0)
    new, m = shortcut_points(checker, path, n, rows, 8, key)
    length = lambda p, k: (p[1:k] - p[:k - 1]).norm(dim=-1).sum()  # noqa: E731
    shorter = 0
    for b in range(4):
        k = int(m[b])
        assert torch.equal(new[b, 0], qs[b]) and torch.equal(new[b, k - 1], qg[b])
        assert length(new[b], k) <= length(path[b], int(n[b])) + 1e-12
        shorter += bool(length(new[b], k) < length(path[b], int(n[b])) - 1e-6)
        f = torch.linspace(0, 1, 64, dtype=torch.float64)[:, None]
        dense = (new[b, :k - 1, None] + f * (new[b, 1:k] - new[b, :k - 1])[:, None]).reshape(-1, 7)
        assert float(rc.min_distance(dense, world).min()) >= 0
    assert shorter >= 1
    r = int((n > 2).nonzero()[0])
    alone, m1 = shortcut_points(checker, path[r:r + 1], n[r:r + 1], rows[r:r + 1], 8, key[r:r + 1])
    assert int(m1[0]) == int(m[r]) and torch.equal(alone[0, :int(m1[0])], new[r, :int(m[r])])


def test_torch_search_connect_steps_no_edge_longer_than_step(robot, monkeypatch):
    """The torch search's CONNECT steps as the C search's: every edge of a path (no shortcuts) at most
    ``step`` long in the bound's metric (CONNECT by one whole edge joined the trees by an edge of any length),
    clear on dense samples by the exact torch distances; with a first room of 16 nodes a tree, grown many
    times as EXTEND and CONNECT fill it, the same paths as with 4096."""
    from diffkin.motion import _search

    chain, rc, world = robot
    checker, qs, qg, rows = _four_pairs(robot, 0.01, seed=3, margin=0.02)
    lim = chain.q_limits.to(torch.float64)
    R = checker.reach.to(torch.float64)
    run = lambda: _search.search(checker, qs, qg, lim[:, 0], lim[:, 1], rows, max_iterations=500,  # noqa: E731
                                 step=0.05, generator=torch.Generator().manual_seed(0))
    path, n, found = run()
    assert found.all() and (n > 100).all()
    for b in range(4):
        k = int(n[b])
        assert torch.equal(path[b, 0], qs[b]) and torch.equal(path[b, k - 1], qg[b])
        L = ((path[b, 1:k] - path[b, :k - 1]).abs() * R).sum(-1)
        assert float(L.max()) <= 0.05 * (1 + 1e-9)
        f = torch.linspace(0, 1, 8, dtype=torch.float64)[:, None]
        dense = (path[b, :k - 1, None] + f * (path[b, 1:k] - path[b, :k - 1])[:, None]).reshape(-1, 7)
        assert float(rc.min_distance(dense, world).min()) >= 0  # (the checker's margin: 0)
    monkeypatch.setattr(_search, "_ROOM", 16)
    path16, n16, found16 = run()
    assert torch.equal(n16, n) and torch.equal(found16, found)
    assert all(torch.equal(path16[b, :int(n[b])], path[b, :int(n[b])]) for b in range(4))


def test_row_keys_are_splitmix64_of_the_bits_in_python_integers():
    """row_keys (numpy's int64 on the CPU for a batch, Python integers for a few rows) against splitmix64
    written here on Python integers modulo 2^64: the products wrap and the shifts are logical, for any sign
    of the bits (negative joint values, a negative seed), whatever the batch; the key of a row alone, or in
    a small batch, equals its key in the large batch."""
    import struct

    from diffkin.motion import _search
    from diffkin.motion._search import row_keys

    M = (1 << 64) - 1

    def mix(x):
        x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & M
        x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & M
        return x ^ (x >> 31)

    def reference(qs, qg, seed):
        key = seed & M
        for v in (*qs, *qg):
            bits = struct.unpack("<Q", struct.pack("<d", v))[0]
            key = mix(key ^ ((bits + 0x9E3779B97F4A7C15) & M))
        return key - (1 << 64) if key >> 63 else key

    g = torch.Generator().manual_seed(5)
    B = 2 * _search._INT_ROWS + 3  # the batch in numpy, its rows alone and in small batches in Python ints
    qs = torch.randn(B, 7, generator=g, dtype=torch.float64) * 3
    qg = torch.randn(B, 7, generator=g, dtype=torch.float64) * 3
    qs[0] = 0.0
    qg[1] = -0.0
    for seed in (0, 12345, -7):
        key = row_keys(qs, qg, seed)
        assert key.dtype == torch.int64 and key.shape == (B,)
        assert key.tolist() == [reference(a.tolist(), b.tolist(), seed) for a, b in zip(qs, qg)]
        assert int(row_keys(qs[3:4], qg[3:4], seed)[0]) == int(key[3])
        assert torch.equal(row_keys(qs[2:2 + _search._INT_ROWS], qg[2:2 + _search._INT_ROWS], seed),
                           key[2:2 + _search._INT_ROWS])
    assert len(set(row_keys(qs, qg, 0).tolist())) == B


def test_cage_problem_spline_refined_not_the_polyline(monkeypatch):
    """A MotionBenchMaker cage problem (spherized Panda, half the default shortcut rounds): the cubic spline
    through its shortcut path leaves the clear region, so without refinement (REFINE_ROUNDS = 0, the
    default) it is timed along the polyline (a stop at each waypoint); refined (6 rounds: midpoints where
    the spline failed) it is a proven spline, faster; the motion keeps d >= 0 on its 10 ms samples by the
    closed-form torch distances."""
    from benchmarks import motion_problems as mp
    from diffkin.collision.boxes import sphere_box
    from diffkin.collision.cylinders import sphere_cylinder

    plan_mod = importlib.import_module("diffkin.motion.plan")  # the module (motion.plan is the function)
    probs = mp.load_problems(families=["cage"], indices=[2])
    chain = models.from_urdf(mp.PANDA_SPHERIZED_URDF, "panda_hand", dtype=torch.float64)
    rc = RobotCollision.from_urdf(mp.PANDA_SPHERIZED_URDF, chain, mp.PANDA_SRDF).requires_grad_(False)
    rc = rc.allow_collisions(probs[0].scene.allowed)
    w = probs[0].scene.to_world(dtype=torch.float64)
    qs = torch.tensor([probs[0].start], dtype=torch.float64)
    qg = torch.tensor([probs[0].goal], dtype=torch.float64)
    kw = dict(collision=rc, world=w, velocity_limit=mp.FRANKA_V, acceleration_limit=mp.FRANKA_A,
              jerk_limit=mp.FRANKA_J, max_iterations=30000, step=0.5, shortcut_rounds=8)
    raw = motion.plan(chain, qs, qg, **kw)  # REFINE_ROUNDS = 0, the default
    monkeypatch.setattr(plan_mod, "REFINE_ROUNDS", 6)
    res = motion.plan(chain, qs, qg, **kw)
    assert res.success.all() and raw.success.all(), (res.reason, raw.reason)
    assert raw.interpolation == ["linear"] and res.interpolation == ["spline"]
    assert float(res.duration[0]) < float(raw.duration[0])
    moving = ~torch.tensor(rc.fixed)
    a, _, r, *_ = rc.placed(res.q[0])
    a, r = a[:, moving, None], r[moving, None]
    d_box = sphere_box(a, r, w.boxes.center, w.boxes.rotation, w.boxes.half_extents)
    d_cyl = sphere_cylinder(a, r, w.cylinders[:, :3], w.cylinders[:, 3:6], w.cylinders[:, 6]) \
        if w.cylinders.numel() else d_box
    assert min(d_box.min(), d_cyl.min()) >= 0


def test_spline_marks_leave_room_for_the_fine_chords():
    """Each spline check point is the first of the fine samples past its mark: the marks' spacing leaves
    room for the longest fine chord, so check points are at most 0.95 · 2η of bound-length apart; a row
    whose chords are too long for its resolution (η = 5 µm, the finest rungs, on a path a metre long) is
    checked again with finer samples, and one that would need more than _FINE_MAX of them (η = 5 nm) is
    not proven."""
    from diffkin.motion._spline import _spline_failures

    class Clear:  # every configuration collision-free: the check points are recorded through clear()
        reach = torch.ones(1, dtype=torch.float64)

        def __init__(self, eta):
            self.eta, self.points = torch.tensor(eta, dtype=torch.float64), []

        def clear(self, q, problem):
            self.points.append((q[..., 0].clone(), problem.clone()))
            return torch.ones(q.shape[:-1], dtype=torch.bool)

        def eta_of(self, problem):
            return self.eta[problem]

    path = torch.tensor([[[0.0], [0.5], [1.0]]], dtype=torch.float64).expand(3, 3, 1)
    knots = torch.tensor([[0.0, 1.0, 2.0]], dtype=torch.float64).expand(3, 3)
    lim = torch.tensor([5.0], dtype=torch.float64)
    checker = Clear([0.005, 5e-6, 5e-9])
    bad = _spline_failures(checker, path, knots, -lim, lim, torch.arange(3))
    assert not bad[0].any() and not bad[1].any() and bad[2].all()
    for row, eta in ((0, 0.005), (1, 5e-6)):  # the check points that proved each row
        q = torch.cat([q[p == row] for q, p in checker.points])
        q = q.sort().values
        assert q[0] == 0 and q[-1] == 1 and q.diff().max() <= 0.95 * 2 * eta * (1 + 1e-9)
