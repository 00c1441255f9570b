"""Retargeting the shipped human clips onto the 29-DoF G1: speed and the artefact metrics beside GMR and mink.

The clips are the five shipped CMU clips (walk, crouch, hop, turn, reach; 60 fps), the robot the 29-DoF G1
(``tests/data/urdf/g1_29dof_rev_1_0.urdf``, the kinematics of MuJoCo Menagerie's current ``unitree_g1``)
with ``retarget.Mapping.builtin("g1")``. Rows:

* ``diffkin``: ``retarget.clip`` on the five clips batched (B = 5, the first 74 frames of each), stage one
  (``warm_start="sequential"``: ``ik.solve`` frame after frame, or ``"batched"``: all frames in one call)
  then the whole-clip optimisation (:func:`diffkin.retarget.optimize_clip`, with the URDF's joint velocity
  limits as hard constraints: ``velocity_limit=``); frames per second over the 370 frames (batched: the
  median of three runs, after a warm-up call), the whole-clip stage's share of the time; the batched run
  with the C kernels on 1 and on 2 threads (``threads=``: the frames shared out over them, torch's own
  count unchanged; still capped by the cores free at the time); ``diffkin one clip``: the walk alone
  (B = 1), end to end through ``retarget.clip``.
* ``mink``: frame by frame with mink (GMR's scheme: a ``FrameTask`` per mapped frame with the same scaled
  human targets, position cost 1 and orientation cost 0, a small ``PostureTask``,
  ``ConfigurationLimit``, ``solve_ik(..., "daqp")`` and ``integrate_inplace``, iterated on each frame
  until the keypoint error falls by less than 1 mm or 10 iterations, warm started from the previous
  frame; the first frame from diffkin's initial posture). The MuJoCo model is the same URDF compiled by
  MuJoCo (meshes dropped, a free joint added to the pelvis).

* ``GMR``: GMR itself (github.com/YanjieZe/GMR, not on the package index: installed from its repository,
  see :mod:`benchmarks.peers_gmr`; its rows are skipped when it is not importable) on the same clips and
  frames, its G1 (``g1_mocap_29dof.xml``, the Menagerie G1's kinematics with narrower ranges: checked
  with MuJoCo's FK before scoring), its two-stage mink scheme and weights, its ``bvh_to_g1.json`` written
  for the CMU skeleton (names mapped, orientation offsets recomputed at the rest pose); one clip after
  the other, frame by frame. ``GMR own mm``: GMR's bodies against its own scaled targets.

* ``diffkin + self-collision``: the batched run again on the MJCF chain of the same G1 with
  ``collision=retarget.g1_collision(chain)`` (Menagerie's MJX colliders and the 26 self pairs of its scene;
  20 whole-clip iterations, ``retarget.clip``'s default with a collision model). Every row also counts
  its frames where one of those pairs penetrates (``self-colliding frames``).
* The walk with a turn, the pick-up and the squat (``NEW``: 30 fps, the MotionBuilder-named CMU skeleton,
  mapping ``Mapping.builtin("g1", "cmu_mb")``), each alone and whole: ``diffkin`` (batched warm start,
  velocity limits), ``diffkin + self-collision`` (the same on the MJCF chain of the G1 with
  ``collision=retarget.g1_collision(chain)``) and ``GMR`` (its scheme, the names and rest pose of that
  skeleton: :mod:`benchmarks.peers_gmr`).

Every output is scored by ``retarget.metrics`` on the same chain with the same contacts (from the human
clip) and keypoints (diffkin's scaled human joints). The machine is shared: times are contended; compare
the ratios of rows measured in the same run. ``frames/CPU-s`` (diffkin and GMR rows) divides by the
process's CPU time (``time.process_time``) instead of the wall clock: other processes' load inflates it
less (not at all when they leave this one a core).
"""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import cli

ROOT = Path(__file__).resolve().parents[1]
G1_URDF = ROOT / "tests" / "data" / "urdf" / "g1_29dof_rev_1_0.urdf"
G1_MJCF = ROOT / "diffkin" / "models" / "robots" / "mjcf" / "unitree_g1_29dof" / "g1.xml"
CLIPS = ("walk", "crouch", "hop", "turn", "reach")
NEW = ("walkturn", "pickup", "squat")  # a walk with a 90° turn, a reach to an object, a deep squat (30 fps,
# skeleton "cmu_mb")


