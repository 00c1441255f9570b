"""The robot's surroundings: :class:`World`, a set of spheres, capsules, boxes, half-spaces and points, and
the distances of capsule-like and box geoms to all of them.

Objects are indexed in the order spheres, capsules, boxes, half-spaces, points; every tensor may carry
leading batch dims (one world per row of a batch), which broadcast against the batch of ``q``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import DiffkinError, ShapeError
from ..validation import broadcast_batch, common_dtype_device, shape_str, tensors
from .boxes import Box, box_box, box_halfspace, capsule_box, checked_boxes
from .broad import box_spheres, capsule_box_bound, capsule_spheres, exact_below, sphere_bound
from .distances import capsule_capsule, capsule_halfspace

__all__ = ["World"]


class World:
    """Obstacles as tensors (leading dims free, one world per batch row allowed).

    Args:
        spheres: ``(..., W_s, 4)``: centre x, y, z and radius.
        capsules: ``(..., W_c, 7)``: the two end points of the axis and the radius.
        boxes: a :class:`~diffkin.collision.Box` from :func:`~diffkin.collision.box` (one ``()`` or a stack
            ``(..., W_b)``).
        halfspaces: ``(..., W_h, 4)``: unit outward normal n and offset d of the solid {x : n·x ≤ d}.
        points: ``(..., W_p, 3)``.
        dtype, device: for arguments given as numbers or arrays (tensors are taken as they are).

    ``len(world)`` is W = W_s + W_c + W_b + W_h + W_p, the last axis of ``world_distances``.
    """

    def __init__(self, spheres=None, capsules=None, boxes: Box | None = None, halfspaces=None, points=None,
                 *, dtype: torch.dtype | None = None, device=None):
        if boxes is not None and not isinstance(boxes, Box):
            raise DiffkinError(f"expected boxes from diffkin.collision.box(...), got {type(boxes).__name__}")
        like = None
        if dtype is not None or device is not None:
            like = torch.empty(0, dtype=dtype or torch.get_default_dtype(), device=device)
        elif boxes is not None and isinstance(boxes.center, Tensor):
            like = boxes.center
        if boxes is not None:  # a Box built directly: the rule of box() (shapes, finite, h >= 0, rotations)
            boxes = checked_boxes(boxes, like)
            like = boxes.center if like is None else like
        s, c, h, p = tensors(("spheres", spheres, (None, 4)), ("capsules", capsules, (None, 7)),
                             ("halfspaces", halfspaces, (None, 4)), ("points", points, (None, 3)), like=like)
        # one world per batch row: the objects' batch dims (all but the last two) must broadcast
        broadcast_batch(("spheres", s, 2), ("capsules", c, 2), ("halfspaces", h, 2), ("points", p, 2),
                        ("boxes.center", None if boxes is None or boxes.center.ndim < 2 else boxes.center, 2))
        for name, radius in (("spheres", s), ("capsules", c)):
            if radius is not None and bool((radius[..., -1] < 0).any()):  # as box() rejects half extents < 0
                bad = radius[..., -1].detach()
                raise DiffkinError(f"expected {name} radii (last column) >= 0, got "
                                   f"{bad[bad < 0].cpu().tolist()}")
        ref = next((t for t in (s, c, h, p) if t is not None), None)
        if boxes is not None:
            common_dtype_device({"boxes": boxes.center, **({"spheres etc.": ref} if ref is not None else {})})
            ref = boxes.center if ref is None else ref
        dt = ref.dtype if ref is not None else (dtype or torch.get_default_dtype())
        dev = ref.device if ref is not None else torch.empty(0, device=device).device
        empty = lambda k: torch.zeros(0, k, dtype=dt, device=dev)  # noqa: E731
        self.spheres = s if s is not None else empty(4)
        self.capsules = c if c is not None else empty(7)
        self.halfspaces = h if h is not None else empty(4)
        self.points = p if p is not None else empty(3)
        if boxes is None:
            boxes = Box(empty(3), torch.zeros(0, 3, 3, dtype=dt, device=dev), empty(3))
        elif boxes.center.ndim == 1:  # one box
            boxes = Box(boxes.center[None], boxes.rotation[None], boxes.half_extents[None])
        self.boxes = boxes
        n = self.halfspaces[..., :3].norm(dim=-1)
        if bool(((n - 1.0).abs() > 1e-5).any()):
            raise DiffkinError(f"expected unit half-space normals, got norms {n.detach().cpu().tolist()}")
        self.dtype, self.device = dt, dev

    @property
    def counts(self) -> tuple[int, int, int, int, int]:
        """(W_s, W_c, W_b, W_h, W_p)."""
        return (self.spheres.shape[-2], self.capsules.shape[-2], self.boxes.center.shape[-2],
                self.halfspaces.shape[-2], self.points.shape[-2])

    def __len__(self) -> int:
        return sum(self.counts)

    def __repr__(self) -> str:
        s, c, b, h, p = self.counts
        return f"World(spheres={s}, capsules={c}, boxes={b}, halfspaces={h}, points={p})"

    @classmethod
    def stack(cls, worlds) -> World:
        """One batched world ``(B, ...)`` from B unbatched worlds of possibly different sizes (one scene per
        row of a batch of q ``(B, n)``): each kind is padded to the largest count with objects that never
        collide (:mod:`diffkin.collision.world_stack`; ``stacked_columns`` maps a world's columns)."""
        from .world_stack import stack_worlds

        if not isinstance(worlds, (list, tuple)) or not all(isinstance(w, World) for w in worlds):
            got = [type(w).__name__ for w in worlds] if isinstance(worlds, (list, tuple)) else \
                type(worlds).__name__
            raise DiffkinError(f"World.stack: expected a list of diffkin.collision.World, got {got}")
        return cls(**stack_worlds(worlds))

    def _round(self) -> tuple[Tensor, Tensor, Tensor]:
        """Spheres, capsules and points as capsules ``(a (..., W, 3), b (..., W, 3), r (..., W))``."""
        parts = [(self.spheres[..., :3], self.spheres[..., :3], self.spheres[..., 3]),
                 (self.capsules[..., :3], self.capsules[..., 3:6], self.capsules[..., 6]),
                 (self.points, self.points, torch.zeros_like(self.points[..., 0]))]
        batch = torch.broadcast_shapes(*(a.shape[:-2] for a, _, _ in parts))
        a = torch.cat([x.expand(*batch, *x.shape[-2:]) for x, _, _ in parts], -2)
        b = torch.cat([x.expand(*batch, *x.shape[-2:]) for _, x, _ in parts], -2)
        r = torch.cat([x.expand(*batch, x.shape[-1]) for _, _, x in parts], -1)
        return a, b, r

    def _kind_columns(self, device=None) -> tuple[Tensor, Tensor, Tensor]:
        """The world-order columns ``(round, boxes, half-spaces)`` of :meth:`_round`'s objects (spheres,
        capsules, then points), of the boxes and of the half-spaces (long index tensors)."""
        s, c, b, h, p = self.counts
        ar = lambda n, start=0: start + torch.arange(n, device=device)  # noqa: E731
        return torch.cat((ar(s + c), ar(p, s + c + b + h))), ar(b, s + c), ar(h, s + c + b)

    def _assemble(self, round_d: Tensor, box_d: Tensor, half_d: Tensor) -> Tensor:
        """(..., G, W) in the world's order from the round (spheres, capsules, points), box, half-space
        blocks."""
        s, c, _, _, p = self.counts
        batch = torch.broadcast_shapes(round_d.shape[:-1], box_d.shape[:-1], half_d.shape[:-1])
        e = lambda x: x.expand(*batch, x.shape[-1])  # noqa: E731
        round_d, box_d, half_d = e(round_d), e(box_d), e(half_d)
        return torch.cat((round_d[..., : s + c], box_d, half_d, round_d[..., s + c:]), -1)

    def distances(self, a: Tensor, b: Tensor, r: Tensor, bc: Tensor, bR: Tensor, bh: Tensor,
                  threshold: float | None = None) -> Tensor:
        """Signed distances of G_r capsules ``a, b (..., G_r, 3), r (..., G_r)`` and G_b boxes ``bc (..., G_b,
        3), bR (..., G_b, 3, 3), bh (..., G_b, 3)`` to every object: ``(..., G_r + G_b, W)`` (capsules
        first). With ``threshold`` the box entries (searches) are exact only where their bounding-sphere
        bound is below it, the others hold that bound (>= threshold; :mod:`diffkin.collision.broad`)."""
        if a.dtype != self.dtype or a.device != self.device:
            raise DiffkinError(f"the world is {self.dtype} on {self.device}, the robot {a.dtype} on "
                               f"{a.device}: build the world in the robot's dtype and device")
        wa, wb, wr = self._round()
        B = self.boxes
        n, d = self.halfspaces[..., :3], self.halfspaces[..., 3]
        g = lambda x: x.unsqueeze(-2)  # noqa: E731  robot geoms (..., G, 1, 3)
        w = lambda x: x.unsqueeze(-3)  # noqa: E731  world objects (..., 1, W, 3)
        wm = lambda x: x.unsqueeze(-4)  # noqa: E731  world matrices (..., 1, W, 3, 3)
        nb = B.center.shape[-2]
        empty = lambda x: x.new_zeros(*x.shape[:-1], 0)  # noqa: E731  (skips the box searches' small ops)
        wbox = (w(B.center), wm(B.rotation), w(B.half_extents))
        ga, gb, gr, gbox = g(a), g(b), r[..., None], (g(bc), bR.unsqueeze(-3), g(bh))
        rows = [self._assemble(
            _pair(capsule_capsule, (ga, gb, gr), (w(wa), w(wb), wr[..., None, :]), threshold),
            _pair(capsule_box, (ga, gb, gr), wbox, threshold) if nb else empty(a),
            capsule_halfspace(ga, gb, gr, w(n), d[..., None, :]))]
        if bc.shape[-2]:
            rows.append(self._assemble(
                _pair(capsule_box, (w(wa), w(wb), wr[..., None, :]), gbox, threshold),
                _pair(box_box, gbox, wbox, threshold) if nb else empty(bc),
                box_halfspace(*gbox, w(n), d[..., None, :])))
        batch = torch.broadcast_shapes(*(x.shape[:-2] for x in rows))
        return torch.cat([x.expand(*batch, *x.shape[-2:]) for x in rows], -2)


def _pair(fn, x: tuple, y: tuple, threshold: float | None) -> Tensor:
    """``fn(*x, *y)`` for ``fn`` one of capsule_capsule (x, y capsules ``(a, b, r)``), capsule_box (x a
    capsule, y a box ``(c, R, h)``), box_box; with ``threshold`` through the broad phase
    (:func:`~diffkin.collision.broad.exact_below`, the bound of the pair's kind)."""
    if threshold is None:
        return fn(*x, *y)
    cap, box = (1, 1, 0), (1, 2, 1)  # the own dims of (a, b, r) and (c, R, h)
    if fn is capsule_capsule:
        bound, ks = sphere_bound(*capsule_spheres(*x), *capsule_spheres(*y)), (cap, cap)
    elif fn is capsule_box:
        bound, ks = capsule_box_bound(*x, *y), (cap, box)
    else:
        bound, ks = sphere_bound(*box_spheres(x[0], x[2]), *box_spheres(y[0], y[2])), (box, box)
    return exact_below(bound, threshold, fn, *zip(x, ks[0]), *zip(y, ks[1]))


def _check_world(world) -> World:
    if not isinstance(world, World):
        raise ShapeError(f"expected a diffkin.collision.World, got {type(world).__name__}"
                         + (f" of shape {shape_str(world.shape)}" if isinstance(world, Tensor) else ""))
    return world
