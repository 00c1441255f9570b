"""One call of each newer public entry point on a device, against the same call on the CPU.

    python -m benchmarks.cuda_smoke --device cuda [--only NAME ...] [--float64-only]

Each case builds small inputs (a fixed seed, on the CPU, then moved), runs the entry point once on
``--device`` and once on the CPU, and prints one line: ``ok`` or ``FAIL``, the case, the dtype, the largest
absolute difference of the outputs from the CPU's, and the device call's seconds (CUDA synchronised; the
first call on a device includes its lazy initialisation). ``skip`` names a missing optional package. The
exit code is 1 when a case fails (an exception, an output off the device or in another dtype, a difference
above the case's tolerance).

What differs between the two calls is only the device: on CUDA the native C kernels do not serve, so the
torch paths run (the motion planner's torch search, the clip optimisation's torch rows); the CPU reference
is the ordinary call (C kernels where they serve). The randomness of every stage comes from CPU generators
(same streams on every device), so the iterative stages take the same branches and the tolerances are
rounding, not algorithmic, differences.

The same cases are the CPU stand-ins and the CUDA twins of ``tests/test_device_standin_motion.py``; ``--device
cpu`` runs the script in CI (``tests/test_cuda_smoke.py``). Optional packages: ``cv2`` (camera calibration's
initial poses and the synthetic scene), ``gymnasium`` (the environments), ``mujoco`` (the Imitate env's G1 and
the G1's self-collision model); every other case needs torch, numpy, scipy and pyyaml only.
"""

from __future__ import annotations

import argparse
import copy
import functools
import importlib
import sys
import time
import traceback
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from benchmarks.common import sync

__all__ = ["CASES", "Case", "compare", "main", "outputs", "run_case"]

F64, F32 = torch.float64, torch.float32
DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
FR3 = DATA / "urdf" / "fr3.urdf"
G1_URDF = DATA / "urdf" / "g1_29dof_rev_1_0.urdf"
#: the FR3's coarse link1 and link3 spheres always overlap (MoveIt's "Never" entry)
FR3_SRDF = ('<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" '
            'reason="Default"/></robot>')
SPHERES = [[0.45, 0.25, 0.45, 0.10], [0.40, -0.30, 0.70, 0.08]]
SCENE = """
world:
  collision_objects:
    - id: ball
      primitives: [{type: sphere, dimensions: [0.05]}]
      primitive_poses: [{position: [0.5, 0.1, 0.4], orientation: [0, 0, 0, 1]}]
    - id: table
      pose: {position: [0.6, 0, 0.2], orientation: [0, 0, 0.3826834323650898, 0.9238795325112867]}
      primitives:
        - {type: box, dimensions: [0.8, 0.4, 0.04]}
        - {type: cylinder, dimensions: [0.3, 0.02]}
      primitive_poses:
        - {position: [0, 0, 0], orientation: [0, 0, 0, 1]}
        - {position: [0.3, 0.1, -0.15], orientation: [0.7071067811865476, 0, 0, 0.7071067811865476]}
"""


@dataclass(frozen=True)
class Case:
    """``make(device, dtype)`` builds the inputs on ``device`` (outside the call) and returns the call, a
    thunk whose tensors (:func:`outputs`) are compared; ``atol`` per dtype; ``needs``: optional modules."""

    name: str
    make: Callable[[str, torch.dtype], Callable[[], object]]
    atol: dict
    needs: tuple[str, ...] = ()

    @property
    def dtypes(self) -> tuple[torch.dtype, ...]:
        return tuple(self.atol)

    def missing(self) -> list[str]:
        out = []
        for m in self.needs:
            try:
                importlib.import_module(m)
            except ImportError:
                out.append(m)
        return out


def outputs(out) -> list[torch.Tensor]:
    """The tensors of a call's result (nested tuples and lists), in order."""
    if isinstance(out, torch.Tensor):
        return [out]
    if isinstance(out, tuple | list):
        return [t for o in out for t in outputs(o)]
    return []


