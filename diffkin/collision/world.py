"""The robot's surroundings: :class:`World`, a set of spheres, capsules, boxes, half-spaces, points and
cylinders, and the distances of the robot's geoms to all of them.

Objects are indexed in the order spheres, capsules, boxes, half-spaces, points, cylinders (a kind added
later comes last, so the columns of the earlier kinds never move), then the ``objects`` of kinds registered
in the pair table (:mod:`diffkin.collision.pairs`), in the order given; every tensor may carry leading batch
dims (one world per row of a batch), which broadcast against the batch of ``q``.
"""

from __future__ import annotations

import itertools

import torch
from torch import Tensor

from .._numerics import broadcast_shapes, normalize_floor, safe_norm
from ..errors import ConventionError, DiffkinError, ModelError, ShapeError
from ..validation import broadcast_batch, check_lower_bound, common_dtype_device, shape_str, tensors
from .boxes import Box, checked_boxes

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
        cylinders: ``(..., W_y, 7)``: the two end points of the axis (the centres of the flat faces) and the
            radius, in the style of ``capsules`` (a cylinder of length L along the unit axis u, placed at p:
            ``p ∓ (L/2) u`` and r). Exact cylinders (flat ends), not capsules; L > 0.
        objects: ``{kind: (arg, ...)}``: objects of any other kind of the pair table
            (:data:`diffkin.collision.pairs.KINDS`) that has a world layout (``Kind.trailing``): each argument
            ``(..., W_k, *trailing)``. The distances run through the pair table (torch); the C decisions
            and the C velocity step leave such a world to torch.
        dtype, device: for arguments given as numbers or arrays (tensors are taken as they are).

    ``len(world)`` is W = W_s + W_c + W_b + W_h + W_p + W_y, the last axis of ``world_distances``.
    """

    def __init__(self, spheres=None, capsules=None, boxes: Box | None = None, halfspaces=None, points=None,
                 cylinders=None, *, objects: dict | None = None, dtype: torch.dtype | None = None,
                 device=None):
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
        s, c, h, p, y = tensors(("spheres", spheres, (None, 4)), ("capsules", capsules, (None, 7)),
                                ("halfspaces", halfspaces, (None, 4)), ("points", points, (None, 3)),
                                ("cylinders", cylinders, (None, 7)), like=like)
        # one world per batch row: the objects' batch dims (all but the last two) must broadcast
        batched = [("spheres", s, 2), ("capsules", c, 2), ("halfspaces", h, 2), ("points", p, 2),
                   ("cylinders", y, 2),
                   ("boxes.center", None if boxes is None or boxes.center.ndim < 2 else boxes.center, 2)]
        broadcast_batch(*batched)
        for name, radius in (("spheres", s), ("capsules", c), ("cylinders", y)):
            if radius is not None:  # as box() rejects half extents < 0
                check_lower_bound(radius[..., -1], f"{name} radii (last column)", cls=ModelError)
        if y is not None:  # a cylinder without length has no axis: its flat faces would face anywhere
            check_lower_bound(safe_norm(y[..., 3:6] - y[..., :3]), "cylinders lengths |b - a| (columns 0-5)",
                              2 * normalize_floor(y), strict=True, cls=ModelError)
        ref = next((t for t in (s, c, h, p, y) if t is not None), None)
        if boxes is not None:
            common_dtype_device({"boxes": boxes.center, **({"spheres etc.": ref} if ref is not None else {})})
            ref = boxes.center if ref is None else ref
        self.objects = _registered_objects(objects, ref if ref is not None else like)
        if self.objects:  # their batch dims too (the object axis and the kind's own dims excluded)
            from .pairs import KINDS

            broadcast_batch(*batched, *((f"objects[{k!r}]", args[0], 1 + KINDS[k].own[0])
                                        for k, args in self.objects.items()))
        if ref is None and self.objects:
            ref = next(iter(self.objects.values()))[0]
        dt = ref.dtype if ref is not None else (dtype or torch.get_default_dtype())
        dev = ref.device if ref is not None else torch.empty(0, device=device).device
        empty = lambda k: torch.zeros(0, k, dtype=dt, device=dev)  # noqa: E731
        self.spheres = s if s is not None else empty(4)
        self.capsules = c if c is not None else empty(7)
        self.halfspaces = h if h is not None else empty(4)
        self.points = p if p is not None else empty(3)
        self.cylinders = y if y is not None else empty(7)
        if boxes is None:
            boxes = Box(empty(3), torch.zeros(0, 3, 3, dtype=dt, device=dev), empty(3))
        elif boxes.center.ndim == 1:  # one box
            boxes = Box(boxes.center[None], boxes.rotation[None], boxes.half_extents[None])
        self.boxes = boxes
        n = self.halfspaces[..., :3].norm(dim=-1)
        if bool(((n - 1.0).abs() > 1e-5).any()):
            raise ModelError(f"expected unit half-space normals, got norms {n.detach().cpu().tolist()}")
        self.dtype, self.device = dt, dev

    @property
    def counts(self) -> tuple[int, int, int, int, int, int]:
        """(W_s, W_c, W_b, W_h, W_p, W_y): the built-in kinds (:attr:`object_counts`: the others)."""
        return (self.spheres.shape[-2], self.capsules.shape[-2], self.boxes.center.shape[-2],
                self.halfspaces.shape[-2], self.points.shape[-2], self.cylinders.shape[-2])

    @property
    def object_counts(self) -> tuple[int, ...]:
        """The number of objects of each kind of :attr:`objects`, in their order."""
        from .pairs import KINDS

        return tuple(args[0].shape[-1 - KINDS[k].own[0]] for k, args in self.objects.items())

    def tensors(self) -> tuple[Tensor, ...]:
        """Every tensor of the world: spheres, capsules, the boxes' centres, rotations and half extents,
        half-spaces, points, cylinders, then the arguments of :attr:`objects` (for memo keys and
        conversions)."""
        b = self.boxes
        return (self.spheres, self.capsules, b.center, b.rotation, b.half_extents, self.halfspaces,
                self.points, self.cylinders, *(t for args in self.objects.values() for t in args))

    def _objects_map(self, fn) -> dict:
        """``objects`` with ``fn(tensor, own dims)`` applied to every argument."""
        from .pairs import KINDS

        return {k: tuple(fn(t, own) for t, own in zip(args, KINDS[k].own))
                for k, args in self.objects.items()}

    @property
    def batch_shape(self) -> torch.Size:
        """The objects' leading (per-row world) dims broadcast together; ``()`` for one world for all rows."""
        from .pairs import KINDS

        s, c, bc, bR, bh, h, p, y = self.tensors()[:8]
        extra = [t.shape[:-1 - own] for k, args in self.objects.items() for t, own in zip(args, KINDS[k].own)]
        return broadcast_shapes(*(t.shape[:-2] for t in (s, c, bc, bh, h, p, y)), bR.shape[:-3], *extra)

    def to(self, dtype: torch.dtype | None = None, device=None) -> World:
        """The same world with every tensor in ``dtype`` on ``device`` (None: unchanged)."""
        return self._map(lambda t, own: t.to(dtype=dtype or self.dtype, device=device or self.device))

    def _map(self, fn) -> World:
        """The same world with ``fn(tensor, own)`` applied to every tensor, registered objects included;
        ``own`` counts the tensor's trailing dims that are not batch dims (the object axis included)."""
        own = (2, 2, 2, 3, 2, 2, 2, 2)  # in the order of tensors(): a rotation has 3, the others 2
        s, c, bc, bR, bh, h, p, y = (fn(t, k) for t, k in zip(self.tensors()[:8], own))
        return World(spheres=s, capsules=c, boxes=Box(bc, bR, bh), halfspaces=h, points=p, cylinders=y,
                     objects=self._objects_map(lambda t, own: fn(t, own + 1)))

    def __len__(self) -> int:
        return sum(self.counts) + sum(self.object_counts)

    def __repr__(self) -> str:
        s, c, b, h, p, y = self.counts
        extra = "".join(f", {k}={n}" for k, n in zip(self.objects, self.object_counts))
        return (f"World(spheres={s}, capsules={c}, boxes={b}, halfspaces={h}, points={p}, cylinders={y}"
                f"{extra})")

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
        kinds = sorted({k for w in worlds for k in w.objects})
        if kinds:  # a registered kind has no padding object that never collides
            raise ConventionError(f"World.stack: worlds with objects of the registered kinds {kinds} are not "
                                  "stacked (no padding object for them); batch their tensors directly")
        return cls(**stack_worlds(worlds))

    def _flattened(self) -> World:
        """The same worlds with every object tensor brought to one batch dim ``(nw, W, ...)`` (nw the
        product of :attr:`batch_shape`)."""
        batch = self.batch_shape
        n = batch.numel()  # not -1: an empty kind (0 objects) leaves -1 undetermined
        return self._map(lambda t, own: t.expand(*batch, *t.shape[-own:]).reshape(n, *t.shape[-own:]))

    def _take(self, index: Tensor) -> World:
        """The worlds ``index (N,)`` (long) of a world with one batch dim: a world per row ``(N, W, ...)``."""
        return self._map(lambda t, own: t[index])

    def _round(self) -> tuple[Tensor, Tensor, Tensor]:
        """Spheres, capsules and points as capsules ``(a (..., W, 3), b (..., W, 3), r (..., W))``."""
        parts = [(self.spheres[..., :3], self.spheres[..., :3], self.spheres[..., 3]),
                 (self.capsules[..., :3], self.capsules[..., 3:6], self.capsules[..., 6]),
                 (self.points, self.points, torch.zeros_like(self.points[..., 0]))]
        batch = broadcast_shapes(*(a.shape[:-2] for a, _, _ in parts))
        a = torch.cat([x.expand(*batch, *x.shape[-2:]) for x, _, _ in parts], -2)
        b = torch.cat([x.expand(*batch, *x.shape[-2:]) for _, x, _ in parts], -2)
        r = torch.cat([x.expand(*batch, x.shape[-1]) for _, _, x in parts], -1)
        return a, b, r

    def blocks(self) -> list[tuple[str, tuple[Tensor, ...]]]:
        """The objects by kind of the pair table (:mod:`diffkin.collision.pairs`), in block order: round
        objects (spheres, capsules, points as ``capsule``: :meth:`_round`), ``box``, ``halfspace``
        (``(n (..., W_h, 3), offset (..., W_h))``), ``cylinder`` (``(a, b, r)``), then :attr:`objects`."""
        B, y = self.boxes, self.cylinders
        return [("capsule", self._round()), ("box", (B.center, B.rotation, B.half_extents)),
                ("halfspace", (self.halfspaces[..., :3], self.halfspaces[..., 3])),
                ("cylinder", (y[..., :3], y[..., 3:6], y[..., 6])), *self.objects.items()]

    def block_counts(self) -> list[tuple[str, int]]:
        """The kinds of :meth:`blocks`, in their order, with their object counts (no tensor made)."""
        s, c, b, h, p, y = self.counts
        return [("capsule", s + c + p), ("box", b), ("halfspace", h), ("cylinder", y),
                *zip(self.objects, self.object_counts)]

    def _kind_columns(self, device=None) -> tuple[Tensor, ...]:
        """The world-order columns of the objects of each of :meth:`blocks` (round: spheres, capsules, then
        points; boxes; half-spaces; cylinders; each kind of :attr:`objects`), long index tensors."""
        s, c, b, h, p, y = self.counts
        ar = lambda n, start=0: start + torch.arange(n, device=device)  # noqa: E731
        starts = list(itertools.accumulate(self.object_counts, initial=0))  # (host numbers)
        return (torch.cat((ar(s + c), ar(p, s + c + b + h))), ar(b, s + c), ar(h, s + c + b),
                ar(y, s + c + b + h + p), *(ar(n, sum(self.counts) + a) for n, a in zip(self.object_counts,
                                                                                      starts)))

    def _assemble(self, parts: list[Tensor]) -> Tensor:
        """(..., G, W) in the world's order from the blocks' distances (order of :meth:`blocks`)."""
        s, c, *_ = self.counts
        batch = broadcast_shapes(*(x.shape[:-1] for x in parts))
        rd, bd, hd, yd, *od = (x.expand(*batch, x.shape[-1]) for x in parts)
        return torch.cat((rd[..., : s + c], bd, hd, rd[..., s + c:], yd, *od), -1)

    def distances(self, a: Tensor, b: Tensor, r: Tensor, bc: Tensor, bR: Tensor, bh: Tensor,
                  threshold: float | None = None, *, cylinders: tuple[Tensor, Tensor, Tensor] | None = None
                  ) -> Tensor:
        """Signed distances of G_r capsules ``a, b (..., G_r, 3), r (..., G_r)``, G_b boxes ``bc (..., G_b,
        3), bR (..., G_b, 3, 3), bh (..., G_b, 3)`` and G_y ``cylinders`` ``(a, b (..., G_y, 3), r (...,
        G_y))`` to every object: ``(..., G_r + G_b + G_y, W)`` (in that order). With ``threshold`` the
        pairs that have a bound (:mod:`diffkin.collision.pairs`) are exact only where their bound is below
        it, the others hold that bound (>= threshold; :mod:`diffkin.collision.broad`)."""
        geoms = [("capsule", (a, b, r)), ("box", (bc, bR, bh))]
        if cylinders is not None:
            geoms.append(("cylinder", tuple(cylinders)))
        return self.distances_of(geoms, threshold)

    def distances_of(self, geoms: list[tuple[str, tuple[Tensor, ...]]], threshold: float | None = None
                     ) -> Tensor:
        """Signed distances ``(..., ΣG_k, W)`` of robot geoms given by kind, ``[(kind, args (..., G_k,
        own dims)), ...]`` (kinds of :data:`diffkin.collision.pairs.KINDS`), to every object, through the
        pair table; ``threshold`` as in :meth:`distances`."""
        from .pairs import KINDS, distance

        ref = geoms[0][1][0]
        if ref.dtype != self.dtype or ref.device != self.device:
            raise DiffkinError(f"the world is {self.dtype} on {self.device}, the robot {ref.dtype} on "
                               f"{ref.device}: build the world in the robot's dtype and device")
        count = lambda k, args: args[0].shape[-1 - KINDS[k].own[0]]  # noqa: E731  (objects / geoms)
        world = [(k, tuple(x.unsqueeze(-2 - own) for x, own in zip(args, KINDS[k].own)), count(k, args))
                 for k, args in self.blocks()]
        rows = []
        for kg, args in geoms:
            if count(kg, args) == 0 and rows:  # (static sizes: skip empty kinds)
                continue
            g = tuple(x.unsqueeze(-1 - own) for x, own in zip(args, KINDS[kg].own))
            empty = g[0].new_zeros(*g[0].shape[:-1 - KINDS[kg].own[0]], 0)
            rows.append(self._assemble([distance(kg, g, kw, w, threshold) if n else empty
                                        for kw, w, n in world]))
        batch = broadcast_shapes(*(x.shape[:-2] for x in rows))
        return torch.cat([x.expand(*batch, *x.shape[-2:]) for x in rows], -2)


