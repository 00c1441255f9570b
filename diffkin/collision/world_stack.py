"""Scenes of different sizes as one batched :class:`~diffkin.collision.World` (:meth:`World.stack`).

Every kind of object is padded to the largest count among the worlds with objects that cannot be touched,
placed :data:`PAD_DISTANCE` (in the worlds' length unit) from the origin: spheres and capsules of zero radius
and length, cylinders of zero radius and unit length (one without a length has no axis), unit boxes, points,
and half-spaces whose solid is {z ≤ −PAD_DISTANCE}. Their distances are about PAD_DISTANCE, far above any
margin, so they never collide. Within each kind a world's own objects keep their order and come first, its
padding after them; :func:`stacked_columns` gives where a world's columns of ``world_distances`` land in the
stacked world's.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..errors import DiffkinError
from .boxes import Box

__all__ = ["PAD_DISTANCE", "stack_worlds", "stacked_columns"]

#: how far padding objects lie from the origin (in the worlds' length unit)
PAD_DISTANCE = 1.0e6

#: per kind: the World attribute and the padding row (columns as the World stores them)
_KINDS = {
    "spheres": lambda t: _row(t, [PAD_DISTANCE, 0.0, 0.0, 0.0]),
    "capsules": lambda t: _row(t, [PAD_DISTANCE, 0.0, 0.0, PAD_DISTANCE, 0.0, 0.0, 0.0]),
    "halfspaces": lambda t: _row(t, [0.0, 0.0, 1.0, -PAD_DISTANCE]),
    "points": lambda t: _row(t, [PAD_DISTANCE, 0.0, 0.0]),
    # a cylinder needs a length (World refuses one without an axis): a unit one, radius 0
    "cylinders": lambda t: _row(t, [PAD_DISTANCE, 0.0, 0.0, PAD_DISTANCE, 0.0, 1.0, 0.0]),
}


def _row(t: Tensor, values: list[float]) -> Tensor:
    return torch.tensor(values, dtype=t.dtype, device=t.device)


def _kinds(world) -> list[str]:
    """The tensor kinds this World has (``cylinders`` only where the World takes them)."""
    return [k for k in _KINDS if isinstance(getattr(world, k, None), Tensor)]


def stack_worlds(worlds: Sequence) -> dict:
    """The keyword arguments of the batched World of ``worlds`` (module docstring): each kind ``(B, W_max,
    ·)``, the boxes a :class:`~diffkin.collision.Box` of ``(B, W_max_b, ·)``. The worlds must be unbatched
    and of one dtype and device."""
    worlds = list(worlds)
    if not worlds or not all(hasattr(w, "boxes") and hasattr(w, "counts") for w in worlds):
        raise DiffkinError("World.stack: expected a non-empty sequence of diffkin.collision.World, got "
                           f"{[type(w).__name__ for w in worlds] if worlds else 'nothing'}")
    ref = worlds[0]
    for i, w in enumerate(worlds):
        if w.dtype != ref.dtype or w.device != ref.device:
            raise DiffkinError(f"World.stack: world {i} is {w.dtype} on {w.device}, world 0 {ref.dtype} on "
                               f"{ref.device}: build them in one dtype and device")
        batched = [k for k in _kinds(w) if getattr(w, k).ndim > 2] + (["boxes"] if w.boxes.center.ndim > 2
                                                                        else [])
        if batched:
            raise DiffkinError(f"World.stack: world {i} is already batched ({', '.join(batched)} have "
                               "leading dims): stack unbatched worlds")
    out = {}
    for kind in _kinds(ref):
        parts = [getattr(w, kind) for w in worlds]
        out[kind] = _pad(parts, _KINDS[kind](parts[0]))
    centers = [w.boxes.center for w in worlds]
    far = _row(centers[0], [PAD_DISTANCE, 0.0, 0.0])
    eye = torch.eye(3, dtype=ref.dtype, device=ref.device)
    out["boxes"] = Box(_pad(centers, far), _pad([w.boxes.rotation for w in worlds], eye),
                       _pad([w.boxes.half_extents for w in worlds], torch.ones_like(far)))
    return out


def _pad(parts: list[Tensor], row: Tensor) -> Tensor:
    """``(B, max W, ...)``: each part ``(W_i, ...)`` followed by copies of ``row``."""
    n = max(p.shape[0] for p in parts)
    return torch.stack([torch.cat((p, row.expand(n - p.shape[0], *row.shape)), 0) for p in parts])


def stacked_columns(worlds: Sequence, index: int) -> Tensor:
    """The columns of ``World.stack(worlds)``'s last axis of ``world_distances`` that hold world ``index``'s
    own objects, in that world's order: ``(len(worlds[index]),)`` long."""
    counts = torch.tensor([list(w.counts) for w in worlds])
    width = counts.amax(0)
    start = torch.cat((width.new_zeros(1), width.cumsum(0)[:-1]))
    own = counts[index]
    return torch.cat([start[k] + torch.arange(int(own[k])) for k in range(len(own))])