def compare(out, ref, device) -> float:
    """The largest absolute difference of ``out`` from ``ref`` (their tensors); raises AssertionError where
    an output is off ``device``, in another dtype or shape, or NaN where the reference is not."""
    out, ref = outputs(out), outputs(ref)
    assert len(out) == len(ref) > 0, (len(out), len(ref))
    worst = 0.0
    for i, (o, r) in enumerate(zip(out, ref)):
        assert o.device.type == torch.device(device).type, f"output {i} on {o.device}, expected {device}"
        assert o.dtype == r.dtype and o.shape == r.shape, (i, o.dtype, r.dtype, o.shape, r.shape)
        o, r = o.detach().cpu(), r.detach()
        if o.dtype == torch.bool or not o.is_floating_point():
            assert torch.equal(o, r), f"output {i}: {o} != {r}"
            continue
        assert torch.equal(o.isnan(), r.isnan()), f"output {i}: NaN unlike the CPU's"
        d = (o - r).abs().nan_to_num(0.0)
        worst = max(worst, float(d.max()) if d.numel() else 0.0)
    return worst


# ----------------------------------------------------------------------------------------- shared inputs
@functools.cache
def _fr3():
    from diffkin import models
    from diffkin.collision import RobotCollision

    chain = models.from_urdf(FR3, "fr3_link8", dtype=F64).requires_grad_(False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's meshes are not shipped: skipped with a warning
        rc = RobotCollision.from_urdf(FR3, chain, srdf=FR3_SRDF).requires_grad_(False)
    return rc


def _robot(device, dtype):
    """The FR3 and its capsule model on ``device`` in ``dtype`` (a copy: ``to`` works in place)."""
    rc = copy.deepcopy(_fr3())
    rc.chain.to(device=device, dtype=dtype)
    return rc.chain, rc.to(device=device, dtype=dtype)


def _pose(xyz, rotvec, dtype=F64, device="cpu"):
    from diffkin.rotations import rotvec_to_matrix
    from diffkin.transforms import make_transform

    t = lambda x: torch.tensor(x, dtype=dtype, device=device)  # noqa: E731
    return make_transform(rotvec_to_matrix(t(rotvec)), t(xyz))


def _rand(*shape, seed: int, dtype=F64):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=F64).to(dtype)


# ----------------------------------------------------------------------------------------------- cases
def _plan(device, dtype):
    """motion.plan through the torch search (the C search does not serve CUDA), optimised, with the implicit
    gradient w.r.t. the starts, the goals and the world's spheres; MotionResult.sample at given times. Two
    problems, each in its own scene (World.stack): one needs the RRT, the other is a short straight move."""
    from diffkin import motion
    from diffkin.collision import World
    from diffkin.motion.optimize import OptimizeConfig

    chain, rc = _robot(device, dtype)
    q = _plan_problem().to(device=device, dtype=dtype)
    sph = torch.tensor(SPHERES, dtype=dtype, device=device)
    t = torch.tensor([0.0, 0.05, 0.3, 0.6], dtype=dtype, device=device)

    def call():
        qs, qg, s = (x.clone().requires_grad_() for x in (q[[0, 0]], q[[1, 2]], sph))
        world = World.stack([World(spheres=s), World(spheres=s[:1])])
        res = motion.plan(chain, qs, qg, collision=rc, world=world, margin=0.005,
                          acceleration_limit=10.0, resolution=0.01, max_iterations=300,
                          optimize=OptimizeConfig(knots=16), search_in_c=torch.device(device).type != "cpu")
        (res.q.sum() + res.waypoints.square().sum()).backward()
        # the case exercises what it names: the RRT (more than two waypoints), the optimised knots kept
        # (whose implicit gradient reaches the starts, the goals and the spheres)
        assert bool(res.success.all()) and bool(res.optimized.all()) and int(res.n_waypoints[0]) > 2, \
            (res.reason, res.optimized, res.n_waypoints)
        assert all(bool(g.abs().sum() > 0) for g in (qs.grad, qg.grad, s.grad))
        return (res.success, res.optimized, res.n_waypoints, res.duration, res.q.detach(), res.qd,
                res.waypoints.detach(), res.sample(t), qs.grad, qg.grad, s.grad)

    return call


@functools.cache
def _plan_problem():
    """A start, a goal whose plan needs the RRT (the straight edge is not clear) and keeps its optimised
    knots, and a goal a short straight move from the start (3, 7), clear of the spheres."""
    from diffkin.collision import World
    from diffkin.sampling import random_configuration

    rc = _fr3()
    q = random_configuration(rc.chain, (8,), torch.Generator().manual_seed(3), collision=rc,
                             world=World(spheres=torch.tensor(SPHERES, dtype=F64)), margin=0.02)
    return torch.stack((q[1], q[5], q[1] + 0.05))