def mujoco_g1():
    """The G1 URDF compiled by MuJoCo: meshes dropped, static bodies kept, a free joint on the pelvis."""
    import mujoco

    text = G1_URDF.read_text()
    text = re.sub(r"<visual>.*?</visual>", "", text, flags=re.S)
    mesh = r"<collision>(?:(?!</collision>).)*<mesh[^>]*/>(?:(?!</collision>).)*</collision>"
    text = re.sub(mesh, "", text, flags=re.S)
    text = re.sub(r"(<robot [^>]*>)", r'\1<mujoco><compiler fusestatic="false"/></mujoco>', text, count=1)
    spec = mujoco.MjSpec.from_string(text)
    spec.worldbody.first_body().add_freejoint()
    return spec.compile()


def g1_velocity_limits() -> dict[str, float]:
    """The G1 URDF's joint velocity limits (rad/s, ``<limit velocity=...>``: its motors' 20-37 rad/s)."""
    import xml.etree.ElementTree as ET

    root = ET.parse(G1_URDF).getroot()
    return {j.get("name"): float(j.find("limit").get("velocity")) for j in root.iter("joint")
            if j.get("type") in ("revolute", "prismatic") and j.find("limit") is not None}


_COLLISION = []


def _self_colliding_frames(q) -> int:
    """Frames of ``q (T, 36)`` (MuJoCo qpos order) where a self pair of Menagerie's MJX G1 scene
    (``retarget.g1_collision``) penetrates."""
    from diffkin import models, retarget

    if not _COLLISION:
        mp = retarget.Mapping.builtin("g1")
        mj = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=torch.float64).requires_grad_(False)
        _COLLISION.append(retarget.g1_collision(mj))
    with torch.no_grad():
        d = _COLLISION[0].self_distances(q.to(torch.float64))
    return int((d.min(-1).values < 0).sum())


def _metrics_row(m, b: int, q=None) -> dict:
    row = {"limit violations": int(m.joint_limit_violations[b]),
           "worst excess rad": float(m.joint_limit_excess[b]), "skating mm": float(m.foot_skating[b]),
           "penetration mm": float(m.ground_penetration[b]), "floating mm": float(m.floating[b]),
           "keypoint mm": float(m.keypoint_error[b]), "max |qd| rad/s": float(m.max_joint_velocity[b])}
    if q is not None:
        row["self-colliding frames"] = _self_colliding_frames(q[b])
    return row


def _mink(chain, model, result, q_init, max_iter: int = 10):
    """Frame-by-frame mink IK on the scaled targets of ``result``; returns q (B, T, nq) in the chain's
    order and the seconds taken."""
    import mink

    names = list(chain.joint_names)
    qadr = [0, 1, 2, 3, 4, 5, 6] + [int(model.joint(n).qposadr[0]) for n in names[1:]]
    X = result.keypoints.numpy()
    B, T, K = X.shape[:3]
    frames = result.keypoint_frames
    cfg = mink.Configuration(model)
    tasks = [mink.FrameTask(f, "body", position_cost=1.0, orientation_cost=0.0, lm_damping=1.0)
             for f in frames]
    posture = mink.PostureTask(model, cost=1e-2)
    limits = [mink.ConfigurationLimit(model)]
    out = np.zeros((B, T, chain.nq))
    dt = 1.0 / result.fps
    start = time.perf_counter()
    for b in range(B):
        q = model.qpos0.copy()
        q[qadr] = q_init[b].numpy()
        cfg.update(q)
        posture.set_target(q)
        for t in range(T):
            for task, x in zip(tasks, X[b, t]):
                task.set_target(mink.SE3.from_translation(x))
            err = np.mean([np.linalg.norm(cfg.get_transform_frame_to_world(f, "body").translation() - x)
                           for f, x in zip(frames, X[b, t])])
            for _ in range(max_iter):
                v = mink.solve_ik(cfg, [*tasks, posture], dt, "daqp", damping=1e-3, limits=limits)
                cfg.integrate_inplace(v, dt)
                new = np.mean([np.linalg.norm(cfg.get_transform_frame_to_world(f, "body").translation() - x)
                               for f, x in zip(frames, X[b, t])])
                done = err - new < 1e-3
                err = new
                if done:
                    break
            out[b, t] = cfg.q[qadr]
    return torch.from_numpy(out), time.perf_counter() - start


