"""The pair table (private): every primitive kind is one entry, every pair of kinds one entry.

A kind names its arguments' own trailing dims (for the broad phase's gathers) and its bounding sphere; a
pair of kinds gives the torch signed-distance function, the lower bound the broad phase uses for it
(:mod:`diffkin.collision.broad`) and the C entry of the decisions that serves it (``None``: the torch
function decides it). :class:`~diffkin.collision.World` and
:class:`~diffkin.collision.RobotCollision` dispatch through :func:`distance` only; a new primitive is a
new :data:`KINDS` entry plus its :data:`PAIRS` entries (``tests/test_extension_points.py`` registers one in
the test: world objects of the kind, torch distances, the C decisions leaving them to torch).

Kinds (arguments, own dims):

* ``capsule``: ``(a, b, r)`` (spheres: a = b; points: r = 0), own dims (1, 1, 0);
* ``box``: ``(c, R, h)``, (1, 2, 1);
* ``cylinder``: ``(a, b, r)`` (the flat faces' centres, the radius), (1, 1, 0);
* ``halfspace``: ``(n, offset)``, (1, 0): world only, no bound (exact and cheap);
* ``convex``: ``(V,)``, the vertices of a convex mesh (its hull), (2,) (:mod:`diffkin.collision.convex`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch import Tensor

from ..errors import ConventionError
from .boxes import box_box, box_halfspace, capsule_box
from .broad import box_spheres, capsule_box_bound, capsule_spheres, exact_below, sphere_bound
from .convex import (
    box_convex,
    capsule_convex,
    convex_convex,
    convex_halfspace,
    convex_spheres,
    cylinder_convex,
)
from .cylinders import box_cylinder, capsule_cylinder, cylinder_cylinder, cylinder_halfspace, cylinder_spheres
from .distances import capsule_capsule, capsule_halfspace

__all__ = ["Kind", "Pair", "KINDS", "PAIRS", "distance", "NATIVE_CLEAR", "NATIVE_CLEAR_SPHERES"]

#: the fused C decisions (``dk_collide_clear``, :func:`diffkin.kernels.native.capsules_clear`)
NATIVE_CLEAR = "dk_collide_clear"
#: the fused C decisions for the robot's sphere geoms (capsules whose ends coincide) only
NATIVE_CLEAR_SPHERES = "dk_collide_clear (spheres)"


@dataclass(frozen=True)
class Kind:
    """A primitive kind: its arguments' own trailing dims and its bounding sphere (None: no bound).

    ``trailing``: the shapes of one object's arguments (e.g. ``((3,), (3, 3), (3,))``), for a kind a
    :class:`~diffkin.collision.World` takes through ``objects=`` (None: the World's own arguments, or not a
    world object); ``check(*args)``: the kind's own argument rule there (radii >= 0, ...), raising a
    :class:`~diffkin.errors.DiffkinError`."""

    own: tuple[int, ...]
    spheres: Callable[..., tuple[Tensor, Tensor]] | None
    trailing: tuple[tuple[int, ...], ...] | None = None
    check: Callable[..., None] | None = None


@dataclass(frozen=True)
class Pair:
    """A pair of kinds: ``fn(*x, *y)``, a lower bound ``bound(*x, *y)`` (None: none, the pair is always
    exact) and the C entry of the decisions that serves it (None: torch; :data:`NATIVE_CLEAR_SPHERES`: C for
    the robot's sphere geoms, torch for the others)."""

    fn: Callable[..., Tensor]
    bound: Callable[..., Tensor] | None
    native: str | None


KINDS: dict[str, Kind] = {
    "capsule": Kind((1, 1, 0), capsule_spheres),
    "box": Kind((1, 2, 1), lambda c, R, h: box_spheres(c, h)),
    "cylinder": Kind((1, 1, 0), cylinder_spheres),
    "halfspace": Kind((1, 0), None),
    "convex": Kind((2,), convex_spheres),
}


def _spheres_bound(kx: str, ky: str) -> Callable[..., Tensor]:
    """The bounding-sphere lower bound of a pair of kinds (:func:`~diffkin.collision.broad.sphere_bound`)."""
    nx = len(KINDS[kx].own)

    def bound(*args: Tensor) -> Tensor:
        return sphere_bound(*KINDS[kx].spheres(*args[:nx]), *KINDS[ky].spheres(*args[nx:]))

    return bound


PAIRS: dict[tuple[str, str], Pair] = {
    ("capsule", "capsule"): Pair(capsule_capsule, _spheres_bound("capsule", "capsule"), NATIVE_CLEAR),
    ("capsule", "box"): Pair(capsule_box, capsule_box_bound, NATIVE_CLEAR),
    ("capsule", "halfspace"): Pair(capsule_halfspace, None, NATIVE_CLEAR),
    ("capsule", "cylinder"): Pair(capsule_cylinder, _spheres_bound("capsule", "cylinder"),
                                  NATIVE_CLEAR_SPHERES),
    ("box", "box"): Pair(box_box, _spheres_bound("box", "box"), None),
    ("box", "halfspace"): Pair(box_halfspace, None, None),
    ("box", "cylinder"): Pair(box_cylinder, _spheres_bound("box", "cylinder"), None),
    ("cylinder", "cylinder"): Pair(cylinder_cylinder, _spheres_bound("cylinder", "cylinder"), None),
    ("cylinder", "halfspace"): Pair(cylinder_halfspace, None, None),
    ("capsule", "convex"): Pair(capsule_convex, _spheres_bound("capsule", "convex"), None),
    ("box", "convex"): Pair(box_convex, _spheres_bound("box", "convex"), None),
    ("cylinder", "convex"): Pair(cylinder_convex, _spheres_bound("cylinder", "convex"), None),
    ("convex", "convex"): Pair(convex_convex, _spheres_bound("convex", "convex"), None),
    ("convex", "halfspace"): Pair(convex_halfspace, None, None),
}


def pair(kx: str, ky: str) -> tuple[Pair, bool]:
    """The entry of kinds (kx, ky) and whether it is stored the other way round (swap the arguments)."""
    if (kx, ky) in PAIRS:
        return PAIRS[(kx, ky)], False
    if (ky, kx) in PAIRS:
        return PAIRS[(ky, kx)], True
    raise ConventionError(f"expected two geom kinds of the pair table ({', '.join(KINDS)}; pairs "
                          f"{', '.join('-'.join(k) for k in PAIRS)}), got {kx!r} and {ky!r}")


def distance(kx: str, x: tuple, ky: str, y: tuple, threshold: float | None = None) -> Tensor:
    """The signed distances of the solids ``x`` of kind ``kx`` and ``y`` of kind ``ky`` (arguments that
    broadcast), from the pair table; with ``threshold`` through the broad phase
    (:func:`~diffkin.collision.broad.exact_below` with the pair's bound: exact wherever the distance or its
    bound is below ``threshold``, the bound, >= threshold, elsewhere)."""
    entry, swap = pair(kx, ky)
    if swap:
        (kx, x), (ky, y) = (ky, y), (kx, x)
    if threshold is None or entry.bound is None:
        return entry.fn(*x, *y)
    return exact_below(entry.bound(*x, *y), threshold, entry.fn, *zip(x, KINDS[kx].own),
                       *zip(y, KINDS[ky].own))