def _time_optimal(interpolation, jerk):
    def make(device, dtype):
        from diffkin.trajectories import time_optimal

        pts = torch.tensor([[[0.0, 1.0], [0.5, -0.2], [1.0, 0.3], [0.2, 0.8]],
                            [[0.0, 0.0], [0.1, 0.2], [0.3, 0.3], [0.6, 0.2]]], dtype=dtype, device=device)
        v = torch.tensor([1.0, 2.0], dtype=dtype, device=device)
        j = torch.tensor([[20.0, 30.0], [40.0, 50.0]], dtype=dtype, device=device) if jerk else None
        t = torch.linspace(0, 1.5, 7, dtype=dtype, device=device)

        def call():
            r = time_optimal(pts, v, 3.0, j, interpolation=interpolation, grid_per_segment=16)
            s = r.sample(t)
            return r.duration, s.position, s.velocity, s.acceleration, r.jerk(t)

        return call

    return make


def _cylinders_and_convex(device, dtype):
    """Every exported cylinder and convex-mesh distance on 16 random pairs."""
    from diffkin import collision as C
    from diffkin.rotations import rotvec_to_matrix

    u = lambda *s, seed: _rand(*s, seed=seed, dtype=dtype).to(device)  # noqa: E731
    a, b, c, r = u(16, 3, seed=1), u(16, 3, seed=2) + 0.2, u(16, 3, seed=3), 0.05 + 0.1 * u(16, seed=4)
    a2, b2 = u(16, 3, seed=5) + 0.5, u(16, 3, seed=6) + 0.7
    R, h = rotvec_to_matrix(u(16, 3, seed=7)), 0.05 + 0.2 * u(16, 3, seed=8)
    V1, V2 = 0.2 * u(16, 8, 3, seed=9) + c[:, None], 0.2 * u(16, 10, 3, seed=10) + a2[:, None]
    n = torch.nn.functional.normalize(u(16, 3, seed=11) - 0.5, dim=-1)
    off = u(16, seed=12)
    return lambda: (C.cylinder_cylinder(a, b, r, a2, b2, r), C.capsule_cylinder(a2, b2, r, a, b, r),
                    C.box_cylinder(c, R, h, a, b, r), C.sphere_cylinder(c, r, a, b, r),
                    C.point_cylinder(c, a, b, r), C.cylinder_halfspace(a, b, r, n, off),
                    C.convex_convex(V1, V2), C.capsule_convex(a, b, r, V2), C.box_convex(c, R, h, V2),
                    C.cylinder_convex(a, b, r, V2), C.convex_halfspace(V1, n, off))


def _worlds(device, dtype):
    """Three scenes: spheres, cylinders, a box and a half-space; a sphere and a point; none."""
    from diffkin.collision import World, box

    t = lambda x: torch.tensor(x, dtype=dtype, device=device)  # noqa: E731
    cyl = t([[0.4, -0.2, 0.1, 0.4, -0.2, 0.6, 0.06], [0.2, 0.3, 0.3, 0.5, 0.3, 0.3, 0.04]])
    w1 = World(spheres=t(SPHERES), cylinders=cyl, boxes=box(t([0.55, 0.0, 0.15]), t([0.10, 0.30, 0.02])),
               halfspaces=t([[0, 0, 1.0, -0.01]]))
    w2 = World(spheres=t(SPHERES[:1]), points=t([[0.3, 0.1, 0.5]]))
    return w1, w2, World(dtype=dtype, device=device)


def _world_stack(device, dtype):
    """World.stack of scenes of different sizes (one per row), cylinders among the obstacles: the robot's
    world distances, min_distance and the clearance decision."""
    from diffkin.collision import World

    chain, rc = _robot(device, dtype)
    w1, w2, w3 = _worlds(device, dtype)
    q = _rand(6, 7, seed=2, dtype=dtype).to(device) * 2 - 1

    def call():
        ws = World.stack([w1, w2, w1, w3, w2, w1])
        return (rc.world_distances(q, ws), rc.min_distance(q, ws), rc._clear(q, ws, margin=0.0),
                rc.world_distances(q, w1), rc._clear(q, w1, 0.01))

    return call


