"""The motion clips shipped with the package (``diffkin/retarget/data``; sources in its README.md)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["example_clips"]

DATA = Path(__file__).resolve().parent / "data"


def example_clips() -> dict[str, Path]:
    """``{name: path}`` of the shipped BVH clips (CMU motion-capture database, subject 131, trimmed):
    ``"walk"``, ``"crouch"``, ``"hop"``, ``"turn"``, ``"reach"``. Load one with
    :func:`~diffkin.retarget.load_bvh`."""
    out = {}
    for p in sorted(DATA.glob("*.bvh")):
        out[p.stem.rsplit("_", 1)[-1]] = p
    return out
