"""The robot's collision geometry: :class:`RobotCollision`, geoms on the chain's links and the pairs checked.

Every geom is a capsule (spheres: zero-length capsules; cylinders: the capsule of the same radius and axis
length, which contains the cylinder and adds a hemispherical cap at each end; meshes: a fitted enclosing
capsule set, :mod:`diffkin.collision.meshes`) or an oriented box, in its link's frame. Links behind fixed
joints have frames of their own (:mod:`diffkin.collision._poses`).

Pair rules for a URDF: links welded together by fixed joints form one rigid body; pairs within one body
and pairs of bodies joined by one moving joint are *adjacent* and not checked (as MoveIt's setup
assistant counts adjacency), and an SRDF's ``<disable_collisions link1= link2=>`` removes those link pairs.
"""

from __future__ import annotations

import functools
import math
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from .._numerics import broadcast_shapes
from ..errors import ModelError, OptionError
from ..kernels.joints import origin_transform
from ..models.urdf_xml import parse_collisions
from ..transforms import transform_points
from ..validation import check_count, check_dtype, check_given, check_number, tensors
from ._checks import check_agree, check_chain, names_str
from ._poses import LinkFrames
from ._values import share_geometry_key
from .broad import capsule_pairs_at_least, group_tables, pairs_clear
from .clear import world_clear
from .distances import capsule_capsule_pairs
from .meshes import convex_parts_of_file, fit_capsules, hull_vertices, resolve_mesh
from .pairs import NATIVE_CLEAR_SPHERES, distance, pair
from .world import World, _check_world

__all__ = ["Geom", "RobotCollision"]


@dataclass(frozen=True)
class Geom:
    """One collision geom: ``name``, its ``link``, ``kind`` as written in the file (``sphere``, ``capsule``,
    ``cylinder``, ``box``, ``mesh``) and ``shape`` as computed (``capsule`` or ``box``); ``source`` is the
    mesh file a fitted capsule came from (a mesh fitted by several capsules gives geoms ``name/0``,
    ``name/1``, ... with the same source); ``shape`` ``convex``: the convex hull of a mesh, and ``hull``
    says that the mesh is not convex itself (the hull is larger than it: conservative)."""

    name: str
    link: str
    kind: str
    shape: str
    source: str | None = None
    hull: bool = False