def _scene(device, dtype):
    """A MoveIt scene (YAML with a box, a sphere and a cylinder) read into a World on the device, exact
    cylinders and their enclosing capsules, and the robot's distances to it."""
    import tempfile

    from diffkin.collision import read_scene, read_world

    chain, rc = _robot(device, dtype)
    q = _rand(4, 7, seed=5, dtype=dtype).to(device) * 2 - 1
    path = Path(tempfile.mkdtemp()) / "scene.yaml"
    path.write_text(SCENE)

    def call():
        w = read_world(path, dtype=dtype, device=device)
        sc = read_scene(path)
        caps = sc.to_world(dtype=dtype, device=device, cylinders="capsules")
        return (*w.tensors(), *caps.tensors(), rc.world_distances(q, w), rc.world_distances(q, caps))

    return call


def _convex_robot(device, dtype):
    """A robot of convex geoms (built directly: no mesh files, no trimesh) and a capsule: self and world
    distances, min_distance, the clearance decision (torch on every device)."""
    from diffkin.collision import Geom, RobotCollision

    base = _fr3().chain
    g = torch.Generator().manual_seed(7)
    hulls = [(0.05 * torch.randn(12, 3, generator=g, dtype=F64)).tolist() for _ in range(3)]
    links = ["fr3_link3", "fr3_link5", "fr3_link7", "fr3_link0"]
    geoms = [Geom(f"hull{i}", k, "mesh", "convex") for i, k in enumerate(links[:3])] + \
        [Geom("base", "fr3_link0", "capsule", "capsule")]
    chain = base.copy().to(device=device, dtype=dtype)
    rc = RobotCollision(chain, geoms, links, [([0, 0, 0], [0, 0, 0.2], 0.05)], [],
                        [(0, 2), (1, 3), (0, 3), (2, 3)], convexes=hulls)
    w1 = _worlds(device, dtype)[0]
    q = _rand(5, 7, seed=4, dtype=dtype).to(device) * 2 - 1
    return lambda: (rc.self_distances(q), rc.world_distances(q, w1), rc.min_distance(q, w1),
                    rc._clear(q, w1, 0.0))


@functools.cache
def _g1(mjcf: bool = False):
    """The builtin G1 mapping and its chain: from the shipped URDF (no MuJoCo), or Menagerie's MJCF (MuJoCo
    compiles it) with its self-collision model."""
    from diffkin import models, retarget

    mp = retarget.Mapping.builtin("g1")
    if not mjcf:
        return mp, models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=F64), None
    chain = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=F64)
    return mp, chain, retarget.g1_collision(chain)


def _clip(warm_start, solver, mjcf=False):
    def make(device, dtype):
        """retarget.clip of six frames of the shipped walk on the G1: both stages, the whole-clip
        optimisation's torch rows (its C rows serve the CPU only), the metrics; ``mjcf``: Menagerie's G1
        with its self-collision pairs kept apart."""
        from diffkin import retarget

        mp, g1, rc = _g1(mjcf)
        if rc is not None:
            rc = copy.deepcopy(rc)
            g1 = rc.chain.to(device=device, dtype=dtype)
            rc = rc.to(device=device, dtype=dtype)
            # the MJCF body poses' companion chain is parsed from the model on first use: here, so the
            # stand-in sees the call (host-side parsing without device= reads there as a misplaced tensor)
            rc.self_distances(torch.zeros(1, g1.nq, dtype=dtype, device=device))
        else:
            g1 = g1.copy().to(device=device, dtype=dtype)
        walk = retarget.load_bvh(retarget.example_clips()["walk"]).frames_slice(0, 6)
        walk = retarget.Motion(walk.positions.to(device=device, dtype=dtype), walk.names, walk.fps)

        def call():
            r = retarget.clip(g1, walk, mp, max_iterations=4, iterations=2, warm_start=warm_start,
                              solver=solver, collision=rc)
            m = r.metrics
            return (r.q, r.scale, r.keypoints, r.contacts, r.cost,
                    *(getattr(m, k) for k in m.__dataclass_fields__))

        return call

    return make


