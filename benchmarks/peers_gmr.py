"""GMR (General Motion Retargeting, github.com/YanjieZe/GMR) as a peer of ``retarget.clip``.

GMR is not on the package index; the benchmark imports it when it is installed (``pip install --no-deps -e``
of its repository, plus ``loop_rate_limiters``; it runs on mink, MuJoCo, SciPy and ``rich``) and its rows
are skipped otherwise (:func:`available`). The figures in docs/bench/retarget.txt are of its commit
4f9e8b7b8b471c9d8b4cb0119f6dca886868b3dd (2025-08-09).

**Its robot.** ``GeneralMotionRetargeting(src_human, "unitree_g1")`` loads GMR's own
``assets/unitree_g1/g1_mocap_29dof.xml``. Its kinematics are those of MuJoCo Menagerie's current 29-DoF
G1 that diffkin vendors: the same 29 joints in the same qpos order after the free joint, and every body
at the same pose for the same qpos (checked by :func:`check_same_kinematics` with MuJoCo's FK, which the
benchmark runs before scoring). Only ranges differ: GMR narrows 15 of them (hip pitch and yaw to ±1.57,
the shoulders, elbows and waist yaw), always inside Menagerie's. So GMR's qpos is scored as it stands by
``retarget.metrics`` on diffkin's chain of the Menagerie G1, limits counted against Menagerie's ranges.

**Its input.** GMR's BVH path (``utils/lafan1.py`` and ``ik_configs/bvh_to_g1.json``) is written for
LAFAN1's skeleton: its joint names (``LeftUpLeg``, ``LeftArm``, ``Spine2``...) and its bone frames, in
which the config's orientation offsets are expressed. The shipped clips are the CMU skeleton (other names,
bone frames aligned with the world in the rest pose). :func:`cmu_config` therefore writes GMR's own
``bvh_to_g1.json`` for the CMU skeleton and changes nothing else: the same two match tables (frames,
position and orientation weights, zero position offsets), the same scale table and human-height
assumption; the names are mapped to the CMU joints of the same anatomy (``LeftUpLeg`` -> ``LeftHip``,
``LeftLeg`` -> ``LeftKnee``, ``LeftFootMod`` -> ``LeftAnkle`` position with ``LeftToe`` orientation as in
GMR's loader, ``LeftArm`` -> ``LeftShoulder``, ``LeftForeArm`` -> ``LeftElbow``, ``LeftHand`` ->
``LeftWrist``, ``Spine2`` -> ``Chest2``), and each orientation offset is recomputed so that the CMU rest
pose (every BVH rotation zero: arms down, each leg 20° out to the side, facing -y after z-up) maps onto
the G1 in that posture (hip roll ±20°, ankle roll ∓20° to keep the feet flat, elbows at π/2, which
straightens the G1's arms (its zero pose bends them 90°), everything else zero, facing -y):
``offset = R_human_rest^T R_robot_rest`` per matched body. GMR's BVH script's fixed human height
(1.75 m) is used as it uses it. The frames are fed to ``GeneralMotionRetargeting.retarget`` one after the
other, as ``scripts/bvh_to_robot.py`` does (without its viewer).

The walk-with-turn and pick-up clips are the same CMU skeleton in the MotionBuilder-friendly conversion
(skeleton ``"cmu_mb"``): GMR's names map onto them as LAFAN1's do (``LeftUpLeg``, ``LeftLeg``,
``LeftFoot`` with ``LeftToeBase`` orientation, ``LeftArm``, ``LeftForeArm``, ``LeftHand``, ``Spine2`` ->
``Spine1``), and their rest pose (every rotation zero) has the arms out to the sides, horizontal (a T
pose), so the G1's rest posture for the offsets raises the arms sideways (shoulder roll ±π/2) as well.
"""

from __future__ import annotations

import copy
import json
import math
import time

import numpy as np

__all__ = ["GMR_NAMES", "available", "check_same_kinematics", "cmu_config", "frames_of", "retarget_gmr"]

#: GMR's LAFAN1 body name -> the CMU joint of the same anatomy (the shipped clips' skeleton)
GMR_NAMES = {"Hips": "Hips", "Spine2": "Chest2",
             **{f"{s}{k}": f"{s}{v}" for s in ("Left", "Right") for k, v in (
                 ("UpLeg", "Hip"), ("Leg", "Knee"), ("FootMod", "Ankle"), ("Arm", "Shoulder"),
                 ("ForeArm", "Elbow"), ("Hand", "Wrist"))}}