def _registered_objects(objects, like) -> dict[str, tuple[Tensor, ...]]:
    """``World(objects=)`` checked: kinds of the pair table with a world layout, each argument ``(...,
    W_k, *trailing)`` by the shared tensor rule (one dtype and device with ``like``), the kind's own check."""
    from .pairs import KINDS

    if objects is None:
        return {}
    if not isinstance(objects, dict):
        raise ConventionError(f"World objects=: expected a dict {{kind: (arg, ...)}}, got "
                              f"{type(objects).__name__}")
    out: dict[str, tuple[Tensor, ...]] = {}
    for kind, args in objects.items():
        spec = KINDS.get(kind)
        if spec is None or spec.trailing is None:
            layouts = [k for k, v in KINDS.items() if v.trailing is not None]
            raise ConventionError(f"World objects=: expected a kind of the pair table with a world layout "
                                  f"({', '.join(layouts) or 'none registered'}), got {kind!r}")
        args = tuple(args) if isinstance(args, (tuple, list)) else (args,)
        if len(args) != len(spec.trailing):
            raise ShapeError(f"World objects[{kind!r}]: expected {len(spec.trailing)} arguments, got "
                             f"{len(args)}")
        names = [f"objects[{kind!r}][{i}]" for i in range(len(args))]
        ts = tensors(*((n, a, (None, *tr)) for n, a, tr in zip(names, args, spec.trailing)), like=like)
        counts = {t.shape[-1 - len(tr)] for t, tr in zip(ts, spec.trailing)}
        if len(counts) > 1:
            raise ShapeError(f"World objects[{kind!r}]: the arguments hold different object counts "
                             f"{sorted(counts)}")
        broadcast_batch(*((n, t, 1 + len(tr)) for n, t, tr in zip(names, ts, spec.trailing)))
        if spec.check is not None:
            spec.check(*ts)
        like = ts[0] if like is None else like
        out[kind] = ts
    return out


def _check_world(world) -> World:
    if not isinstance(world, World):
        raise ShapeError(f"expected a diffkin.collision.World, got {type(world).__name__}"
                         + (f" of shape {shape_str(world.shape)}" if isinstance(world, Tensor) else ""))
    return world