def _metrics(device, dtype):
    """retarget.metrics of a short G1 clip (feet from the URDF's sole spheres) and their gradient."""
    from diffkin import retarget

    mp, g1, _ = _g1()
    g1 = g1.copy().to(device=device, dtype=dtype)
    q = torch.zeros(1, 3, g1.nq, dtype=dtype, device=device)
    q[..., 2], q[..., 3] = 0.79, 1.0
    q[:, 1, 8], q[:, 2, 9], q[:, 2, 2] = 0.2, -0.1, 0.81
    c = torch.tensor([[[True, True], [True, False], [False, True]]], device=device)

    def call():
        x = q.clone().requires_grad_()
        m = retarget.metrics(g1, x, c, 30, feet=mp.feet)
        (m.ground_penetration + m.floating + m.foot_skating).sum().backward()
        return (*(getattr(m, k) for k in m.__dataclass_fields__), x.grad)

    return call


def _velocity_tasks(device, dtype):
    """ik.solve_velocity with frame, posture and damping tasks under configuration,
    velocity and collision limits (the FR3, a sphere and a point)."""
    from diffkin import ik

    chain, rc = _robot(device, dtype)
    q = chain.clamp_to_limits(_rand(4, 7, seed=16, dtype=dtype).to(device) * 2 - 1)
    T = chain.forward_kinematics(q) @ _pose([0.03] * 3, [0.03] * 3, dtype, device)
    tasks = [ik.FrameTask("fr3_link8", target=T, lm_damping=1e-3),
             ik.PostureTask(torch.zeros(7, dtype=dtype, device=device), cost=0.1), ik.DampingTask(cost=1e-3)]
    world = _worlds(device, dtype)[1]  # (a sphere and a point: the collision rows' Jacobian is the cost)
    limits = [ik.ConfigurationLimit(), ik.VelocityLimit(1.0), ik.CollisionLimit(rc, world=world)]
    return lambda: ik.solve_velocity(chain, q, tasks, 0.02, limits=limits)


def _hand_eye(device, dtype):
    """hand_eye (AX = XB) and robot_world_hand_eye (AX = ZB) on exact poses of a panda, and project_points
    with distortion."""
    from diffkin import models
    from diffkin.calibration import hand_eye, project_points, robot_world_hand_eye
    from diffkin.transforms import transform_inverse

    chain = models.load("panda", dtype=F64)
    q = chain.random_configuration((10,), generator=torch.Generator().manual_seed(5))
    fk = chain.forward_kinematics(q)
    X = _pose([0.05, -0.02, 0.1], [0.3, -0.2, 0.1])  # the camera on the gripper
    Z = _pose([0.6, 0.1, 0.0], [0.0, 0.1, 1.2])  # the target in the base frame
    cam_target = transform_inverse(fk @ X) @ Z
    K = torch.tensor([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]], dtype=F64)
    dist = torch.tensor([0.05, -0.1, 0.001, 0.002, 0.01], dtype=F64)
    pts = _rand(20, 3, seed=9) * 0.2
    d = lambda x: x.to(device=device, dtype=dtype)  # noqa: E731
    fk, cam_target, K, dist, pts = map(d, (fk, cam_target, K, dist, pts))
    # three refinement steps of the default 10: each is a forward-mode Jacobian, the cost of this case
    steps = 3
    return lambda: (hand_eye(fk, cam_target, iterations=steps),
                    robot_world_hand_eye(fk, cam_target, iterations=steps),
                    project_points(pts, cam_target, K, dist))


def _calibrate_camera(device, dtype):
    """calibrate_camera of a UR5 with a camera on its flange and a chessboard (benchmarks.camera_scenes,
    noise-free pixels of 8 images): the camera's, the board's and the robot's geometry."""
    from benchmarks.camera_scenes import DIST, K, chessboard, images, scene
    from diffkin.calibration import calibrate_camera

    nominal, true, q, q_out, cam, board, _ = scene("ur5", 8)
    uv = images(true, q, cam, board, "eye_in_hand")
    d = lambda x: x.to(device=device, dtype=dtype)  # noqa: E731
    nominal = nominal.copy().to(device=device, dtype=dtype)
    q, q_out, uv, pts, Kd, dist = map(d, (q, q_out, uv, chessboard(), K, DIST))

    def call():
        r = calibrate_camera(nominal, q, uv, pts, camera_matrix=Kd, dist_coeffs=dist, setup="eye_in_hand",
                             cross_validation=0, progress=False)
        with torch.no_grad():
            return r.camera_pose, r.board_pose, r.chain.forward_kinematics(q_out)

    return call


