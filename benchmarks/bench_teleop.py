"""Differential IK at teleoperation rate: one velocity-IK step of diffkin's C path beside PlaCo, mink, pink.

    python -m benchmarks.bench_teleop [--steps 2000] [--rows 4096] [--quick]
    python -m benchmarks.run teleop

The step, on every side: a FrameTask on the Panda's ``hand`` (position and orientation cost 1, gain 1,
lm_damping 1e-3), a PostureTask (cost 1e-2, towards the start posture), the joint position limits
(ConfigurationLimit, gain 0.95) and |q̇| ≤ 2 rad/s (VelocityLimit), Δt = 2 ms (500 Hz), the target moving
on a 5 cm circle at 0.5 Hz while turning about its z axis; then q ← q ⊕ q̇ Δt. Each side runs its own loop
from the same start over the same targets, ``--steps`` steps (≥ 2 000), and the median time of a whole step
(set the target, solve, integrate) is reported, with the tracking error at the end. Each side's per-step
target objects are made before the loop (mink's and pink's SE(3) objects, diffkin's tensor views; PlaCo
takes a numpy row).

* ``diffkin C step``: :class:`diffkin.ik._native_velocity.NativeVelocity` ``.step`` (one foreign call: FK,
  Jacobian, mink's SE(3) error and log Jacobian, the QP and its exact box solve, the integration);
  ``diffkin solve_velocity`` the public function (routed to the same C step) where it exists.
* ``mink``: ``mink.solve_ik(..., solver="daqp")`` on the Menagerie Panda MJCF (compiled without meshes),
  ``Configuration.integrate_inplace``; it solves the same QP, so the two trajectories agree to rounding
  (the largest |q_diffkin − q_mink| over the loop is reported).
* ``PlaCo`` (KinematicsSolver, soft frame and joints tasks, joint and velocity limits) and ``pink``
  (``solve_ik`` with daqp, Pinocchio) read a URDF; both get the same Panda arm: the URDF written from the
  compiled MJCF (bodies ``link0`` … ``hand``, the seven hinges with their axes and ranges; the fingers are
  left out: their columns are zero in every side's frame task), checked here to give diffkin's MJCF FK to
  1e-12. PlaCo's weights are not mink's (its own QP), so only its time compares.

Then 4 096 Panda rows in one call of the C step against mink looped over rows (a teleoperation-like batch:
q within 0.3 rad of the start posture, each row's posture reference near its own q, each target its pose
moved by ~1 mm, three times the loop's per-tick motion; mink timed row by row on
256 of them, the median row times 4 096), and the Unitree G1 (floating base; both feet held by frame
tasks, both hands moving, posture, limits; knees and elbows bent at the start) beside mink, with the
largest |q̇_diffkin − q̇_mink| at mink's states along the loop (whole
trajectories are not compared: near the straight-knee singularity a 1e-12 difference grows along the
loop). The machine may be shared: ratios are measured in the same run.

Rows of the C step's v3 (``dk_vel`` version 3): ``teleop_panda_collision_step``, the Panda step plus a
CollisionLimit (the self pairs, the SRDF's disabled pairs applied, and three world spheres under and beside
the hand, detection 0.1 m, minimum distance 5 mm, gain 0.85) on VAMP's spherized Panda URDF (59 spheres, 690
self pairs; its ``panda_hand`` is the MJCF's ``hand`` to 4e-8 m), beside mink with a
CollisionAvoidanceLimit on the same URDF in MuJoCo and exactly the same pairs (spheres: the same QP; the two
steps agree to rounding at Δt = 1, where mink's bound γ(d − d_min)/Δt is CollisionLimit's γ(d − d_min):
tests/test_native_velocity_rows.py); ``teleop_fr3_collision_step``, the same on the FR3 (the Panda's
seven-joint successor, whose URDF collision model is capsules and spheres), where mink collides MuJoCo's
cylinders where diffkin has capsules (nearly, not exactly, the same problem; only the times compare); and
``teleop_g1_com_step``, the G1
step with a ComTask (the centre of mass held over its start, swaying 1 cm with the hands), on the chain of
``teleop_g1_step`` (nv 29, the fingers held) and on one that reaches every body (nv 43, MuJoCo's: the same
problem as mink's, the largest |Δq̇| at mink's states reported), each beside mink with its ComTask.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import cli

__all__ = ["run", "main", "panda_arm_urdf"]

ROOT = Path(__file__).resolve().parents[1]
PANDA = ROOT / "tests" / "data" / "mjcf" / "franka_emika_panda" / "panda.xml"
G1 = ROOT / "tests" / "data" / "mjcf" / "unitree_g1" / "g1.xml"
G1_ENDS = [("left_foot", "site"), ("right_foot", "site"), ("left_elbow_roll_link", "body"),
           ("right_elbow_roll_link", "body")]
# MuJoCo Menagerie's current 29-DoF G1 (no fingers: its four end links reach every body, nv 35 = MuJoCo's)
G1_29 = ROOT / "tests" / "data" / "mjcf" / "unitree_g1_29dof" / "g1.xml"
G1_29_ENDS = [("left_foot", "site"), ("right_foot", "site"), ("left_wrist_yaw_link", "body"),
              ("right_wrist_yaw_link", "body")]
DT, VMAX, POSTURE, LM = 0.002, 2.0, 1e-2, 1e-3
Q0 = [0.0, -0.4, 0.0, -2.2, 0.0, 1.9, 0.8]


def _rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF's fixed-axis roll, pitch, yaw of R = Rz(y) Ry(p) Rx(r)."""
    return (math.atan2(R[2, 1], R[2, 2]), math.asin(-max(-1.0, min(1.0, R[2, 0]))),
            math.atan2(R[1, 0], R[0, 0]))