#: per skeleton of ``retarget.Mapping.builtin``: (GMR name -> joint, foot -> toe joint for "FootMod"'s
#: orientation, the rest pose's arms: "down" or "out" (horizontal, to the sides))
SKELETON_NAMES = {
    "cmu": (GMR_NAMES, {f"{s}Ankle": f"{s}Toe" for s in ("Left", "Right")}, "down"),
    "cmu_mb": ({"Hips": "Hips", "Spine2": "Spine1",
                **{f"{s}{k}": f"{s}{v}" for s in ("Left", "Right") for k, v in (
                    ("UpLeg", "UpLeg"), ("Leg", "Leg"), ("FootMod", "Foot"), ("Arm", "Arm"),
                    ("ForeArm", "ForeArm"), ("Hand", "Hand"))}},
               {f"{s}Foot": f"{s}ToeBase" for s in ("Left", "Right")}, "out"),
}
#: GMR's BVH script's fixed human height (``utils/lafan1.py``: ``human_height = 1.75``)
HUMAN_HEIGHT = 1.75
SPLAY = math.radians(20.0)  # the CMU rest pose's leg abduction: atan(2.49329 / 6.85026) = 20.0°


def available() -> bool:
    try:
        import general_motion_retargeting  # noqa: F401
    except Exception:  # not installed (or its imports fail): the GMR rows are skipped
        return False
    return True


def _rest_pose_rotations(model, arms: str = "down") -> dict[str, np.ndarray]:
    """World rotations of GMR's G1 bodies in the CMU rest posture, facing -y (MuJoCo FK); ``arms="out"``:
    the arms raised sideways to horizontal (the MotionBuilder conversion's T pose)."""
    import mujoco

    data = mujoco.MjData(model)
    q = model.qpos0.copy()
    q[3:7] = [math.cos(-math.pi / 4), 0.0, 0.0, math.sin(-math.pi / 4)]  # yaw -90°: x forward -> -y
    for side, sign in (("left", 1.0), ("right", -1.0)):
        q[model.joint(f"{side}_hip_roll_joint").qposadr[0]] = sign * SPLAY
        q[model.joint(f"{side}_ankle_roll_joint").qposadr[0]] = -sign * SPLAY
        q[model.joint(f"{side}_elbow_joint").qposadr[0]] = math.pi / 2  # G1's zero bends it 90°: straighten
        if arms == "out":
            q[model.joint(f"{side}_shoulder_roll_joint").qposadr[0]] = sign * math.pi / 2
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    return {model.body(b).name: data.xmat[b].reshape(3, 3).copy() for b in range(model.nbody)}


def cmu_config(model, skeleton: str = "cmu") -> dict:
    """GMR's ``bvh_to_g1.json`` for the CMU skeleton (see the module doc): names mapped, orientation
    offsets recomputed at the rest pose, everything else as GMR ships it."""
    from general_motion_retargeting.params import IK_CONFIG_DICT
    from scipy.spatial.transform import Rotation

    with open(IK_CONFIG_DICT["bvh"]["unitree_g1"]) as f:
        config = json.load(f)
    robot = _rest_pose_rotations(model, SKELETON_NAMES[skeleton][2])
    human = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # every CMU joint at rest: the y-up -> z-up turn
    for table in ("ik_match_table1", "ik_match_table2"):
        for frame, entry in config[table].items():
            offset = human.T @ robot[frame]
            entry[4] = Rotation.from_matrix(offset).as_quat(scalar_first=True).tolist()
    return config


def frames_of(motion, b: int = 0, skeleton: str = "cmu") -> list[dict]:
    """One clip of a :class:`diffkin.retarget.Motion` (with orientations) as GMR's per-frame dicts
    ``{GMR name: (position (3,), orientation wxyz (4,))}``, metres, z up (what GMR's BVH loader makes)."""
    from scipy.spatial.transform import Rotation

    P = motion.positions[b].double().numpy()
    R = motion.orientations[b].double().numpy()
    T = P.shape[0]
    names, toes, _ = SKELETON_NAMES[skeleton]
    quat = {}
    for name in {*names.values(), *toes.values()}:
        quat[name] = Rotation.from_matrix(R[:, motion.index([name])[0]]).as_quat(scalar_first=True)
    out = []
    for t in range(T):
        frame = {}
        for gmr, cmu in names.items():
            j = motion.index([cmu])[0]
            rot = toes[cmu] if gmr.endswith("FootMod") else cmu  # GMR's "FootMod": the toe's orientation
            frame[gmr] = (P[t, j].copy(), quat[rot][t].copy())
        out.append(frame)
    return out