class RobotCollision(nn.Module):
    """Collision geoms on the links of a chain, and the batched signed distances of their pairs and to a
    :class:`~diffkin.collision.World`.

    Build it with :meth:`from_urdf` or :meth:`from_mjcf`. Attributes: ``geoms`` (list of :class:`Geom`),
    ``pairs`` (list of ``(geom_a, geom_b)`` names, the order of :meth:`self_distances`), ``chain``.
    Parameters (learnable, in the link frames, dtype and device of the chain): ``capsule_a``, ``capsule_b``
    ``(G_c, 3)``, ``capsule_radius`` ``(G_c,)``; ``box_center``, ``box_rpy``, ``box_half_extents``
    ``(G_b, 3)``; ``convex_vertices`` ``(G_v, M, 3)`` (the hulls' vertices, padded by repeating one).

    The chain is held by reference, not as a submodule: ``parameters()`` are the geometry's only (an
    optimiser over them never moves the robot), and ``to()`` / ``double()`` / ``float()`` convert the
    geometry only, never the user's chain. The chain, ``q`` and the geometry must then agree in dtype and
    device: a mismatch raises :class:`~diffkin.errors.DTypeError` / :class:`~diffkin.errors.DeviceError`
    naming both (convert the chain and the model together: ``chain.double(); rc.double()``). The geoms are
    always placed by this chain, so :func:`diffkin.ik.solve`, :func:`diffkin.ik.optimize` and
    :func:`~diffkin.sampling.random_configuration` require ``collision.chain`` to be the very chain they are
    given (the same object; :class:`~diffkin.errors.ModelError` naming both otherwise). ``rc.chain = other``
    rebinds the model to another chain of the same robot.
    """

    def __setattr__(self, name, value):
        if name == "chain":  # by reference: never a submodule (see the class docstring)
            object.__setattr__(self, "_chain_ref", value)
        else:
            super().__setattr__(name, value)

    @property
    def chain(self):
        """The chain whose links carry the geoms (held by reference)."""
        return self.__dict__["_chain_ref"]

    def __init__(self, chain, geoms: list[Geom], links: list[str], capsules: list, boxes: list,
                 pairs: list[tuple[int, int]], *, convexes=(), frames=None, dtype=None, device=None):
        super().__init__()
        self.chain = chain
        self.geoms = list(geoms)
        self._frames = LinkFrames(chain) if frames is None else frames
        dt = chain.dtype if chain is not None else dtype or torch.get_default_dtype()
        dev = chain.device if chain is not None else torch.empty(0, device=device).device
        link_index = [self._frames.index[k] for k in links]  # per geom
        cap = [g for g, geom in enumerate(self.geoms) if geom.shape == "capsule"]
        bx = [g for g, geom in enumerate(self.geoms) if geom.shape == "box"]
        cv = [g for g, geom in enumerate(self.geoms) if geom.shape == "convex"]
        where = {g: (0, i) for i, g in enumerate(cap)} | {g: (1, i) for i, g in enumerate(bx)} \
            | {g: (2, i) for i, g in enumerate(cv)}
        f = lambda rows, k, n: torch.tensor([r[k] for r in rows], dtype=dt, device=dev).reshape(-1, *n)  # noqa: E731
        self.capsule_a = nn.Parameter(f(capsules, 0, (3,)))
        self.capsule_b = nn.Parameter(f(capsules, 1, (3,)))
        self.capsule_radius = nn.Parameter(f(capsules, 2, ()).reshape(-1))
        self.box_center = nn.Parameter(f(boxes, 0, (3,)))
        self.box_rpy = nn.Parameter(f(boxes, 1, (3,)))
        self.box_half_extents = nn.Parameter(f(boxes, 2, (3,)))
        self.convex_vertices = nn.Parameter(_padded_vertices(convexes, dt, dev))
        M = self.convex_vertices.shape[1]
        ilong = lambda x: torch.tensor(x, dtype=torch.long, device=dev).reshape(-1)  # noqa: E731
        anchor = [self._frames.bodies[k] for k in link_index]
        static = getattr(self._frames, "static", {0})  # anchors placed independently of q (the base)
        #: per geom: its placement does not depend on q (a link fixed to the base): see ``skip_fixed``
        self.fixed = [a in static for a in anchor]
        self._anchor = anchor
        #: leave the geoms that ``fixed`` marks out of the world checks, and pairs of two such geoms out of
        #: the self checks, of IK and collision-free sampling (their distances cannot change with q)
        self.skip_fixed = True
        # the columns of the placement product (see _columns): capsule starts, ends, box centres, box axes
        cols = lambda per: ([per[g] for g in cap] * 2 + [per[g] for g in bx]  # noqa: E731
                            + [per[g] for g in bx for _ in range(3)]  # box g's axes: columns 3 g + k
                            + [per[g] for g in cv for _ in range(M)])  # convex g's vertices: M g + k
        col_link, col_anchor = cols(link_index), cols(anchor)
        self.register_buffer("_col_link", ilong(col_link), persistent=False)
        self.register_buffer("_col_anchor", ilong(col_anchor), persistent=False)
        self._counts = (len(cap), len(bx))
        self._nconvex = len(cv)  # (apart from _counts, which the C paths read as (capsules, boxes))
        order = cap + bx + cv  # the geoms in the world rows' order (by kind)
        self.register_buffer("_rows", ilong(_argsort(order)), persistent=False)
        self._rows_in_order = order == list(range(len(self.geoms)))  # then no gather of the world rows
        self.pairs = [(self.geoms[i].name, self.geoms[j].name) for i, j in pairs]
        self._pair_index = [(int(i), int(j)) for i, j in pairs]  # geom indices of ``pairs``
        kinds: dict[tuple[int, int], list] = {k: [] for k in _PAIR_KINDS}
        for p, (i, j) in enumerate(pairs):
            (ki, ii), (kj, jj) = sorted((where[i], where[j]))
            kinds[(ki, kj)].append((p, ii, jj))
        order = []
        for key, rows in kinds.items():
            self.register_buffer(f"_pairs_{key[0]}{key[1]}", ilong([r[1:] for r in rows]).reshape(-1, 2),
                                 persistent=False)
            order += [r[0] for r in rows]
        tables = group_tables([anchor[g] for g in cap], [(ii, jj) for _, ii, jj in kinds[(0, 0)]],
                              self.capsule_a.dtype, dev)
        for name, t in zip(_GROUP_BUFFERS, tables):  # the first stage of the decisions' broad phase
            self.register_buffer(name, t, persistent=False)
        perm = _argsort(order)
        self.register_buffer("_pair_perm", ilong(perm), persistent=False)
        self._pairs_in_order = perm == list(range(len(perm)))  # then no gather (slow on the last axis)
        moving_pairs = [p for p, (i, j) in enumerate(pairs) if not (self.fixed[i] and self.fixed[j])]
        self.register_buffer("_moving_pairs", ilong(moving_pairs), persistent=False)

    def world_only(self) -> RobotCollision:
        """The same geoms on the same chain, checked against a world only: no self pairs (``diffkin fk/ik
        --world`` without ``--self-collision``). The geometry's current values are copied (the result has
        parameters of its own); ``skip_fixed`` is kept."""
        return self._with_pairs([])

    def allow_collisions(self, pairs) -> RobotCollision:
        """The same geoms on the same chain without the self pairs of the given link pairs: an allowed-
        collision matrix's true entries (:attr:`diffkin.collision.moveit.Scene.allowed`) or any iterable of
        two link names, as an SRDF's ``<disable_collisions>``. Pairs of two names neither of which is a
        link of the robot (object–object entries) are ignored; a pair of a robot link and another name (a
        robot–object rule) is a :class:`~diffkin.errors.ModelError`, as the
        :class:`~diffkin.collision.World` has no per-object rules. The geometry is copied as in
        :meth:`world_only`; ``skip_fixed`` is kept."""
        links = set(self._frames.links)
        tree = getattr(self.chain, "tree", None)
        links |= set(getattr(tree, "links", ()))  # links of the URDF the chain leaves out (no geoms)
        rules = set()
        for p in pairs:
            if isinstance(p, (set, frozenset)) and len(p) == 1:  # a link with itself: never checked
                continue
            p = (p,) if isinstance(p, str) else tuple(p)
            if len(p) != 2 or not all(isinstance(n, str) for n in p):
                raise ModelError(f"allow_collisions: expected pairs of two link names, got {p!r}")
            known = [n in links for n in p]
            if all(known):
                rules.add(frozenset(p))
            elif any(known):
                other = p[known.index(False)]
                raise ModelError(f"allow_collisions: {p!r} pairs a robot link with {other!r}, not a link of "
                                 "this robot: robot-object rules are not supported (the World has no "
                                 "per-object rules; leave the object out of the world instead)")
        return self._with_pairs([(i, j) for i, j in self._pair_index
                                 if frozenset((self.geoms[i].link, self.geoms[j].link)) not in rules])

    def _with_pairs(self, pairs: list[tuple[int, int]]) -> RobotCollision:
        """A copy of the geometry's current values (parameters of its own) on the same chain and frames,
        checking the geom index ``pairs``; ``skip_fixed`` and ``requires_grad`` kept."""
        caps, boxes, convexes = self._geometry_values()
        out = type(self)(self.chain, self.geoms, [g.link for g in self.geoms], caps, boxes, pairs,
                         convexes=convexes, frames=self._frames, dtype=self.capsule_a.dtype,
                         device=self.capsule_a.device)
        out.skip_fixed = self.skip_fixed
        out.requires_grad_(any(p.requires_grad for p in self.parameters()))
        share_geometry_key(self, out)  # equal values: the planner's constants remembered for them serve both
        return out

    def _geometry_values(self) -> tuple[list, list, list]:
        """The geometry's current values as the constructor takes them, per kind in geom order: capsules
        ``(a, b, radius)``, boxes ``(centre, rpy, half extents)``, convex vertex arrays; one host read per
        tensor (on CUDA, a read per geom and value would be a host sync each)."""
        with torch.no_grad():
            caps = list(zip(self.capsule_a.tolist(), self.capsule_b.tolist(), self.capsule_radius.tolist()))
            boxes = list(zip(self.box_center.tolist(), self.box_rpy.tolist(), self.box_half_extents.tolist()))
            convexes = [v.cpu().numpy() for v in self.convex_vertices]
        return caps, boxes, convexes

    # ------------------------------------------------------------------------------------ geometry
    def _columns(self, q: Tensor) -> Tensor:
        """Every geom point and axis in the base frame as the columns of one product ``(..., 3, C)``.

        Column c is F_k · h_c with F_k the pose of the moving-joint frame the geom is welded to and
        h_c = O_link · (point; 1) or (axis; 0) in that frame (O: the fixed origins down to the link, no
        batch dims). Stacking the frames side by side, ``[F_0 … F_K][:3] · H`` with H holding h_c in the
        block of its frame, places all of them in one batched matrix product instead of a gather of a 4 × 4
        pose per geom.
        """
        self._check_agree(q)
        return self._columns_at(self._frames.frames(self.chain, q))

    def _columns_at(self, F: Tensor) -> Tensor:
        """:meth:`_columns` from the anchor frames' poses ``F (..., K, 4, 4)`` (a caller that has them from
        its own FK pass, with their Jacobians: :mod:`diffkin.retarget.self_collision`)."""
        Fm = F[..., :3, :].transpose(-3, -2).reshape(*F.shape[:-3], 3, 4 * F.shape[-3])  # (..., 3, K·4)
        return Fm @ self._placement(F)

    def _columns_by_component(self, q: Tensor) -> Tensor:
        """:meth:`_columns` of q ``(N, n)`` laid out component-major, ``(C, 3, N)`` contiguous (the layout of
        the C decisions): the same product taken as one matrix product ``Hᵀ · [F]`` with the N frames side by
        side, so no transpose of the (larger) result is needed."""
        self._check_agree(q)
        F = self._frames.frames(self.chain, q)  # (N, K, 4, 4)
        Fk = F[..., :3, :].permute(1, 3, 2, 0).reshape(4 * F.shape[-3], 3 * F.shape[0])  # (K·4, 3 N)
        H = self._placement(F)
        return (H.T @ Fk).reshape(H.shape[-1], 3, F.shape[0])

    def _check_agree(self, q: Tensor) -> None:
        """The geometry, the chain and q in one dtype and device (:func:`._checks.check_agree`)."""
        check_agree(self, q)

    def _placement(self, F: Tensor) -> Tensor:
        """H ``(K·4, C)`` of :meth:`_columns`, remembered while no gradient is needed and neither the
        chain's state (:meth:`_state_key`) nor the geometry (tensor versions) changes."""
        key, params = None, tuple(self.parameters())
        # H reads the chain's origins too: no memo while they need a gradient
        own = tuple(self.chain.parameters()) if isinstance(self.chain, nn.Module) else ()
        if not (torch.is_grad_enabled() and any(p.requires_grad for p in params + own)) \
                and isinstance(self._frames, LinkFrames) and self.chain is not None:
            ck = self.chain._state_key()
            key = None if ck is None else (ck, F.shape[-3], F.dtype, F.device,
                                           tuple(p._version for p in params))
        memo = self.__dict__.get("_placement_memo")  # (key, the parameters themselves: no reused storage, H)
        if key is not None and memo is not None and memo[0] == key and len(memo[1]) == len(params) \
                and all(a is b for a, b in zip(memo[1], params)):
            return memo[2]
        H = self._placement_matrix(F)
        if key is not None:
            self.__dict__["_placement_memo"] = (key, params, H)
        return H

    def _placement_matrix(self, F: Tensor) -> Tensor:
        O = self._frames.offsets(self.chain, F.dtype, F.device).index_select(0, self._col_link)  # (C, 4, 4)
        nc, nb = self._counts
        one, zero = self.capsule_a.new_ones(nc + nc + nb, 1), self.capsule_a.new_zeros(3 * nb, 1)
        Rb = origin_transform(torch.zeros_like(self.box_rpy), self.box_rpy)[..., :3, :3]  # (G_b, 3, 3)
        local = torch.cat((torch.cat((self.capsule_a, self.capsule_b, self.box_center), 0), one), 1)
        axes = torch.cat((Rb.transpose(-1, -2).reshape(-1, 3), zero), 1)  # box g's axis k: row 3 g + k
        verts = self.convex_vertices.reshape(-1, 3)
        verts = torch.cat((verts, verts.new_ones(len(verts), 1)), 1)
        h = (O @ torch.cat((local, axes, verts), 0).unsqueeze(-1)).squeeze(-1)  # (C, 4)
        K, C = F.shape[-3], h.shape[0]
        H = h.new_zeros(K, C, 4).index_put((self._col_anchor, torch.arange(C, device=h.device)), h)
        return H.transpose(1, 2).reshape(4 * K, C)

    def _as_q(self, q) -> Tensor:
        """``q`` of a public method by the chain's rule (:meth:`~diffkin.chain.KinematicChain.check_q`:
        lists, numbers and numpy arrays converted to the chain's dtype and device, the trailing size
        checked); a tensor first meets :meth:`_check_agree` (its dtype and device against the geometry's
        and the chain's). Finiteness is left to the FK pass (no extra host sync). Without a chain (an MJCF
        model placed by ``body_poses``), numbers become the geometry's dtype and device."""
        if isinstance(q, Tensor):
            check_dtype(q, "q")
            self._check_agree(q)
        chain = self.chain
        if chain is not None and hasattr(chain, "check_q"):
            return chain.check_q(q, finite=False)
        check_given(q, "q", "joint values (..., n)")
        return tensors(("q", q, None), like=self.capsule_radius, finite=False)[0]

    def placed(self, q: Tensor) -> tuple[Tensor, ...]:
        """The geoms in the base frame for joint values ``q (..., n)``: ``(a (..., G_c, 3), b (..., G_c, 3),
        radius (G_c,), box centres (..., G_b, 3), rotations (..., G_b, 3, 3), half extents (G_b, 3))``.
        ``q`` as the chain takes it (a tensor, a list or an array, converted to the chain's dtype)."""
        return self._placed_from(self._columns(self._as_q(q)))

    def _placed_from(self, P: Tensor) -> tuple[Tensor, ...]:
        nc, nb = self._counts
        a, b, c, ax, _ = P.split((nc, nc, nb, 3 * nb, P.shape[-1] - 2 * nc - 4 * nb), -1)
        R = ax.reshape(*ax.shape[:-1], nb, 3).movedim(-3, -2)  # (..., G_b, 3 (i), 3 (k))
        return (a.transpose(-1, -2), b.transpose(-1, -2), self.capsule_radius, c.transpose(-1, -2), R,
                self.box_half_extents)

    def _convex_from(self, P: Tensor) -> Tensor:
        """The convex geoms' vertices in the base frame ``(..., G_v, M, 3)`` from the placement product."""
        nc, nb = self._counts
        V = P[..., 2 * nc + 4 * nb:]
        return V.reshape(*V.shape[:-1], self._nconvex, -1).movedim(-3, -1)

    def placed_convex(self, q: Tensor) -> Tensor:
        """The convex geoms' vertices in the base frame for joint values ``q (..., n)``: ``(..., G_v, M,
        3)`` (geoms in the order of ``geoms``; shorter hulls padded by repeating a vertex)."""
        return self._convex_from(self._columns(self._as_q(q)))

    def self_distances(self, q: Tensor) -> Tensor:
        """Signed distances ``(..., P)`` of the checked pairs (order of ``pairs``; negative: penetration
        depth), in the chain's length unit, differentiable in q and in the geometry; ``q`` as in
        :meth:`placed`."""
        return self._self_from(self._columns(self._as_q(q)))

    def _self_from(self, P: Tensor, placed=None, threshold: float | None = None) -> Tensor:
        """:meth:`self_distances` from the placement product ``P`` (and its :meth:`placed` split); with
        ``threshold`` the box pairs go through the broad phase (:meth:`_distances_at_least`)."""
        (i, j), (k, m), (u, v) = self._pairs_00.T, self._pairs_01.T, self._pairs_11.T
        nc = self._counts[0]
        batch = P.shape[:-2]
        if len(k) or len(u) or self._nconvex:
            a, b, r, c, R, h = self._placed_from(P) if placed is None else placed
        sel = lambda x, idx, k: x.index_select(-1 - k, idx)  # noqa: E731
        d = []
        if len(i):  # (static sizes: the box searches cost dozens of small ops even on empty tensors)
            kern = functools.partial(capsule_pairs_at_least, threshold=threshold)
            if len(k) or len(u) or self._nconvex:
                d.append(capsule_capsule_pairs(a, b, r, i, j, kern))
            else:  # capsules only: stay in the product's component-major layout
                Pc = P[..., : 2 * nc].reshape(-1, 3, 2 * nc).permute(2, 1, 0).contiguous()  # (2 G_c, 3, N)
                A, B = Pc[:nc], Pc[nc:]
                d.append(kern(A, B - A, self.capsule_radius[:, None], i, j).T.reshape(*batch, len(i)))
        if len(k):
            d.append(distance("capsule", (sel(a, k, 1), sel(b, k, 1), r[k]),
                              "box", (sel(c, m, 1), sel(R, m, 2), h[m]), threshold))
        if len(u):
            d.append(distance("box", (sel(c, u, 1), sel(R, u, 2), h[u]), "box",
                              (sel(c, v, 1), sel(R, v, 2), h[v]), threshold))
        if self._nconvex:
            V = self._convex_from(P)
            args = {0: lambda x: (sel(a, x, 1), sel(b, x, 1), r[x]),
                    1: lambda x: (sel(c, x, 1), sel(R, x, 2), h[x]), 2: lambda x: (sel(V, x, 2),)}
            for ki, kj in _PAIR_KINDS[3:]:
                x, y = getattr(self, f"_pairs_{ki}{kj}").T
                if len(x):
                    d.append(distance(_KIND_NAMES[ki], args[ki](x), _KIND_NAMES[kj], args[kj](y), threshold))
        if not d:
            return self.capsule_radius.new_zeros(*batch, 0)
        d = torch.cat([x.expand(*batch, x.shape[-1]) for x in d], -1) if len(d) > 1 else d[0]
        return d if self._pairs_in_order else d.index_select(-1, self._pair_perm)

    def world_distances(self, q: Tensor, world: World) -> Tensor:
        """Signed distances ``(..., G, W)`` of every geom (order of ``geoms``) to every object of ``world``
        (spheres, capsules, boxes, half-spaces, points); the world's batch dims broadcast with q's."""
        world = _check_world(world)
        P = self._columns(self._as_q(q))
        return self._world_from(self._placed_from(P), world,
                                convex=self._convex_from(P) if self._nconvex else None)

    def _world_from(self, placed, world: World, threshold: float | None = None, convex=None) -> Tensor:
        a, b, r, c, R, h = placed
        if self._nconvex:
            d = world.distances_of([("capsule", (a, b, r.expand(a.shape[:-1]))),
                                    ("box", (c, R, h.expand(c.shape))), ("convex", (convex,))], threshold)
        else:
            d = world.distances(a, b, r.expand(a.shape[:-1]), c, R, h.expand(c.shape), threshold)
        return d if self._rows_in_order else d.index_select(-2, self._rows)

    def _distances_at_least(self, q: Tensor, world: World | None = None, threshold: float | None = None,
                            moving_only: bool = False) -> Tensor:
        """The self distances and, with ``world``, the world distances flattened geom-major, ``(..., P +
        G·W)``, from one placement of the geoms. With ``threshold`` (for decisions and constraint rows, not
        the public distances): an entry whose bounding-sphere lower bound already proves it >= threshold
        may hold that bound instead of the exact distance (the box searches are skipped there), so the
        result equals the exact distances wherever either is below ``threshold`` and is >= threshold
        elsewhere (:mod:`diffkin.collision.broad`); ``None``: exact everywhere. With a threshold, a large
        batch (one world for all rows) is evaluated in blocks of ``_BLOCK`` rows: the per-pair temporaries
        of a block stay in the cache (about 25 % faster at 10 000 rows on the development machine).
        ``moving_only``: without the entries that cannot change with q (:attr:`fixed`): the pairs of two
        fixed geoms and the world rows of fixed geoms (the columns :meth:`_distance_names` names)."""
        rows = q.shape[:-1].numel()
        if threshold is not None and rows > _BLOCK and (world is None or _unbatched(world)):
            flat = q.reshape(rows, q.shape[-1])
            d = torch.cat([self._distances_at_least(x, world, threshold, moving_only)
                           for x in flat.split(_BLOCK)])
            return d.reshape(*q.shape[:-1], d.shape[-1])
        P = self._columns(q)
        placed = self._placed_from(P)
        d = self._self_from(P, placed, threshold)
        keep_self, keep_world = self._kept(world, moving_only)
        if keep_self is not None:
            d = d.index_select(-1, keep_self)
        if world is None:
            return d
        convex = self._convex_from(P) if self._nconvex else None
        w = self._world_from(placed, world, threshold, convex).flatten(-2)
        w = w if keep_world is None else w.index_select(-1, keep_world)
        batch = broadcast_shapes(d.shape[:-1], w.shape[:-1])
        return torch.cat((d.expand(*batch, d.shape[-1]), w.expand(*batch, w.shape[-1])), dim=-1)

    def _kept(self, world: World | None, moving_only: bool) -> tuple[Tensor | None, Tensor | None]:
        """The columns :meth:`_distances_at_least` keeps with ``moving_only`` (None: all):
        :func:`diffkin.collision._fixed.kept_columns`."""
        from ._fixed import kept_columns

        return kept_columns(self, world, moving_only)

    def _distance_names(self, world: World | None = None, moving_only: bool = False) -> list[str]:
        """A name per column of :meth:`_distances_at_least` (:func:`._fixed.distance_names`)."""
        from ._fixed import distance_names

        return distance_names(self, world, moving_only)

    def _clear(self, q: Tensor, world: World | None = None, margin: float = 0.0,
               slack: float = 0.0, moving_only: bool = False, world_index: Tensor | None = None) -> Tensor:
        """Whether every distance d of :meth:`_distances_at_least` (with ``moving_only``: the columns it
        keeps) has d − margin >= slack, ``(...)`` bool (a decision, no gradient): the exact distances
        wherever the bounds do not prove it. Capsule geoms go through the fused C pass
        (:meth:`_clear_native`) or the component-major broad phase of
        :func:`~diffkin.collision.broad.pairs_clear` and :func:`~diffkin.collision.clear.world_clear` (the
        world entries left out masked there); robot boxes or self pairs left out through
        :meth:`_distances_at_least`.

        A batched world broadcasts against q's batch as in :meth:`_distances_at_least`; or ``world_index``
        ``(N,)`` (long) with q ``(N, n)`` and a world of one batch dim ``(nw,)`` names each row's world (the
        planner's rows of many problems, each with its own scene)."""
        nc, nb = self._counts
        if world is not None and world_index is None and not _unbatched(world):
            batch = broadcast_shapes(q.shape[:-1], world.batch_shape)
            flat = world._flattened()
            idx = torch.arange(flat.batch_shape[0], device=q.device).reshape(world.batch_shape).expand(batch)
            ok = self._clear(q.expand(*batch, q.shape[-1]).reshape(-1, q.shape[-1]), flat, margin, slack,
                             moving_only, idx.reshape(-1))
            return ok.reshape(batch)
        keep_self, keep_world = self._kept(world, moving_only)
        if nb or self._nconvex or keep_self is not None:  # robot boxes and convex meshes: torch
            return self._clear_torch(q, world, margin, slack, moving_only, world_index)
        with torch.no_grad():
            batch, rows = q.shape[:-1], q.shape[:-1].numel()
            Pc = self._columns_by_component(q.reshape(rows, q.shape[-1]))  # (C, 3, N)
            A, B, r = Pc[:nc], Pc[nc: 2 * nc], self.capsule_radius
            skip = None if world is None else self._world_skip(world, keep_world)
            ok = self._clear_native(A, B, r, world, margin, slack, skip, world_index)
            if ok is None and world_index is not None:
                return self._clear_torch(q, world, margin, slack, moving_only, world_index)
            if ok is None:
                i, j = self._pairs_00.T
                groups = tuple(getattr(self, name) for name in _GROUP_BUFFERS)
                ok = pairs_clear(A, B - A, r[:, None], i, j, margin, slack, groups) if len(i) else \
                    torch.ones(rows, dtype=torch.bool, device=q.device)
                if world is not None:
                    ok &= world_clear(A, B, r, world, margin, slack, skip)
        return ok.reshape(batch)

    def _clear_torch(self, q: Tensor, world: World | None, margin: float, slack: float, moving_only: bool,
                     world_index: Tensor | None) -> Tensor:
        """:meth:`_clear` through :meth:`_distances_at_least` (rows of ``world_index`` each with their own
        world gathered)."""
        if world_index is not None:
            world = world._take(world_index)
        d = self._distances_at_least(q, world, margin + slack, moving_only=moving_only)
        return ((d - margin) >= slack).all(-1)

    def _clear_native(self, A: Tensor, B: Tensor, r: Tensor, world: World | None, margin: float,
                      slack: float, skip: Tensor | None, world_index: Tensor | None = None) -> Tensor | None:
        """:meth:`_clear`'s decision by the fused C pass (``dk_collide_clear``: every self pair and every
        world object the pair table serves there exactly, configurations in blocks, no broad phase needed;
        per-row worlds by ``world_index``) and the torch broad phase for the rest (cylinders against proper
        segments; boxes against proper segments when margin + slack < 0); None where the pass does not
        serve (not built, CUDA; per-row worlds with entries left for torch)."""
        from ..kernels import native

        ok = torch.ones(A.shape[-1], dtype=torch.bool, device=A.device)
        objects, hs, skip_r, skip_h, extra, left, points = self._native_inputs(world, margin, slack, skip,
                                                                                world_index, A)
        done = native.capsules_clear(A, B, r, self._pairs_00, objects, hs, skip_r, skip_h, margin, slack, ok,
                                     **extra)
        if not done:
            return None
        if left:
            if world_index is not None:
                return None
            # what C left: every kind named in ``left`` (cylinders: the proper segments only)
            decided = torch.zeros(len(r), len(world), dtype=torch.bool, device=A.device)
            for k, cols in zip(("capsule", "box", "halfspace", "cylinder"), world._kind_columns(A.device)):
                if k not in left:
                    decided[:, cols] = True
                elif k == "cylinder":
                    decided[:, cols] = points[:, None]
            rest = decided if skip is None else decided | skip
            ok &= world_clear(A, B, r, world, margin, slack, rest, kinds=left)
        return ok

    def _native_inputs(self, world: World | None, margin: float, slack: float, skip: Tensor | None,
                       world_index: Tensor | None, like: Tensor) -> tuple:
        """The world arguments of :func:`~diffkin.kernels.native.capsules_clear` for :meth:`_clear_native`
        ``(objects, halfspaces, skip_round, skip_half, extra keywords, left, points)``: ``left`` names the
        world kinds the C pass leaves to torch, ``points (G_c,)`` the sphere capsules."""
        A = like
        points = (self.capsule_a.detach() == self.capsule_b.detach()).all(-1)  # (G_c,): the spheres
        extra: dict = {}
        if world is None:
            objects = (A.new_zeros(0, 3), A.new_zeros(0, 3), A.new_zeros(0))
            hs, skip_r, skip_h = A.new_zeros(0, 4), None, None
            left = []
        else:
            objects, hs = world._round(), world.halfspaces
            round_cols, box_cols, half_cols, cyl_cols, *_ = world._kind_columns(A.device)  # (+ objects=)
            cut = lambda cols: None if skip is None else skip[:, cols]  # noqa: E731
            skip_r, skip_h = cut(round_cols), cut(half_cols)
            # boxes against proper segments: exact in C only where a penetration fails (margin + slack >= 0)
            boxes_here = margin + slack >= 0 or bool(points.all())
            b = world.boxes
            if boxes_here:
                extra.update(boxes=(b.center, b.rotation, b.half_extents), skip_box=cut(box_cols))
            y = world.cylinders
            extra.update(cylinders=(y[..., :3], y[..., 3:6], y[..., 6]), skip_cylinder=cut(cyl_cols),
                         points=points, world_index=world_index)
            # the kinds C does not decide here (a kind registered without a C entry: always torch)
            left = [k for k, count in world.block_counts() if count and (
                pair("capsule", k)[0].native is None or (k == "box" and not boxes_here)
                or (pair("capsule", k)[0].native == NATIVE_CLEAR_SPHERES and not bool(points.all())))]
        return objects, hs, skip_r, skip_h, extra, left, points

    def _world_skip(self, world: World, keep_world: Tensor | None) -> Tensor | None:
        """``(G_c, W)`` bool, capsule-major rows and the world's columns: the entries :meth:`_kept` leaves
        out (None: none)."""
        if keep_world is None:
            return None
        kept = torch.zeros(len(self.geoms) * len(world), dtype=torch.bool, device=keep_world.device)
        kept[keep_world] = True
        capsule_geoms = torch.argsort(self._rows)[: self._counts[0]]  # capsule k is geom capsule_geoms[k]
        return ~kept.reshape(len(self.geoms), len(world))[capsule_geoms]

    def min_distance(self, q: Tensor, world: World | None = None) -> Tensor:
        """The smallest signed distance ``(...)`` over the checked pairs and, with ``world``, every
        geom–object pair (+inf where there are none); ``q`` as in :meth:`placed`."""
        q = self._as_q(q)
        d = self.self_distances(q)
        if world is not None:
            w = self.world_distances(q, world)
            batch = broadcast_shapes(d.shape[:-1], w.shape[:-2])
            d = torch.cat((d.expand(*batch, d.shape[-1]), w.flatten(-2).expand(*batch, -1)), -1)
        inf = torch.full_like(d[..., :1], math.inf)
        return torch.cat((d, inf), -1).amin(-1)

    def _check_chain(self, chain, who: str) -> None:
        """``chain`` must be the chain this model places its geoms with (:func:`._checks.check_chain`)."""
        check_chain(self, chain, who)

    def extra_repr(self) -> str:
        return f"geoms={len(self.geoms)}, pairs={len(self.pairs)}"

    # ------------------------------------------------------------------------------------ builders
    @classmethod
    def from_urdf(cls, source, chain, srdf=None, *, package_dirs=(), mesh_capsules: int = 4,
                  geometry: str = "capsules", mesh_tolerance: float | None = None) -> RobotCollision:
        """The ``<collision>`` geoms of the chain's links (fixed links included) from a URDF (path, text or
        :class:`~diffkin.models.urdf_xml.URDFTree`), with the URDF pair rules (module docstring) and the
        ``<disable_collisions>`` of ``srdf`` (path or text). Meshes whose files resolve (``package://``
        and relative names from the URDF's directory, or ``package_dirs``) become a fitted set of at most
        ``mesh_capsules`` capsules that together contain every triangle of the mesh
        (:mod:`diffkin.collision.meshes`; 1: one enclosing capsule) with ``geometry="capsules"``, or their
        exact convex hull with ``geometry="convex"`` (one ``convex`` geom per mesh,
        :mod:`diffkin.collision.convex`; a mesh that is not convex itself is held as its hull, flagged
        ``Geom.hull``); with ``mesh_tolerance`` (m) a non-convex mesh becomes instead convex parts
        ``name/0``, ``name/1``, ... whose union contains its triangles and reaches beyond it by at most
        that much (:func:`diffkin.collision.decompose.convex_parts`, at most 128 parts; a warning names a
        mesh left above the tolerance; seconds to minutes per mesh, once per file in a process); the
        others are skipped with one warning naming them. A ``<collision>`` whose shape
        URDF does not define (``<cone>``) is left out with a
        warning naming it; a ``<geometry>`` holding two shapes, and an SRDF naming links the URDF does not
        have (another robot's SRDF, a typo), are a :class:`~diffkin.errors.ModelError`.
        """
        if getattr(chain, "tree", None) is None:  # None, a DH chain or anything else without the URDF tree
            raise ModelError(f"RobotCollision.from_urdf: expected chain as the chain built from this URDF "
                             f"(models.from_urdf(source, end_link)), got {type(chain).__name__}")
        mesh_capsules = check_count(mesh_capsules, "mesh_capsules")
        if mesh_tolerance is not None:
            mesh_tolerance = check_number(mesh_tolerance, "mesh_tolerance", unit=" (m)")
        if geometry not in ("capsules", "convex"):
            raise OptionError(f"RobotCollision.from_urdf: expected geometry 'capsules' or 'convex', got "
                              f"{geometry!r}")
        if mesh_tolerance is not None and geometry != "convex":  # the capsule fit has no such bound
            raise OptionError("RobotCollision.from_urdf: mesh_tolerance (convex parts of non-convex meshes) "
                              f"needs geometry='convex', got geometry={geometry!r}")
        disabled = _srdf_disabled(srdf) if srdf is not None else set()  # a missing SRDF: before any work
        base_dir = None
        if isinstance(source, (str, Path)) and "<" not in str(source):
            base_dir = Path(source).resolve().parent
        unknown: list[str] = []
        specs = parse_collisions(source, unknown=unknown)
        if unknown:
            warnings.warn(f"RobotCollision.from_urdf: {len(unknown)} <collision> shape(s) URDF does not "
                          f"define (box, cylinder, sphere, mesh; capsule) left out: {', '.join(unknown)}",
                          stacklevel=2)
        frames = LinkFrames(chain)
        if not set(frames.links) & set(specs):  # another robot's file: no geom would be found
            raise ModelError(f"RobotCollision.from_urdf: the URDF has none of the chain's links (the chain: "
                             f"{names_str(frames.links)}; the URDF: {names_str(list(specs))}): is it this "
                             "robot's file?")
        geoms, links, missing = [], [], []
        data_of: dict[str, list] = {"capsule": [], "box": [], "convex": []}
        for link in frames.links:
            for s in specs.get(link, []):
                found = _geoms_of(s, base_dir, package_dirs, mesh_capsules, geometry, mesh_tolerance)
                if not found:
                    missing.append(f"{s.name} ({s.filename})")
                for geom, data in found:
                    geoms.append(geom)
                    links.append(link)
                    data_of[geom.shape].append(data)
        if missing:
            warnings.warn(f"RobotCollision.from_urdf: {len(missing)} mesh file(s) not found, those geoms are "
                          f"skipped: {', '.join(missing)}", stacklevel=2)
        _check_srdf_links(disabled, specs)
        pairs = _urdf_pairs(chain, frames, geoms, disabled)
        return cls(chain, geoms, links, data_of["capsule"], data_of["box"], pairs, convexes=data_of["convex"])

    @classmethod
    def from_mjcf(cls, source, chain=None, *, body_poses=None, dtype: torch.dtype | None = None,
                  device=None, mesh_capsules: int = 4) -> RobotCollision:
        """The geoms of an MJCF model's bodies (path, XML text or a compiled ``mujoco.MjModel``) with
        MuJoCo's pair rules: contype/conaffinity, ``<contact><exclude>``, the weld and parent–child filters
        (unless disabled in ``<option>``), plus explicit ``<contact><pair>``s. Geoms are named by their MJCF
        names, unnamed ones ``"<body>/<i>"``; spheres, capsules, boxes, cylinders and meshes are read, other
        types skipped with a warning, visual geoms (contype = conaffinity = 0, in no ``<pair>``) left out.
        A cylinder becomes the capsule of the same axis and radius (conservative: its distance is never
        above MuJoCo's and at most the cylinders' radii below it; on the Menagerie's H1, Go2, G1, UR5e and
        Shadow hand a median 1-5 mm and at most 96 mm below, docs/collision.md). A mesh becomes a fitted set
        of at most ``mesh_capsules`` capsules containing its convex hull's triangles (MuJoCo collides a mesh
        as its hull; :mod:`diffkin.collision.meshes`), named ``"<geom>/<k>"`` when there are several.

        ``body_poses(q) -> (..., nbody, 4, 4)``: the pose of every MuJoCo body (world first), differentiable
        for gradients; for an MJCF chain (:func:`diffkin.models.from_mjcf`) it defaults to
        :func:`diffkin.models.mjcf_bodies.body_poses` of that chain. ``chain`` (optional) sets dtype and
        device; without it ``dtype`` / ``device``.
        """
        from .mjcf import BodyFrames, load_model, mjcf_geoms, mjcf_pairs

        mesh_capsules = check_count(mesh_capsules, "mesh_capsules")
        m = load_model(source)
        poses = body_poses
        if poses is None and hasattr(chain, "to_qpos"):  # an MJCF chain: every body from its own q
            from ..models.mjcf_bodies import body_poses as mjcf_body_poses

            poses = functools.partial(mjcf_body_poses, chain)
        if poses is None:
            raise ModelError("RobotCollision.from_mjcf needs the body poses: pass an MJCF chain "
                             "(models.from_mjcf) or body_poses=callable(q) -> (..., nbody, 4, 4)")
        names = [m.body(b).name or f"body{b}" for b in range(m.nbody)]
        found, ids = mjcf_geoms(m, mesh_capsules)
        geoms = [Geom(name, names[body], kind, shape) for name, body, kind, shape, _ in found]
        caps = [data for *_, shape, data in found if shape == "capsule"]
        boxes = [data for *_, shape, data in found if shape == "box"]
        frames = BodyFrames(names, poses)
        frames.static = {b for b in range(m.nbody) if int(m.body_weldid[b]) == 0}  # welded to the world
        return cls(chain, geoms, [g.link for g in geoms], caps, boxes, mjcf_pairs(m, ids),
                   frames=frames, dtype=dtype, device=device)