def _one_clip(g1, mp, motion, name: str, vmax: dict) -> list[dict]:
    """The speed of one clip alone (B = 1, batched warm start then the whole-clip optimisation); the
    median of three runs."""
    from diffkin import retarget

    times = []
    for _ in range(3):
        t0, c0 = time.perf_counter(), time.process_time()
        r = retarget.clip(g1, motion, mp, warm_start="batched", velocity_limit=vmax)
        times.append((time.perf_counter() - t0, time.process_time() - c0))
    t, cpu = sorted(times)[1]
    return [{"method": "diffkin one clip (batched warm start)", "clip": name, "frames/s": motion.frames / t,
             "frames/CPU-s": motion.frames / cpu,
             **_metrics_row(r.metrics, 0, r.q)}]


def run(args) -> list[dict]:
    from diffkin import models, retarget
    from diffkin.retarget.clip import _initial

    frames = 40 if args.quick else 74  # the shortest shipped clip (the reach): one batch, equal lengths
    mp = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(G1_URDF, mp.frames, floating_base=True, dtype=torch.float64).requires_grad_(False)
    clips = [retarget.load_bvh(retarget.example_clips()[n]).frames_slice(0, frames) for n in CLIPS]
    motion = retarget.Motion(torch.cat([c.positions for c in clips]), clips[0].names, clips[0].fps,
                             torch.cat([c.orientations for c in clips]))
    n = motion.batch * motion.frames
    vmax = {j: v for j, v in g1_velocity_limits().items() if j in g1.joint_names}
    rows = []
    base = None
    retarget.clip(g1, clips[0].frames_slice(0, 4), mp, velocity_limit=vmax)  # warm-up: builds the C library
    for warm, threads in (("sequential", 1), ("batched", 1), ("batched", 2)):
        runs = []
        for _ in range(1 if warm == "sequential" else 3):  # batched: the median of three runs
            t0, c0 = time.perf_counter(), time.process_time()
            r = retarget.clip(g1, motion, mp, whole_clip=False, warm_start=warm, threads=threads)
            t1 = time.perf_counter()
            opt = retarget.optimize_clip(g1, r.q, r.keypoints, r.contacts, feet=mp.feet,
                                         keypoint_frames=r.keypoint_frames, fps=motion.fps,
                                         velocity_limit=vmax, threads=threads)
            runs.append((time.perf_counter() - t0, t0, t1, time.perf_counter(), time.process_time() - c0))
        _, t0, t1, t2, cpu = sorted(runs)[len(runs) // 2]
        m = retarget.metrics(g1, opt.q, r.contacts, motion.fps, feet=mp.feet, keypoints=r.keypoints,
                             keypoint_frames=r.keypoint_frames)
        base = base or r
        for b, name in enumerate(CLIPS):
            if warm == "sequential":
                rows.append({"method": "diffkin stage one (sequential)", "clip": name, "frames/s": None,
                             **_metrics_row(r.metrics, b, r.q)})
            rows.append({"method": f"diffkin whole clip ({warm} warm start, {threads} C thread"
                                   f"{'s' if threads > 1 else ''})", "clip": name,
                         "frames/s": n / (t2 - t0), "frames/CPU-s": n / cpu,
                         "stage-two share": (t2 - t1) / (t2 - t0),
                         **_metrics_row(m, b, opt.q)})
    rows += _one_clip(g1, mp, clips[0], CLIPS[0], vmax)
    model = mujoco_g1()
    kp = base.keypoint_frames
    root = [f for f in kp if f not in mp.feet][0]
    q_init = _initial(g1, base.keypoints[:, :1], kp, root, mp.feet, 1)[:, 0]
    q_mink, secs = _mink(g1, model, base, q_init)
    q_mink[..., 3:7] /= q_mink[..., 3:7].norm(dim=-1, keepdim=True)
    mm = retarget.metrics(g1, q_mink, base.contacts, motion.fps, feet=mp.feet, keypoints=base.keypoints,
                          keypoint_frames=kp)
    for b, name in enumerate(CLIPS):
        rows.append({"method": "mink frame by frame (GMR's scheme)", "clip": name, "frames/s": n / secs,
                     **_metrics_row(mm, b, q_mink)})
    rows += _gmr_rows(g1, motion, base, mp)
    rows += _with_collision(g1, motion, mp, vmax, CLIPS)
    for name in NEW:
        rows += _new_clip(g1, name, vmax)
    return rows


def _new_clip(g1, name: str, vmax: dict) -> list[dict]:
    """One of ``NEW`` whole, alone: diffkin, diffkin with self-collision (MJCF chain), GMR."""
    from diffkin import retarget

    motion = retarget.load_bvh(retarget.example_clips()[name])
    skeleton = retarget.skeleton_of(motion.names)
    mp = retarget.Mapping.builtin("g1", skeleton)
    rows = []
    t0 = time.perf_counter()
    r = retarget.clip(g1, motion, mp, warm_start="batched", velocity_limit=vmax)
    rows.append({"method": "diffkin whole clip (batched warm start)", "clip": name,
                 "frames/s": motion.frames / (time.perf_counter() - t0), **_metrics_row(r.metrics, 0, r.q)})
    rows += _with_collision(g1, motion, mp, vmax, (name,))
    return rows + _gmr_rows(g1, motion, r, mp, (name,), skeleton)


def _with_collision(g1, motion, mp, vmax: dict, names) -> list[dict]:
    """diffkin with ``collision=retarget.g1_collision`` on the MJCF chain of the same G1 (batched warm
    start), scored on ``g1`` like every other row (the same kinematics and qpos order)."""
    from diffkin import models, retarget

    mj = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=torch.float64).requires_grad_(False)
    t0 = time.perf_counter()
    rc = retarget.clip(mj, motion, mp, warm_start="batched", velocity_limit=vmax,
                       collision=retarget.g1_collision(mj))
    secs = time.perf_counter() - t0
    m = retarget.metrics(g1, rc.q, rc.contacts, motion.fps, feet=mp.feet, keypoints=rc.keypoints,
                         keypoint_frames=rc.keypoint_frames)
    return [{"method": "diffkin + self-collision (MJCF G1)", "clip": name,
             "frames/s": motion.batch * motion.frames / secs, **_metrics_row(m, b, rc.q)}
            for b, name in enumerate(names)]


