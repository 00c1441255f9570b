"""The world half of the decisions' broad phase (private): :func:`world_clear`, kind by kind through the pair
table (:mod:`diffkin.collision.pairs`) with the bounds of :mod:`diffkin.collision.broad`."""

from __future__ import annotations

import torch
from torch import Tensor

from .broad import _pad, _sqrt
from .pairs import KINDS, distance

__all__ = ["world_clear"]


def world_clear(A: Tensor, B: Tensor, r: Tensor, world, margin: float, slack: float,
                skip: Tensor | None = None, kinds: list[str] | None = None) -> Tensor:
    """Whether every capsule ``A, B (G, 3, N)``, ``r (G,)`` has d − margin >= slack to every object of an
    unbatched ``world`` (:class:`~diffkin.collision.World`), ``(N,)``, kind by kind through the pair table
    (:mod:`diffkin.collision.pairs`): kinds with a bounding sphere first get the bounding-sphere bound of
    every (geom, object, row) entry, the entries left their pair's own bound (capsule–box: the face normals,
    :func:`capsule_box_bound`) and only the entries left after that their exact distance; half-spaces are
    exact and cheap for all. ``skip (G, W)`` (bool, the world's object order): entries that take no part
    (geoms fixed to the base, entries the C pass decided); ``kinds``: the kinds to decide (None: all; the
    others the C pass decided)."""
    thr = margin + slack
    D = B - A
    M = torch.addcmul(A, D, D.new_tensor(0.5))  # the bounding spheres (G, 3, N), (G, N)
    rho = 0.5 * _sqrt((D * D).sum(1)) + r[:, None]
    ok = torch.ones(A.shape[-1], dtype=torch.bool, device=A.device)

    def refute(d: Tensor, n: Tensor) -> None:  # rows n whose entry d fails the test
        ok.index_fill_(0, n[(d - margin) < slack], False)

    def near(c: Tensor, rc: Tensor, cols: Tensor):  # the (geom, object, row) entries the sphere bound
        d2 = sum((M[:, None, k] - c[None, :, k, None]) ** 2 for k in range(3))  # leaves, gathered; (G, W, N)
        bound = _sqrt(d2) - rho.unsqueeze(1) - rc[None, :, None]
        hit = bound < thr + _pad(bound, thr)
        if skip is not None:
            hit &= ~skip[:, cols, None]
        g, w, n = hit.nonzero(as_tuple=True)
        return g, w, n, A[g, :, n], B[g, :, n]

    for (kind, args), cols in zip(world.blocks(), world._kind_columns(A.device)):
        if not args[0].shape[0] or (kinds is not None and kind not in kinds):
            continue
        if KINDS[kind].spheres is None:  # half-spaces: exact for every entry
            a, b = (X.transpose(1, 2).unsqueeze(1) for X in (A, B))  # (G, 1, N, 3)
            y = tuple(x[None, :, None] for x in args)
            d = distance("capsule", (a, b, r[:, None, None]), kind, y)
            fine = (d - margin) >= slack
            if skip is not None:
                fine |= skip[:, cols, None]
            ok &= fine.flatten(0, 1).all(0)
            continue
        g, w, n, a, b = near(*KINDS[kind].spheres(*args), cols)
        if n.numel():
            refute(distance("capsule", (a, b, r[g]), kind, tuple(x[w] for x in args), thr), n)
    return ok
