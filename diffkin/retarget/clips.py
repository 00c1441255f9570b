"""The motion clips shipped with the package (``diffkin/retarget/data``; sources in its README.md)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["example_clips"]

DATA = Path(__file__).resolve().parent / "data"


def example_clips() -> dict[str, Path]:
    """``{name: path}`` of the shipped BVH clips (CMU motion-capture database, trimmed; data/README.md):
    subject 131 at 60 fps (skeleton ``"cmu"``): ``"walk"``, ``"crouch"``, ``"hop"``, ``"turn"`` (on the
    spot), ``"reach"`` (an arm raised); at 30 fps (skeleton ``"cmu_mb"``): ``"walkturn"`` (subject 69: a
    walk with a 90° left turn), ``"pickup"`` (subject 143: walk up to a tool box, bend down and grasp
    it) and ``"squat"`` (subject 22: one deep squat, down and up). Load one with
    :func:`~diffkin.retarget.load_bvh`; its mapping is ``Mapping.builtin(robot,
    retarget.skeleton_of(motion.names))``."""
    out = {}
    for p in sorted(DATA.glob("*.bvh")):
        out[p.stem.rsplit("_", 1)[-1]] = p
    return out