_GROUP_BUFFERS = ("_group", "_group_pairs", "_group_table", "_group_mean", "_group_members")
_KIND_NAMES = ("capsule", "box", "convex")  # the geom kinds of a model, in column order
#: the pairs of geom kinds (indices into _KIND_NAMES) in the order of self_distances' blocks
_PAIR_KINDS = ((0, 0), (0, 1), (1, 1), (0, 2), (1, 2), (2, 2))


def _argsort(order: list[int]) -> list[int]:
    """The indices that sort ``order`` (distinct integers: the inverse of a permutation), on the host."""
    return sorted(range(len(order)), key=order.__getitem__)


def _padded_vertices(convexes, dtype, device) -> Tensor:
    """``(G_v, M, 3)``: the vertex arrays of the convex geoms, each padded to the longest by repeating its
    first vertex (the hull is unchanged)."""
    M = max((len(v) for v in convexes), default=0)
    rows = [torch.as_tensor(v, dtype=torch.float64, device="cpu").reshape(-1, 3) for v in convexes]
    rows = [torch.cat((v, v[:1].expand(M - len(v), 3))) for v in rows]
    out = torch.stack(rows) if rows else torch.zeros(0, 0, 3, dtype=torch.float64, device="cpu")
    return out.to(dtype=dtype, device=device)
