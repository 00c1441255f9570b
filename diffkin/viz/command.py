"""``diffkin view`` (and ``python -m diffkin.viz``): its options, and the command that loads the robot and
serves it."""

from __future__ import annotations

import argparse
import time

import torch

from ..errors import DiffkinError
from .scene import _import_viser
from .viewer import Viewer

__all__ = ["add_parser", "cmd_view"]


def add_parser(subparsers, parents=()) -> argparse.ArgumentParser:
    """Add the ``view`` subcommand to an ``argparse`` subparsers object (``parents``: shared options)."""
    p = subparsers.add_parser(
        "view", parents=list(parents),
        help="3D viewer in the browser: joint sliders, live IK on a draggable target, trajectory playback",
        description="Serve an interactive 3D view of a robot (viser; the 'viz' extra): link frames and "
        "segments (URDF meshes when they resolve), one slider per joint, a draggable target per end link "
        "that runs ik.solve live, and playback of a joint trajectory. Serves on loopback unless --host.",
        epilog="examples:\n  diffkin view --robot panda\n"
               "  diffkin view --urdf arm.urdf --end-link tool0 --trajectory q.npy --play\n"
               "  diffkin view --mjcf g1.xml --end-link left_foot right_foot --collision\n"
               "  diffkin view --robot ur5 --host 0.0.0.0 --port 8081   # reachable from other machines",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robot", help="built-in robot name or a robot YAML file")
    p.add_argument("--urdf", help="URDF file (with --end-link)")
    p.add_argument("--mjcf", help="MJCF (MuJoCo) file (with --end-link: bodies or sites); meshes drawn where "
                   "their files resolve")
    p.add_argument("--end-link", dest="end_link", nargs="+", metavar="LINK",
                   help="end link(s) of the URDF or MJCF (several: a tree, one target each)")
    p.add_argument("--root-link", dest="root_link", help="root link of the URDF chain (default: its root)")
    p.add_argument("--trajectory", help="joint vectors (N, n) to play back: .npy, .csv, .npz (entry q), "
                   "the .npz of `diffkin trajectory joint`, a retargeted clip's .npz (`diffkin retarget "
                   "--output`; clip --clip at its frame rate) or the .npz of `diffkin plan`")
    p.add_argument("--problem", "--clip", dest="index", type=int, default=0, metavar="I",
                   help="which problem of a `diffkin plan` .npz (played up to its end at its rate 1 / dt) or "
                        "which clip of a retargeted .npz to play (default 0)")
    p.add_argument("--fps", type=float, default=None,
                   help="playback frames per second (default: the file's times if it has them, else 30)")
    p.add_argument("--play", action="store_true", help="start playing the trajectory at once")
    p.add_argument("--host", default="127.0.0.1",
                   help="interface to serve on (default 127.0.0.1, loopback only; 0.0.0.0: every interface)")
    p.add_argument("--port", type=int, default=8080, help="TCP port (default 8080; 0: any free port)")
    p.add_argument("--no-meshes", dest="meshes", action="store_false", help="frames and segments only")
    p.add_argument("--collision", action="store_true",
                   help="draw the URDF's / MJCF's collision geometry, pairs in contact in red")
    p.add_argument("--margin", type=float, default=0.0,
                   help="with --collision: a pair is in contact below this distance (m, default 0)")
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"],
                   help="compute dtype of the robot and IK (default float64)")
    p.add_argument("--duration", type=float, default=None, metavar="S",
                   help="stop after S seconds (default: serve until Ctrl+C)")
    p.set_defaults(func=cmd_view)
    return p


def _cli_collision(chain, urdf, mjcf):
    """``--collision``: the RobotCollision of the URDF or MJCF file shown."""
    import functools

    from ..collision import RobotCollision

    if urdf:
        return RobotCollision.from_urdf(urdf, chain)
    if mjcf:
        from ..models.mjcf import compile_mjcf
        from ..models.mjcf_bodies import body_poses

        return RobotCollision.from_mjcf(compile_mjcf(mjcf)[0], chain, body_poses=functools.partial(body_poses,
                                                                                                   chain))
    raise DiffkinError("--collision needs --urdf or --mjcf (a built-in robot has no collision geometry)")


def cmd_view(args) -> int:
    """``diffkin view``: load the robot, serve it, print the URL, run until Ctrl+C (or ``--duration``)."""
    _import_viser()  # the missing extra is the first thing to report
    from .. import models
    from .._console import check_one_robot

    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    mjcf = getattr(args, "mjcf", None)
    check_one_robot(args)
    if args.urdf or mjcf:
        if not args.end_link:
            raise DiffkinError(f"--{'urdf' if args.urdf else 'mjcf'} needs --end-link NAME (the end link)")
        ends = args.end_link[0] if len(args.end_link) == 1 else args.end_link
        load = models.from_urdf if args.urdf else models.from_mjcf
        chain = load(args.urdf or mjcf, ends, root_link=args.root_link, dtype=dtype)
    elif args.robot:
        chain = models.load(args.robot, dtype=dtype)
    else:
        raise DiffkinError("give --robot NAME (see `diffkin models`), --urdf FILE or --mjcf FILE with "
                           "--end-link LINK")
    collision = _cli_collision(chain, args.urdf, mjcf) if getattr(args, "collision", False) else None
    viewer = Viewer(chain, host=args.host, port=args.port, fps=args.fps, urdf=args.urdf, meshes=args.meshes,
                    collision=collision, margin=getattr(args, "margin", 0.0))
    try:
        if args.trajectory:  # --problem / --clip: which one of a plan's problems or a retarget file's clips
            index = getattr(args, "index", 0)
            viewer.load_trajectory(args.trajectory, fps=args.fps, clip=index, problem=index)
        if args.play and args.trajectory:
            viewer.play()
        what = ("MJCF geoms, frames" if viewer.visual_geoms else "URDF meshes, frames") if viewer.has_meshes \
            else "frames"
        print(f"diffkin view: '{chain.name}' ({chain.n_joints} joints; {what} and segments) at {viewer.url}"
              + ("" if args.duration else "  (Ctrl+C to stop)"), flush=True)
        end = None if args.duration is None else time.monotonic() + args.duration
        while end is None or time.monotonic() < end:
            time.sleep(0.2 if end is None else max(0.0, min(0.2, end - time.monotonic())))
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
    return 0