def panda_arm_urdf(model, end: str = "hand", velocity: float = VMAX) -> str:
    """A kinematic URDF of the MuJoCo model's bodies from the world to ``end`` (hinge joints at the body
    origins, with their axes and ranges; jointless bodies fixed), for the peers that read URDF only."""
    import mujoco

    bodies, b = [], model.body(end).id
    while b != 0:
        bodies.append(b)
        b = int(model.body_parentid[b])
    out = ['<robot name="panda_arm">', '<link name="world"/>']
    for b in reversed(bodies):
        name, parent = model.body(b).name, model.body(int(model.body_parentid[b])).name or "world"
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, model.body_quat[b])
        xyz = " ".join(f"{v:.17g}" for v in model.body_pos[b])
        rpy = " ".join(f"{v:.17g}" for v in _rpy(R.reshape(3, 3)))
        out.append(f'<link name="{name}"/>')
        joints = [j for j in range(model.njnt) if model.jnt_bodyid[j] == b]
        if not joints:
            out.append(f'<joint name="{name}_fixed" type="fixed"><parent link="{parent}"/>'
                       f'<child link="{name}"/>'
                       f'<origin xyz="{xyz}" rpy="{rpy}"/></joint>')
            continue
        (j,) = joints
        if np.abs(model.jnt_pos[j]).max() > 0 or model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
            raise ValueError("panda_arm_urdf takes hinges at their body's origin")
        lo, hi = model.jnt_range[j]
        axis = " ".join(f"{v:.17g}" for v in model.jnt_axis[j])
        out.append(f'<joint name="{model.joint(j).name}" type="revolute"><parent link="{parent}"/>'
                   f'<child link="{name}"/><origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{axis}"/>'
                   f'<limit lower="{lo:.17g}" upper="{hi:.17g}" effort="100" velocity="{velocity}"/></joint>')
    out.append("</robot>")
    return "\n".join(out)