def _env(env_id, **kw):
    def make(device, dtype):
        """TorchVectorEnv: reset and two steps of 3 envs (built outside the call: the model loads on the
        host)."""
        from diffkin.envs.vector import TorchVectorEnv

        env = TorchVectorEnv(env_id, 3, device=device, dtype=dtype, **kw)
        n = env.single_action_space.shape[0]
        act = (_rand(3, n, seed=0, dtype=dtype) * 2 - 1).to(device)

        def call():
            obs, _ = env.reset(seed=1)
            out = [obs]
            for _ in range(2):
                out.append(env.step(act)[:4])
            return [list(o.values()) if isinstance(o, dict) else o for o in out]

        return call

    return make


CASES = [
    Case("motion.plan (torch search, optimize, gradients, sample)", _plan, {F64: 1e-6}),
    *(Case(f"trajectories.time_optimal {i}{' jerk' if j else ''}", _time_optimal(i, j),
           {F64: 1e-9, F32: 1e-4}) for i in ("spline", "linear") for j in (False, True)),
    Case("collision cylinders and convex meshes", _cylinders_and_convex, {F64: 1e-9, F32: 2e-4}),
    Case("collision World.stack with cylinders", _world_stack, {F64: 1e-9, F32: 1e-4}),
    Case("collision read_world / read_scene", _scene, {F64: 1e-9, F32: 1e-4}),
    Case("collision convex robot", _convex_robot, {F64: 1e-9, F32: 2e-4}),
    *(Case(f"retarget.clip {w} {s}", _clip(w, s), {F64: 1e-6}) for w, s in
      (("batched", "banded"), ("sequential", "cg"))),
    Case("retarget.clip G1 MJCF with g1_collision", _clip("batched", "banded", mjcf=True), {F64: 1e-6},
         needs=("mujoco",)),
    Case("retarget.metrics", _metrics, {F64: 1e-9, F32: 1e-3}),
    Case("ik.solve_velocity tasks and limits", _velocity_tasks, {F64: 1e-8}),
    Case("calibration hand_eye / project_points", _hand_eye, {F64: 1e-8}),
    Case("calibration.calibrate_camera", _calibrate_camera, {F64: 1e-6}, needs=("cv2",)),
    Case("envs Track", _env("diffkin/Track-v0"), {F32: 1e-4}, needs=("gymnasium",)),
    Case("envs Reach cartesian", _env("diffkin/Reach-v0", action_mode="cartesian"), {F64: 1e-9},
         needs=("gymnasium",)),
    Case("envs Imitate (G1 MJCF)", _env("diffkin/Imitate-v0"), {F32: 1e-4}, needs=("gymnasium", "mujoco")),
]


def run_case(case: Case, device: str, dtype: torch.dtype) -> tuple[float, float]:
    """(largest difference from the CPU's outputs, seconds of the device call); raises on a failure."""
    ref = case.make("cpu", dtype)()
    call = case.make(device, dtype)
    sync(device)
    t0 = time.perf_counter()
    out = call()
    sync(device)
    seconds = time.perf_counter() - t0
    diff = compare(out, ref, device)
    if not diff <= case.atol[dtype]:
        raise AssertionError(f"max difference {diff:.3g} above the tolerance {case.atol[dtype]:.1g}")
    return diff, seconds


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--only", nargs="*", default=None, help="cases whose name contains one of these")
    p.add_argument("--float64-only", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    failed = 0
    for case in CASES:
        if args.only and not any(s in case.name for s in args.only):
            continue
        for dtype in case.dtypes:
            if args.float64_only and dtype != F64:
                continue
            label = f"{case.name} [{str(dtype).removeprefix('torch.')}]"
            if case.missing():
                print(f"skip  {label}: no {', '.join(case.missing())}", flush=True)
                continue
            try:
                diff, seconds = run_case(case, args.device, dtype)
                print(f"ok    {label}  max|diff| {diff:.2e}  {seconds:.3f} s", flush=True)
            except Exception as e:  # a failing case is a line, not the end of the run
                failed += 1
                where = traceback.extract_tb(e.__traceback__)[-1]
                print(f"FAIL  {label}: {type(e).__name__}: {str(e)[:300]} "
                      f"({Path(where.filename).name}:{where.lineno})", flush=True)
    print(f"{'FAIL' if failed else 'ok'}: {failed} case(s) failed on {args.device}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