_BLOCK = 2048  # rows per block of the broad phase (see RobotCollision._distances_at_least)


def _unbatched(world: World) -> bool:
    """One world for every row (no batch dims on its objects)."""
    return len(world.batch_shape) == 0


def _geoms_of(s, base_dir, package_dirs, mesh_capsules: int, geometry: str = "capsules",
              mesh_tolerance: float | None = None) -> list:
    """[(Geom, link-frame data)] of a CollisionSpec: one geom, a mesh's fitted capsules, its hull or (a
    non-convex mesh with ``mesh_tolerance``) its convex parts (``geometry``), or none for a mesh whose
    file does not resolve."""
    T = origin_transform(torch.tensor(s.xyz, dtype=torch.float64), torch.tensor(s.rpy, dtype=torch.float64))
    pt = lambda p: transform_points(T, torch.tensor(p, dtype=torch.float64)).tolist()  # noqa: E731
    if s.type == "sphere":
        c = pt((0.0, 0.0, 0.0))
        return [(Geom(s.name, s.link, "sphere", "capsule"), (c, c, s.size[0]))]
    if s.type in ("cylinder", "capsule"):
        r, length = s.size
        return [(Geom(s.name, s.link, s.type, "capsule"),
                 (pt((0.0, 0.0, -length / 2)), pt((0.0, 0.0, length / 2)), r))]
    if s.type == "box":
        return [(Geom(s.name, s.link, "box", "box"), (list(s.xyz), list(s.rpy), [x / 2 for x in s.size]))]
    path = resolve_mesh(s.filename, base_dir, package_dirs)
    if path is None:
        return []
    if geometry == "convex":
        V, convex = hull_vertices(path, s.size)
        if convex or mesh_tolerance is None:
            V = transform_points(T, torch.as_tensor(V, dtype=torch.float64)).numpy()
            return [(Geom(s.name, s.link, "mesh", "convex", s.filename, hull=not convex), V)]
        parts = convex_parts_of_file(path, s.size, tolerance=mesh_tolerance)
        if parts.excess > mesh_tolerance:
            warnings.warn(f"RobotCollision.from_urdf: the convex parts of {s.filename} reach "
                          f"{parts.excess:.3g} m beyond it (mesh_tolerance {mesh_tolerance:g} m): the part "
                          "limit was reached first", stacklevel=3)
        names = [s.name] if len(parts.parts) == 1 else [f"{s.name}/{k}" for k in range(len(parts.parts))]
        return [(Geom(n, s.link, "mesh", "convex", s.filename),
                 transform_points(T, torch.as_tensor(V, dtype=torch.float64)).numpy())
                for n, V in zip(names, parts.parts)]
    caps = fit_capsules(path, s.size, max_capsules=mesh_capsules)
    names = [s.name] if len(caps) == 1 else [f"{s.name}/{k}" for k in range(len(caps))]
    return [(Geom(n, s.link, "mesh", "capsule", s.filename), (pt(tuple(a)), pt(tuple(b)), r))
            for n, (a, b, r) in zip(names, caps)]


