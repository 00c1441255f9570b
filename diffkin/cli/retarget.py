"""``diffkin retarget``: a human clip (BVH, SMPL joint ``.npz`` or a shipped clip's name) onto a humanoid
through :func:`diffkin.retarget.clip`, written as ``.npz`` (:meth:`RetargetResult.save`) or ``.csv`` (one
row per frame: clip, frame, t, the q columns in the chain's order, the two foot contacts)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from ..errors import DiffkinError
from ..validation import check_count

__all__: list[str] = []

DESCRIPTION = (
    "Retarget a human clip onto a humanoid: a per-clip scale, a frame-by-frame warm start with ik.solve,\n"
    "then one optimisation over all frames (feet held on the ground in contact without sliding, no\n"
    "penetration, joint limits, smoothness). The clip is a BVH file, an .npz of SMPL / SMPL-X joint\n"
    "positions (key 'joints', with 'fps' or 'mocap_framerate'), or a shipped clip: walk, crouch, hop,\n"
    "turn, reach. "
    "The robot is a built-in robot by name (--robot g1), or a URDF or MJCF file, whose bodies the\n"
    "built-in mapping (--mapping) names. Prints the artefact metrics before and after the whole-clip\n"
    "optimisation.")
EXAMPLES = ("diffkin retarget walk --mapping g1 --robot g1 --output walk_g1.npz\n"
            "  diffkin retarget walk --mapping g1 --urdf g1_29dof_rev_1_0.urdf --output walk_g1.npz\n"
            "  diffkin retarget clip.bvh --mapping h1 --mjcf h1.xml --frames 0:300 --output clip_h1.csv")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("clip", help="a .bvh file, an .npz of SMPL joints, or a shipped clip name (walk, crouch, "
                                "hop)")
    g = p.add_argument_group("robot")
    g.add_argument("--mapping", default="g1", help="built-in mapping (g1, h1)")
    g.add_argument("--skeleton", default=None, choices=["cmu", "cmu_mb", "smpl"],
                   help="the clip's skeleton (default: smpl for .npz, else found from the BVH's joint names)")
    src = g.add_mutually_exclusive_group(required=True)
    src.add_argument("--robot", help="a built-in URDF / MuJoCo robot by name (g1: MuJoCo Menagerie's "
                     "29-DoF G1, h1; see `diffkin models`)")
    src.add_argument("--urdf", help="robot URDF (floating base added)")
    src.add_argument("--mjcf", help="robot MJCF (its free joint)")
    g.add_argument("--dtype", default="float64", choices=["float32", "float64"], help="compute dtype")
    o = p.add_argument_group("retargeting")
    o.add_argument("--frames", metavar="START:STOP", help="a slice of the clip's frames (default all)")
    o.add_argument("--iterations", type=int, default=10, help="whole-clip iterations (0: stage one only)")
    o.add_argument("--warm-start", dest="warm_start", default="sequential", choices=["sequential", "batched"],
                   help="stage one frame after frame, or all frames in one IK call")
    o.add_argument("--ground", type=float, default=0.0, help="ground height [m]")
    p.add_argument("--output", required=True, help="the robot clip: .npz (q, qd, root pose, contacts, fps, "
                                                   "joint names) or .csv (one row per frame)")


def _motion(spec: str, skeleton: str | None):
    from .. import retarget

    shipped = retarget.example_clips()
    if spec in shipped or Path(spec).suffix.lower() == ".bvh":
        motion = retarget.load_bvh(shipped.get(spec, spec))
        return motion, skeleton or retarget.skeleton_of(motion.names)
    path = Path(spec)
    if path.suffix.lower() == ".npz":
        return retarget.load_smpl(path), skeleton or "smpl"
    raise DiffkinError(f"{spec}: expected a .bvh file, an .npz of SMPL joints or a shipped clip name "
                       f"{sorted(shipped)}")


def _slice(text: str | None, frames: int) -> tuple[int, int]:
    if not text:
        return 0, frames
    try:
        a, b = (int(v) if v else None for v in text.split(":"))
    except ValueError:
        raise DiffkinError(f"--frames: expected START:STOP (integers), got {text!r}") from None
    start, stop, _ = slice(a, b).indices(frames)
    if stop - start < 1:
        raise DiffkinError(f"--frames {text} selects no frame of the clip's {frames}")
    return start, stop


def cmd_retarget(args) -> int:
    from .. import models, retarget
    from ..io.data import check_output_path, write_arrays

    out = check_output_path(args.output, (".npz", ".csv"))
    check_count(args.iterations, "--iterations", minimum=0)
    motion, skeleton = _motion(args.clip, args.skeleton)
    start, stop = _slice(args.frames, motion.frames)
    motion = motion.frames_slice(start, stop)
    mapping = retarget.Mapping.builtin(args.mapping, skeleton)
    dtype = getattr(torch, args.dtype)
    if args.robot:  # its mapping's frames as the end links; a URDF robot by name keeps its catalogue root
        chain = models.load(args.robot, dtype=dtype, end_link=mapping.frames)
    elif args.urdf:
        chain = models.from_urdf(args.urdf, mapping.frames, floating_base=True, dtype=dtype)
    else:
        chain = models.from_mjcf(args.mjcf, mapping.frames, dtype=dtype)
    result = retarget.clip(chain, motion, mapping, ground=args.ground, whole_clip=args.iterations > 0,
                           iterations=max(args.iterations, 1), warm_start=args.warm_start)
    rows = [("stage one", result.warm_start or result.metrics)]
    if result.warm_start is not None:
        rows.append(("whole clip", result.metrics))
    for b in range(motion.batch):
        print(f"clip {b}: {motion.frames} frames at {motion.fps:g} fps, scale {float(result.scale[b]):.3f}")
        for name, m in rows:
            print(f"  {name:>10}: limit violations {int(m.joint_limit_violations[b])}, skating "
                  f"{float(m.foot_skating[b]):.1f} mm, penetration {float(m.ground_penetration[b]):.1f} mm, "
                  f"floating {float(m.floating[b]):.1f} mm, keypoint error "
                  f"{float(m.keypoint_error[b]):.1f} mm")
    if out.suffix == ".npz":
        result.save(out)
    else:
        q = result.q.detach().cpu().double().numpy()
        B, T = q.shape[:2]
        t = np.arange(T) / motion.fps
        write_arrays(out, {"clip": np.repeat(np.arange(B), T), "frame": np.tile(np.arange(T), B),
                           "t": np.tile(t, B), "q": q.reshape(B * T, -1),
                           "contact": result.contacts.cpu().numpy().reshape(B * T, 2).astype(np.float64)})
    print(f"wrote {out}")
    return 0