def retarget_gmr(motion, skeleton: str = "cmu") -> tuple[np.ndarray, float, np.ndarray, object]:
    """GMR on every clip of ``motion`` -> ``(q, seconds, own_error, model)``: qpos ``(B, T, 36)`` (GMR's
    model's order: free joint, wxyz, then the 29 joints), the seconds spent in
    ``GeneralMotionRetargeting.retarget`` (one retargeter per clip, built outside the timing, as GMR's
    script builds it once), the mean distance ``(B,)`` in m of GMR's position-tracked bodies (its second
    table's position weights > 0) to GMR's own scaled targets, and GMR's MuJoCo model."""
    import mujoco
    from general_motion_retargeting import GeneralMotionRetargeting

    clips = [frames_of(motion, b, skeleton) for b in range(motion.batch)]
    out, own, secs, cpu = [], [], 0.0, 0.0
    for frames in clips:
        gmr = GeneralMotionRetargeting("bvh", "unitree_g1", actual_human_height=HUMAN_HEIGHT)
        config = cmu_config(gmr.model, skeleton)
        # GMR reads its config in __init__; rebuild its tables from the CMU config the same way
        ratio = HUMAN_HEIGHT / config["human_height_assumption"]
        gmr.human_scale_table = {k: v * ratio for k, v in config["human_scale_table"].items()}
        gmr.ik_match_table1 = config["ik_match_table1"]
        gmr.ik_match_table2 = config["ik_match_table2"]
        gmr.human_body_to_task1, gmr.human_body_to_task2 = {}, {}
        gmr.pos_offsets1, gmr.rot_offsets1, gmr.pos_offsets2, gmr.rot_offsets2 = {}, {}, {}, {}
        gmr.task_errors1, gmr.task_errors2 = {}, {}
        gmr.setup_retarget_configuration()
        q = np.zeros((len(frames), gmr.model.nq))
        targets = []
        start, start_cpu = time.perf_counter(), time.process_time()
        for t, frame in enumerate(frames):
            q[t] = gmr.retarget(copy.copy(frame))
            targets.append(gmr.scaled_human_data)
        secs += time.perf_counter() - start
        cpu += time.process_time() - start_cpu
        out.append(q)
        tracked = {f: e[0] for f, e in config["ik_match_table2"].items() if e[1] > 0}
        data = mujoco.MjData(gmr.model)
        err = []
        for qt, target in zip(q, targets):
            data.qpos[:] = qt
            mujoco.mj_kinematics(gmr.model, data)
            err += [np.linalg.norm(data.body(f).xpos - target[h][0]) for f, h in tracked.items()]
        own.append(float(np.mean(err)))
    return np.stack(out), (secs, cpu), np.array(own), gmr.model


def check_same_kinematics(gmr_model, ours_model, samples: int = 20, seed: int = 0) -> float:
    """The largest difference (m, plus the Frobenius norm of the rotation difference) of any body's pose
    between GMR's G1 and ``ours_model`` for the same random qpos within ``ours_model``'s ranges (MuJoCo
    FK of both); also asserts the joint names and order agree."""
    import mujoco

    names = [gmr_model.joint(j).name for j in range(1, gmr_model.njnt)]
    ours = [ours_model.joint(j).name for j in range(1, ours_model.njnt)]
    if names != ours or gmr_model.nq != ours_model.nq:
        raise AssertionError(f"GMR's G1 joints {names} differ from ours {ours}")
    rng = np.random.default_rng(seed)
    da, db = mujoco.MjData(gmr_model), mujoco.MjData(ours_model)
    lo, hi = ours_model.jnt_range[1:].T
    worst = 0.0
    for _ in range(samples):
        q = np.zeros(gmr_model.nq)
        q[:3] = rng.normal(size=3)
        q[3:7] = rng.normal(size=4)
        q[3:7] /= np.linalg.norm(q[3:7])
        q[7:] = rng.uniform(lo, hi)
        da.qpos[:] = q
        db.qpos[:] = q
        mujoco.mj_kinematics(gmr_model, da)
        mujoco.mj_kinematics(ours_model, db)
        for b in range(1, ours_model.nbody):
            n = ours_model.body(b).name
            worst = max(worst, float(np.linalg.norm(da.body(n).xpos - db.body(n).xpos)
                                     + np.linalg.norm(da.body(n).xmat - db.body(n).xmat)))
    return worst