def _srdf_disabled(srdf) -> set[frozenset[str]]:
    """The link pairs of an SRDF's ``<disable_collisions>`` (path or XML text)."""
    if isinstance(srdf, str) and "<" in srdf:
        text = srdf
    elif isinstance(srdf, (str, Path)):
        if not Path(srdf).is_file():
            raise ModelError(f"SRDF file {str(srdf)!r} not found (srdf: a path or the XML text)")
        text = Path(srdf).read_text()
    else:
        raise ModelError(f"expected srdf as a path or the XML text, got {type(srdf).__name__}")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise ModelError(f"SRDF: malformed XML ({e})") from None
    return {frozenset((e.get("link1"), e.get("link2"))) for e in root.iter("disable_collisions")}


def _check_srdf_links(disabled: set[frozenset[str]], specs: dict) -> None:
    """Every link an SRDF's ``<disable_collisions>`` names is a link of the URDF (``specs``: every link);
    else a :class:`ModelError` naming the unknown ones (a pair of unknown links would disable nothing)."""
    named = {link for pair in disabled for link in pair}
    unknown = sorted(str(n) for n in named - set(specs))
    if unknown:
        raise ModelError(f"SRDF: <disable_collisions> names {len(unknown)} link(s) the URDF does not have: "
                         f"{names_str(unknown)} (the URDF's links: {names_str(list(specs))}); is it this "
                         "robot's SRDF?")


def _urdf_pairs(chain, frames: LinkFrames, geoms: list[Geom], disabled) -> list[tuple[int, int]]:
    """Geom index pairs (i < j) on different, non-adjacent bodies whose links the SRDF does not exclude."""
    parents = chain._topo.parents  # frame j's parent frame (-1: the base)
    parent_body = {0: None, **{j + 1: p + 1 for j, p in enumerate(parents)}}
    body = [frames.bodies[frames.index[g.link]] for g in geoms]
    out = []
    for i in range(len(geoms)):
        for j in range(i + 1, len(geoms)):
            bi, bj = body[i], body[j]
            if bi == bj or parent_body[bi] == bj or parent_body[bj] == bi:
                continue
            if frozenset((geoms[i].link, geoms[j].link)) in disabled:
                continue
            out.append((i, j))
    return out