def _targets(T0: np.ndarray, steps: int) -> np.ndarray:
    """The moving target: T0 translated on a 5 cm circle (0.5 Hz) in its y-z plane and turned about its z
    axis by 0.3 sin(2π 0.25 t)."""
    t = np.arange(steps) * DT
    out = np.repeat(T0[None], steps, axis=0)
    w = 2 * math.pi * 0.5
    out[:, 1, 3] += 0.05 * np.sin(w * t)
    out[:, 2, 3] += 0.05 * (1 - np.cos(w * t))
    a = 0.3 * np.sin(2 * math.pi * 0.25 * t)
    Rz = np.zeros((steps, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 2, 2] = np.cos(a), -np.sin(a), 1
    Rz[:, 1, 0], Rz[:, 1, 1] = np.sin(a), np.cos(a)
    out[:, :3, :3] = T0[:3, :3] @ Rz
    return out


def _loop(step, targets: np.ndarray) -> tuple[list[int], object]:
    times = []
    state = None
    for k in range(len(targets)):
        t0 = time.perf_counter_ns()
        state = step(k)
        times.append(time.perf_counter_ns() - t0)
    return times, state


def _pos_err(T: np.ndarray, Tt: np.ndarray) -> float:
    return float(np.linalg.norm(T[:3, 3] - Tt[:3, 3]))


def _diffkin_side(targets):
    from diffkin.ik._native_velocity import NativeVelocity
    from diffkin.models import from_mjcf

    chain = from_mjcf(PANDA, "hand", dtype=torch.float64).requires_grad_(False)
    prob = NativeVelocity(chain, [(0, 1.0, 1.0, 1.0, LM)], posture=(POSTURE, 1.0, 0.0),
                          configuration_limit=(0.95, 0.0), velocity_limit=VMAX)
    q = torch.tensor(Q0, dtype=torch.float64)
    q_ref = q.clone()
    v = torch.empty(7, dtype=torch.float64)
    # the targets as (1, 4, 4) views made beforehand (as mink's SE3 objects are), the trajectory's rows as
    # the steps' q and next_q: the loop records it as it runs
    tgt = list(torch.from_numpy(targets).contiguous()[:, None])
    traj_t = torch.empty(len(targets) + 1, 7, dtype=torch.float64)
    rows = list(traj_t)

    def step(k):
        prob.step(rows[k], tgt[k], q_ref, DT, out=v, next_q=rows[k + 1])
        return rows[k + 1]

    traj_t[0] = q
    _loop(step, targets[:200])  # warm-up (the first call packs the chain)
    traj_t[0] = q
    times, _ = _loop(step, targets)
    traj = traj_t[1:].numpy()
    T = chain.forward_kinematics(torch.from_numpy(traj[-1])).numpy()
    return times, traj, _pos_err(T, targets[-1]), chain, prob


def _solve_velocity_side(chain, targets):
    from diffkin import ik

    if not hasattr(ik, "solve_velocity"):
        return None
    q = torch.tensor(Q0, dtype=torch.float64)
    q_ref = q.clone()
    tgt = list(torch.from_numpy(targets).contiguous())  # (4, 4) views made beforehand, as mink's SE3s
    limits = (ik.ConfigurationLimit(gain=0.95), ik.VelocityLimit(VMAX))
    posture = ik.PostureTask(q_ref, cost=POSTURE)
    state = [q]

    def step(k):
        task = ik.FrameTask(0, target=tgt[k], position_cost=1.0, orientation_cost=1.0, lm_damping=LM)
        v = ik.solve_velocity(chain, state[0], [task, posture], DT, limits=limits)
        state[0] = state[0] + v * DT  # q ⊕ v Δt: the Panda's joints are hinges
        return state[0]

    with torch.no_grad():
        _loop(step, targets[:200])
        state[0] = q
        times, qn = _loop(step, targets)
    return times, qn.numpy()


def _mink_side(targets):
    import mink

    from diffkin.models.mjcf import compile_mjcf

    model = compile_mjcf(PANDA)[0]
    cfg = mink.Configuration(model)
    q = np.zeros(model.nq)
    q[:7] = Q0
    frame = mink.FrameTask("hand", "body", position_cost=1.0, orientation_cost=1.0, gain=1.0, lm_damping=LM)
    posture = mink.PostureTask(model, cost=POSTURE)
    arm = [model.joint(i).name for i in range(7)]
    limits = [mink.ConfigurationLimit(model, gain=0.95), mink.VelocityLimit(model, dict.fromkeys(arm, VMAX))]
    posture.set_target(q)
    traj = np.empty((len(targets), 7))
    se3 = [mink.SE3.from_matrix(T) for T in targets]

    def step(k):
        frame.set_target(se3[k])
        v = mink.solve_ik(cfg, [frame, posture], DT, "daqp", damping=1e-12, limits=limits)
        cfg.integrate_inplace(v, DT)
        traj[k] = cfg.q[:7]
        return cfg.q

    cfg.update(q)
    _loop(step, targets[:200])
    cfg.update(q)
    times, _ = _loop(step, targets)
    T = cfg.get_transform_frame_to_world("hand", "body").as_matrix()
    return times, traj, _pos_err(T, targets[-1]), model


def _placo_side(urdf: str, targets):
    import placo

    robot = placo.RobotWrapper(urdf, placo.Flags.ignore_collisions)
    for i, name in enumerate(robot.joint_names()):
        robot.set_joint(name, Q0[i])
    robot.set_velocity_limits(VMAX)
    robot.update_kinematics()
    solver = placo.KinematicsSolver(robot)
    solver.mask_fbase(True)
    solver.dt = DT
    solver.enable_joint_limits(True)
    solver.enable_velocity_limits(True)
    frame = solver.add_frame_task("hand", targets[0])
    frame.configure("hand", "soft", 1.0, 1.0)
    joints = solver.add_joints_task()
    joints.set_joints({name: Q0[i] for i, name in enumerate(robot.joint_names())})
    joints.configure("posture", "soft", POSTURE)

    def step(k):
        frame.T_world_frame = targets[k]
        solver.solve(True)
        robot.update_kinematics()

    _loop(step, targets[:200])
    times, _ = _loop(step, targets)
    return times, _pos_err(robot.get_T_world_frame("hand"), targets[-1])


def _pink_side(urdf: str, targets):
    import pink
    import pinocchio as pin
    from pink.limits import ConfigurationLimit, VelocityLimit

    model = pin.buildModelFromUrdf(urdf)
    data = model.createData()
    q = np.array(Q0)
    cfg = pink.Configuration(model, data, q)
    frame = pink.FrameTask("hand", position_cost=1.0, orientation_cost=1.0, lm_damping=LM)
    posture = pink.PostureTask(cost=POSTURE)
    posture.set_target(q)
    limits = [ConfigurationLimit(model, config_limit_gain=0.95), VelocityLimit(model)]
    se3 = [pin.SE3(T[:3, :3].copy(), T[:3, 3].copy()) for T in targets]
    state = [cfg]

    def step(k):
        frame.set_target(se3[k])
        v = pink.solve_ik(state[0], [frame, posture], DT, solver="daqp", limits=limits)
        state[0].integrate_inplace(v, DT)

    _loop(step, targets[:200])
    state[0] = pink.Configuration(model, data, q.copy())
    times, _ = _loop(step, targets)
    T = state[0].get_transform_frame_to_world("hand").homogeneous
    return times, _pos_err(np.asarray(T), targets[-1])


def _median_us(times) -> float:
    return statistics.median(times) / 1e3


def _batch_rows(chain, prob, model, B: int, mink_rows: int):
    """4 096 teleoperation-like rows in one call against mink looped (per row)."""
    import mink

    g = torch.Generator().manual_seed(0)
    q0 = torch.tensor(Q0, dtype=torch.float64)
    q = q0 + 0.3 * torch.randn(B, 7, generator=g, dtype=torch.float64)
    q = chain.clamp_to_limits(q)
    T = chain.forward_kinematics(q)
    step = torch.zeros(B, 4, 4, dtype=torch.float64)
    step[:, :3, 3] = 1e-3 * torch.randn(B, 3, generator=g, dtype=torch.float64)
    T_t = (T + step)[:, None].contiguous()
    q_ref = q + 0.01 * torch.randn(B, 7, generator=g, dtype=torch.float64)  # each row's own home posture
    prob.solve(q, T_t, q_ref, DT)
    reps = []
    for _ in range(5):
        t0 = time.perf_counter()
        v, ok = prob.solve(q, T_t, q_ref, DT)
        reps.append(time.perf_counter() - t0)
    t_ours = statistics.median(reps)
    cfg = mink.Configuration(model)
    frame = mink.FrameTask("hand", "body", position_cost=1.0, orientation_cost=1.0, gain=1.0, lm_damping=LM)
    posture = mink.PostureTask(model, cost=POSTURE)
    qm = np.zeros(model.nq)
    qm[:7] = Q0
    posture.set_target(qm)
    arm = [model.joint(i).name for i in range(7)]
    limits = [mink.ConfigurationLimit(model, gain=0.95), mink.VelocityLimit(model, dict.fromkeys(arm, VMAX))]
    worst, per_row = 0.0, []
    for i in range(mink_rows):
        t0 = time.perf_counter()
        qm[:7] = q_ref[i].numpy()
        posture.set_target(qm)
        qm[:7] = q[i].numpy()
        cfg.update(qm)
        frame.set_target(mink.SE3.from_matrix(T_t[i, 0].numpy()))
        vm = mink.solve_ik(cfg, [frame, posture], DT, "daqp", damping=1e-12, limits=limits)
        per_row.append(time.perf_counter() - t0)
        worst = max(worst, float(np.abs(vm[:7] - v[i].numpy()).max()))
    t_mink = statistics.median(per_row)
    return t_ours, t_mink, worst, bool(ok.all())


def _g1_mink(model, ends, costs, steps: int):
    """The G1 problem both G1 rows share, on mink's side: the start (knees and elbows bent, away from the
    straight-leg singularity), mink's frame tasks, posture task and limits, and the target trajectory (feet
    held, hands on a 8 cm circle at 0.5 Hz) -> ``(cfg, q0, tasks, posture, limits, targets (steps, K, 4, 4),
    phase (steps,))``."""
    import mink

    cfg = mink.Configuration(model)
    q0 = model.qpos0.copy()
    bent = {"hip_pitch": -0.3, "knee": 0.6, "ankle_pitch": -0.3, "elbow_pitch": 1.0, "elbow_joint": 1.0}
    for j in range(1, model.njnt):
        q0[model.jnt_qposadr[j]] = next((a for key, a in bent.items() if key in model.joint(j).name), 0.0)
    cfg.update(q0)
    T0 = [cfg.get_transform_frame_to_world(e, t).as_matrix() for e, t in ends]
    tasks = [mink.FrameTask(e, t, position_cost=p, orientation_cost=o, gain=1.0, lm_damping=LM)
             for (e, t), (p, o) in zip(ends, costs)]
    posture = mink.PostureTask(model, cost=POSTURE)
    posture.set_target(q0)
    hinges = [model.joint(i).name for i in range(model.njnt) if model.jnt_type[i] != 0]
    limits = [mink.ConfigurationLimit(model, gain=0.95),
              mink.VelocityLimit(model, dict.fromkeys(hinges, VMAX * 2))]
    phase = 2 * math.pi * 0.5 * np.arange(steps) * DT
    hand = 0.08 * np.stack([np.zeros_like(phase), np.sin(phase), 1 - np.cos(phase)], -1)
    targets = np.repeat(np.stack(T0)[None], steps, axis=0)
    targets[:, 2:, :3, 3] += hand[:, None]
    return cfg, q0, tasks, posture, limits, targets, phase


def _g1(steps: int):
    import mink

    from diffkin.ik._native_velocity import NativeVelocity
    from diffkin.models import from_mjcf
    from diffkin.models.mjcf import compile_mjcf

    chain = from_mjcf(G1, [e for e, _ in G1_ENDS], dtype=torch.float64).requires_grad_(False)
    model = compile_mjcf(G1)[0]
    qadr, dofs = chain.qpos_index(), chain.dof_index()  # MuJoCo's qpos / qvel entries of q and v
    costs = [(1.0, 1.0), (1.0, 1.0), (1.0, 0.5), (1.0, 0.5)]
    vmax = torch.full((chain.nv,), VMAX * 2, dtype=torch.float64)
    vmax[:6] = math.inf
    prob = NativeVelocity(chain, [(k, p, o, 1.0, LM) for k, (p, o) in enumerate(costs)],
                          posture=(POSTURE, 1.0, 0.0),
                          configuration_limit=(0.95, 0.0), velocity_limit=vmax)
    cfg, q0, tasks, posture, limits, targets, _ = _g1_mink(model, G1_ENDS, costs, steps)
    tgt = torch.from_numpy(targets).contiguous()
    q = torch.tensor(q0[qadr])
    q_ref = q.clone()
    qs = [q.clone(), torch.empty_like(q)]
    v = torch.empty(chain.nv, dtype=torch.float64)

    tgts = list(tgt)  # (4, 4, 4) views made beforehand, as mink's SE3 objects

    def ours(k):
        prob.step(qs[k % 2], tgts[k], q_ref, DT, out=v, next_q=qs[(k + 1) % 2])

    _loop(ours, targets[:100])
    qs[0].copy_(q)
    times_ours, _ = _loop(ours, targets)
    q_ours = qs[steps % 2].numpy().copy()
    se3 = [[mink.SE3.from_matrix(T) for T in Ts] for Ts in targets]

    def theirs(k):
        for task, T in zip(tasks, se3[k]):
            task.set_target(T)
        vm = mink.solve_ik(cfg, [*tasks, posture], DT, "daqp", damping=1e-12, limits=limits)
        cfg.integrate_inplace(vm, DT)

    n_mink = min(steps, 500)
    times_mink, _ = _loop(theirs, targets[:n_mink])
    cfg.update(q0)
    agree = 0.0
    for k in range(n_mink):  # the same loop again: both steps at mink's states agree
        for task, T in zip(tasks, se3[k]):
            task.set_target(T)
        vm = mink.solve_ik(cfg, [*tasks, posture], DT, "daqp", damping=1e-12, limits=limits)
        if k % 5 == 0:
            mine, _ = prob.solve(torch.from_numpy(cfg.q[qadr])[None], tgt[k][None], q_ref, DT)
            agree = max(agree, float(np.abs(mine[0].numpy() - vm[dofs]).max()))
        cfg.integrate_inplace(vm, DT)
    feet = max(float(np.linalg.norm(chain.forward_kinematics(torch.from_numpy(q_ours))[k, :3, 3].numpy()
                                    - targets[0, k, :3, 3])) for k in range(2))
    return _median_us(times_ours), _median_us(times_mink), agree, feet, chain.nv


FR3 = ROOT / "tests" / "data" / "urdf" / "fr3.urdf"
FR3_SRDF = ('<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" '
            'reason="Default"/></robot>')
VAMP_PANDA = ROOT / "tests" / "data" / "vamp_panda" / "panda_spherized.urdf"
DETECT, D_MIN, C_GAIN = 0.1, 0.005, 0.85  # the CollisionLimit of the collision rows
#: the robots of the collision rows: (URDF, SRDF, end link). The FR3: capsules and spheres (its mesh geoms
#: are not shipped); VAMP's spherized Panda: 59 spheres, its MoveIt SRDF's 34 disabled pairs, the hand of
#: the Menagerie Panda's rows (the same frame, to 4e-8 m)
COLLISION_ROBOTS = {"fr3": (FR3, FR3_SRDF, "fr3_link8"),
                    "panda": (VAMP_PANDA, VAMP_PANDA.with_name("panda.srdf"), "panda_hand")}


def _fr3_world(T0: np.ndarray) -> np.ndarray:
    """Three world spheres (x, y, z, r): under and beside the start flange (the loop's circle passes them)
    and one away from the arm."""
    p = T0[:3, 3]
    return np.array([[p[0], p[1], p[2] - 0.15, 0.05], [p[0] + 0.2, p[1], p[2], 0.04], [0.5, 0.5, 0.2, 0.1]])


def collision_robot(name: str, dtype=torch.float64):
    """``(chain, rc)``: the chain to the end link and its RobotCollision (the SRDF's disabled pairs
    applied) of a robot of :data:`COLLISION_ROBOTS`."""
    import warnings

    from diffkin.collision import RobotCollision
    from diffkin.models import from_urdf

    urdf, srdf, end = COLLISION_ROBOTS[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's mesh geoms are not shipped: skipped with a warning
        chain = from_urdf(urdf, end, dtype=dtype).requires_grad_(False)
        rc = RobotCollision.from_urdf(urdf, chain, srdf=srdf).requires_grad_(False)
    return chain, rc


def collision_mink_model(name: str, spheres: np.ndarray):
    """The robot's URDF in MuJoCo for mink: visuals and mesh geoms dropped (the FR3's files are not
    shipped), the capsule links' cylinders and spheres kept (MuJoCo collides the cylinders as cylinders),
    fixed links kept as bodies (``fusestatic="false"``: the end link is a body, the frame task the same
    function as diffkin's), the world spheres added as fixed mocap bodies ``obstacle0`` ..."""
    import re

    import mujoco

    text = COLLISION_ROBOTS[name][0].read_text()
    text = re.sub(r"<visual>.*?</visual>", "", text, flags=re.S)
    text = re.sub(r"<collision>(?:(?!</collision>).)*<mesh.*?</collision>", "", text, flags=re.S)
    text = re.sub(r"(<robot[^>]*>)", r'\1<mujoco><compiler fusestatic="false"/></mujoco>', text, count=1)
    spec = mujoco.MjSpec.from_string(text)  # no saved-XML round trip: it rounds the constants (~1e-7 m)
    for i, (x, y, z, r) in enumerate(spheres):
        # mocap: a weld of its own, else mink's parent-child filter drops the first link against it
        body = spec.worldbody.add_body(name=f"obstacle{i}", pos=[x, y, z], mocap=True)
        body.add_geom(name=f"obstacle{i}", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[r, 0.0, 0.0])
    return spec.compile()


def collision_mink_pairs(model, rc, q0) -> list:
    """diffkin's pair set for mink's CollisionAvoidanceLimit ``geom_pairs``: each of ``rc``'s self pairs as
    a pair of one-geom groups, and every robot geom against the obstacles. Each diffkin geom (a sphere or a
    capsule) is the MuJoCo geom at its centre with its radius at ``q0`` (mj_kinematics); mink's own filters
    (same weld, parent and child) keep all of these pairs but the base's geoms against the obstacles
    (constant distances, which diffkin's CollisionLimit leaves out too: ``RobotCollision.skip_fixed``)."""
    import mujoco

    if any(g.shape == "box" for g in rc.geoms):
        raise ValueError("collision_mink_pairs takes spheres and capsules (a box geom has no radius)")
    data = mujoco.MjData(model)
    data.qpos[:] = q0
    mujoco.mj_kinematics(model, data)
    a, b, r = (x.numpy() for x in rc.placed(torch.as_tensor(q0))[:3])
    gap = (np.linalg.norm(data.geom_xpos[None] - (a + b)[:, None] / 2, axis=-1)
           + np.abs(model.geom_size[None, :, 0] - r[:, None]))
    ids = gap.argmin(-1)
    if gap.min(-1).max() > 1e-6 or len(set(ids.tolist())) != len(ids):
        raise AssertionError(f"the MuJoCo geoms are not diffkin's ({gap.min(-1).max():.3g} m)")
    index = {g.name: int(ids[k]) for k, g in enumerate(rc.geoms)}
    obstacles = [i for i in range(model.ngeom) if model.geom(i).name.startswith("obstacle")]
    return [([index[x]], [index[y]]) for x, y in rc.pairs] + [(ids.tolist(), obstacles)]


def _collision(name: str, steps: int):
    """A collision row: the Panda step (frame task, posture, configuration and velocity limits) plus a
    CollisionLimit on the robot's self pairs and three world spheres, the C step (NativeVelocity.step: FK,
    the distances and their gradients, the QP with the rows solved exactly) beside mink with a
    CollisionAvoidanceLimit on the same URDF's geoms in MuJoCo and the same pairs
    (:func:`collision_mink_pairs`); returns (ours µs, mink µs, our smallest distance over the loop, steps
    whose collision rows were detected (%))."""
    import mink

    from diffkin.collision import World
    from diffkin.ik._native_velocity import NativeVelocity
    from diffkin.ik.residuals import DistanceConstraint

    chain, rc = collision_robot(name)
    end = COLLISION_ROBOTS[name][2]
    q = torch.tensor(Q0, dtype=torch.float64)
    T0 = chain.forward_kinematics(q).numpy()
    spheres = _fr3_world(T0)
    world = World(spheres=torch.tensor(spheres))
    prob = NativeVelocity(chain, [(0, 1.0, 1.0, 1.0, LM)], posture=(POSTURE, 1.0, 0.0),
                          configuration_limit=(0.95, 0.0), velocity_limit=VMAX,
                          collision=(rc, world, C_GAIN, D_MIN, DETECT))
    targets = _targets(T0, steps)
    tgt = torch.from_numpy(targets).contiguous()
    q_ref = q.clone()
    qs = [q.clone(), torch.empty_like(q)]
    v = torch.empty(7, dtype=torch.float64)
    traj = np.empty((steps, 7))

    def ours(k):
        prob.step(qs[k % 2], tgt[k:k + 1], q_ref, DT, out=v, next_q=qs[(k + 1) % 2])

    def record(k):
        ours(k)
        traj[k] = qs[(k + 1) % 2].numpy()

    _loop(ours, targets[:200])
    qs[0].copy_(q)
    times_ours, _ = _loop(record, targets)
    with torch.no_grad():
        d = DistanceConstraint(rc, world).distances(torch.from_numpy(traj))
    detected = float((d < DETECT).any(-1).double().mean()) * 100
    model = collision_mink_model(name, spheres)
    cfg = mink.Configuration(model)
    qm = np.array(Q0)
    frame = mink.FrameTask(end, "body", position_cost=1.0, orientation_cost=1.0, gain=1.0, lm_damping=LM)
    posture = mink.PostureTask(model, cost=POSTURE)
    posture.set_target(qm)
    arm = [model.joint(i).name for i in range(model.njnt)]
    limits = [mink.ConfigurationLimit(model, gain=0.95), mink.VelocityLimit(model, dict.fromkeys(arm, VMAX)),
              mink.CollisionAvoidanceLimit(model, collision_mink_pairs(model, rc, qm), gain=C_GAIN,
                                           minimum_distance_from_collisions=D_MIN,
                                           collision_detection_distance=DETECT)]
    se3 = [mink.SE3.from_matrix(T) for T in targets]

    def theirs(k):
        frame.set_target(se3[k])
        vm = mink.solve_ik(cfg, [frame, posture], DT, "daqp", damping=1e-12, limits=limits)
        cfg.integrate_inplace(vm, DT)

    n_mink = min(steps, 500)
    cfg.update(qm)
    _loop(theirs, targets[:50])
    cfg.update(qm)
    times_mink, _ = _loop(theirs, targets[:n_mink])
    return _median_us(times_ours), _median_us(times_mink), float(d.min()), detected


def _g1_com(steps: int, every_body: bool = True, path: Path = G1, ends: list = G1_ENDS):
    """The G1 step of :func:`_g1` with a ComTask (cost (5, 5, 1): the centre of mass held over its start,
    moving 1 cm sideways with the hands) in the C step, beside mink with its ComTask. ``every_body``: the
    chain reaches every body (the hands' leaves too: nv 43 = MuJoCo's), so the two solve the same problem,
    compared at mink's states (largest |Δq̇|); else the chain of :func:`_g1` (nv 29: the fingers held at
    qpos0, their masses still in the centre of mass), whose time compares with ``teleop_g1_step`` (mink
    then also moves the fingers: no agreement reported)."""
    import mink

    from diffkin.ik._native_velocity import NativeVelocity
    from diffkin.models import from_mjcf
    from diffkin.models.mjcf import compile_mjcf

    model = compile_mjcf(path)[0]
    leaves = [model.body(b).name for b in range(1, model.nbody)
              if not any(model.body_parentid[k] == b for k in range(model.nbody))
              and "ankle" not in model.body(b).name and model.body(b).name not in dict(ends)] \
        if every_body else []
    chain = from_mjcf(path, [e for e, _ in ends] + leaves, dtype=torch.float64).requires_grad_(False)
    qadr, dofs = chain.qpos_index(), chain.dof_index()
    costs = [(1.0, 1.0), (1.0, 1.0), (1.0, 0.5), (1.0, 0.5)]
    com_cost = [5.0, 5.0, 1.0]
    vmax = torch.full((chain.nv,), VMAX * 2, dtype=torch.float64)
    vmax[:6] = math.inf
    prob = NativeVelocity(chain, [(k, p, o, 1.0, LM) for k, (p, o) in enumerate(costs)],
                          posture=(POSTURE, 1.0, 0.0), configuration_limit=(0.95, 0.0), velocity_limit=vmax,
                          com=(com_cost, 1.0, 0.0))
    cfg, q0, tasks, posture, limits, targets, phase = _g1_mink(model, ends, costs, steps)
    c0 = cfg.data.subtree_com[1].copy()
    com_task = mink.ComTask(cost=com_cost)
    coms = np.repeat(c0[None], steps, axis=0)
    coms[:, 1] += 0.01 * np.sin(phase)
    tgt, ctg = torch.from_numpy(targets).contiguous(), torch.from_numpy(coms).contiguous()
    q = torch.tensor(q0[qadr])
    q_ref = q.clone()
    qs = [q.clone(), torch.empty_like(q)]
    v = torch.empty(chain.nv, dtype=torch.float64)

    def ours(k):
        prob.step(qs[k % 2], tgt[k], q_ref, DT, out=v, next_q=qs[(k + 1) % 2], com_target=ctg[k])

    _loop(ours, targets[:100])
    qs[0].copy_(q)
    times_ours, _ = _loop(ours, targets)
    se3 = [[mink.SE3.from_matrix(T) for T in Ts] for Ts in targets]

    def theirs(k):
        for task, T in zip(tasks, se3[k]):
            task.set_target(T)
        com_task.set_target(coms[k])
        vm = mink.solve_ik(cfg, [*tasks, com_task, posture], DT, "daqp", damping=1e-12, limits=limits)
        cfg.integrate_inplace(vm, DT)
        return vm

    n_mink = min(steps, 500)
    times_mink, _ = _loop(theirs, targets[:n_mink])
    cfg.update(q0)
    agree = 0.0 if every_body else None
    for k in range(0, n_mink if every_body else 0, 5):  # both steps at mink's states
        qk = torch.from_numpy(cfg.q[qadr])
        vm = theirs(k)
        mine, _ = prob.solve(qk[None], tgt[k][None], q_ref, DT, com_target=ctg[k])
        agree = max(agree, float(np.abs(mine[0].numpy() - vm[dofs]).max()))
    return _median_us(times_ours), _median_us(times_mink), agree, chain.nv


def run(args) -> list[dict]:
    quick = getattr(args, "quick", False)
    steps = 300 if quick else max(2000, getattr(args, "steps", 2000))
    B = 256 if quick else getattr(args, "rows", 4096)
    torch.set_num_threads(1)
    from diffkin.models import from_mjcf

    chain0 = from_mjcf(PANDA, "hand", dtype=torch.float64).requires_grad_(False)
    T0 = chain0.forward_kinematics(torch.tensor(Q0, dtype=torch.float64)).numpy()
    targets = _targets(T0, steps)
    rows = []
    with torch.no_grad():
        times, traj, err, chain, prob = _diffkin_side(targets)
    rows.append(dict(benchmark="teleop_panda_step", impl="diffkin C step (NativeVelocity.step)", steps=steps,
                     median_us=_median_us(times), p99_us=float(np.percentile(times, 99)) / 1e3,
                     final_pos_err_m=err))
    sv = _solve_velocity_side(chain, targets)
    if sv is not None:
        rows.append(dict(benchmark="teleop_panda_step",
                         impl="diffkin ik.solve_velocity (+ FrameTask, q + v dt)",
                         steps=steps,
                         median_us=_median_us(sv[0]), p99_us=float(np.percentile(sv[0], 99)) / 1e3))
    peers = {}
    try:
        t_m, traj_m, err_m, model = _mink_side(targets)
        peers["mink"] = (t_m, err_m, float(np.abs(traj_m - traj).max()))
    except ImportError as e:
        print(f"[teleop] mink skipped: {e}")
        model = None
    if model is not None:
        fd = tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False)
        fd.write(panda_arm_urdf(model))
        fd.close()
        from diffkin.models import from_urdf

        check = from_urdf(Path(fd.name), "hand", dtype=torch.float64).requires_grad_(False)
        qq = chain.random_configuration(64).detach()
        urdf_fk = float((check.forward_kinematics(qq) - chain.forward_kinematics(qq)).abs().max())
        if urdf_fk > 1e-12:
            raise AssertionError(f"the written URDF is not the MJCF Panda ({urdf_fk})")
        for name, side in (("PlaCo", _placo_side), ("pink", _pink_side)):
            try:
                t_p, err_p = side(fd.name, targets)
                peers[name] = (t_p, err_p, None)
            except ImportError as e:
                print(f"[teleop] {name} skipped: {e}")
    ours = _median_us(times)
    for name, (t_p, err_p, agree) in peers.items():
        row = dict(benchmark="teleop_panda_step", impl=name, steps=steps, median_us=_median_us(t_p),
                   p99_us=float(np.percentile(t_p, 99)) / 1e3, final_pos_err_m=err_p,
                   ratio_to_diffkin=_median_us(t_p) / ours)
        if agree is not None:
            row["max_abs_q_diff_vs_diffkin"] = agree
        rows.append(row)
    if model is not None:
        with torch.no_grad():
            t_ours, t_mink, worst, ok = _batch_rows(chain, prob, model, B, 64 if quick else 256)
        rows.append(dict(benchmark="teleop_panda_batch", impl="diffkin C step, one call", batch=B,
                         ms=1e3 * t_ours, us_per_row=1e6 * t_ours / B, all_ok=ok))
        rows.append(dict(benchmark="teleop_panda_batch", impl="mink looped", batch=B, ms=1e3 * t_mink * B,
                         us_per_row=1e6 * t_mink, ratio_to_diffkin=t_mink * B / t_ours,
                         max_abs_v_diff=worst))
        with torch.no_grad():
            g_ours, g_mink, agree, feet, nv = _g1(300 if quick else steps)
        rows.append(dict(benchmark="teleop_g1_step", impl=f"diffkin C step (nv {nv})", steps=steps,
                         median_us=g_ours, feet_drift_m=feet))
        rows.append(dict(benchmark="teleop_g1_step", impl="mink", median_us=g_mink,
                         ratio_to_diffkin=g_mink / g_ours,
                         max_abs_v_diff=agree))
        for robot in COLLISION_ROBOTS:  # v3 rows: CollisionLimit and ComTask in the C step
            with torch.no_grad():
                c_ours, c_mink, dmin, detected = _collision(robot, 300 if quick else steps)
            bench = f"teleop_{robot}_collision_step"
            rows.append(dict(benchmark=bench, impl="diffkin C step (+ CollisionLimit)", steps=steps,
                             median_us=c_ours, min_distance_m=dmin, steps_with_rows_pct=detected))
            rows.append(dict(benchmark=bench, impl="mink (+ CollisionAvoidanceLimit)", median_us=c_mink,
                             ratio_to_diffkin=c_mink / c_ours))
        for every in (False, True):
            with torch.no_grad():
                m_ours, m_mink, m_agree, m_nv = _g1_com(300 if quick else steps, every)
            rows.append(dict(benchmark="teleop_g1_com_step", impl=f"diffkin C step (+ ComTask, nv {m_nv})",
                             steps=steps, median_us=m_ours))
            row = dict(benchmark="teleop_g1_com_step", impl="mink (+ ComTask, nv 43)", median_us=m_mink,
                       ratio_to_diffkin=m_mink / m_ours)
            if m_agree is not None:
                row["max_abs_v_diff"] = m_agree
            rows.append(row)
        with torch.no_grad():  # the G1: Menagerie's current 29-DoF model, every body (nv 35)
            m_ours, m_mink, m_agree, m_nv = _g1_com(300 if quick else steps, True, G1_29, G1_29_ENDS)
        rows.append(dict(benchmark="teleop_g1_29dof_com_step", impl=f"diffkin C step (+ ComTask, nv {m_nv})",
                         steps=steps, median_us=m_ours))
        rows.append(dict(benchmark="teleop_g1_29dof_com_step", impl=f"mink (+ ComTask, nv {m_nv})",
                         median_us=m_mink, ratio_to_diffkin=m_mink / m_ours, max_abs_v_diff=m_agree))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--rows", type=int, default=4096)
    return cli(p, run, "differential IK at teleoperation rate (medians; ratios in the same run)", argv)


if __name__ == "__main__":
    raise SystemExit(main())