def _gmr_rows(chain, motion, base, mp, clip_names=CLIPS, skeleton: str = "cmu") -> list[dict]:
    """GMR itself on the same clips (``benchmarks.peers_gmr``), scored like the other rows; [] when GMR is
    not installed."""
    from benchmarks import peers_gmr
    from diffkin import retarget
    from diffkin.models.mjcf import compile_mjcf

    if not peers_gmr.available():
        print("GMR (general_motion_retargeting) is not installed: its rows are skipped")
        return []
    q, (secs, cpu), own, model = peers_gmr.retarget_gmr(motion, skeleton)
    worst = peers_gmr.check_same_kinematics(model, compile_mjcf(G1_MJCF)[0])
    if worst > 1e-9:
        raise AssertionError(f"GMR's G1 is not the Menagerie G1's kinematics (bodies {worst:.2e} apart)")
    names = list(chain.joint_names)
    qadr = [0, 1, 2, 3, 4, 5, 6] + [int(model.joint(n).qposadr[0]) for n in names[1:]]
    q = torch.from_numpy(q[..., qadr])
    m = retarget.metrics(chain, q, base.contacts, motion.fps, feet=mp.feet, keypoints=base.keypoints,
                         keypoint_frames=base.keypoint_frames)
    n = motion.batch * motion.frames
    return [{"method": "GMR (its G1, its scheme and weights)", "clip": name, "frames/s": n / secs,
             "frames/CPU-s": n / cpu,
             **_metrics_row(m, b, q), "GMR own mm": 1000 * float(own[b])}
            for b, name in enumerate(clip_names)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    title = ("retargeting the shipped clips onto the G1 (contended 2-core CPU; 5 clips x 74 frames, then the "
             "walk with a turn, the pick-up and the squat whole)")
    return cli(p, run, title, argv)


if __name__ == "__main__":
    raise SystemExit(main())
