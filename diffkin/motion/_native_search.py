"""The search stage of :func:`diffkin.motion.plan` in C: RRT-Connect and shortcutting per problem
(``dk_plan_search`` of ``diffkin/kernels/_native_plan.c``), problems spread over threads.

Same algorithm and success semantics as :mod:`diffkin.motion._search` (the torch path, which serves CUDA
tensors, builds without a C compiler and models the C decisions do not serve): the straight edge first, then
trees from the start and the goal, the one with fewer nodes extending by at most ``step`` towards a uniform
sample and the other stepping towards the new node by at most ``step`` a step (CONNECT; each edge taken
whole or not at all), then random
shortcuts; every edge decided by the
subdivision of :mod:`diffkin.motion._edges` with the same reach bound ``R``
(:func:`~diffkin.motion.joint_reach`) and each problem's resolution. What differs: one problem at a time per
thread instead of all problems per iteration
(a solved problem stops costing at once), and the randomness: each problem's stream is seeded by ``seed``
and the bytes of its own start and goal, so a problem planned alone returns what its row returns in any
batch, on any number of threads (the torch path draws one stream for the whole batch).

Interface: :class:`PlanArgs` mirrors ``dk_plan`` (``DK_PLAN_FIELDS``) field by field, checked once against
the library by :func:`diffkin.kernels.native.check_layout` (a mismatch: the torch path serves).
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from ..kernels import native
from ._reach import capsule_end_frames, pairs_apart

__all__ = ["NativePlanner", "PlanArgs", "VERSION", "search_native", "serves"]

#: the version of ``dk_plan`` this module speaks (DK_PLAN_VERSION in _native_plan.c)
VERSION = 6
#: dk_plan_search's per-problem status codes (DK_PLAN_* of _native_plan.c)
FOUND, NOT_FOUND, TOO_LONG, NO_MEMORY, START_BAD, GOAL_BAD, ENDS_BAD = 1, 0, 2, -1, 3, 4, 5
_I64, _F64, _PTR = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p


class PlanArgs(ctypes.Structure):
    """``dk_plan`` of ``_native_plan.c`` (``DK_PLAN_FIELDS``, where each field is described)."""

    VERSION = VERSION
    _fields_ = [(name, _I64) for name in ("version", "size", "nthreads")] + \
        [("chain", _PTR), ("collide", _PTR), ("C", _I64), ("col_frame", _PTR), ("col_h", _PTR),
         ("base", _PTR), ("B", _I64)] + \
        [(name, _PTR) for name in ("q_start", "q_goal", "world", "eta", "lo", "hi", "reach")] + \
        [("step", _F64), ("goal_bias", _F64)] + \
        [(name, _I64) for name in ("max_iterations", "restart", "shortcut_tries", "seed", "capacity")] + \
        [(name, _PTR) for name in ("path", "n_way", "status", "iterations", "checked", "nodes")] + \
        [("N", _I64), ("q", _PTR), ("wid", _PTR), ("slack", _F64), ("ok", _PTR)] + \
        [("qb", _PTR), ("steps", _PTR), ("slacks", _PTR), ("prefix", _I64), ("first_bad", _PTR)] + \
        [("keys", _PTR), ("rounds", _I64), ("tries", _I64), ("stop_after", _I64)] + \
        [("ends", _I64), ("resolution", _F64), ("nanoseconds", _PTR), ("no_hints", _I64), ("hinted", _PTR)]


_fns: dict = {}  # id of the loaded library -> (dk_plan_search, dk_plan_decide, dk_plan_edges, dk_plan_points)


def _functions():
    lib = native._lib
    fns = _fns.get(id(lib))
    if fns is None:
        native.check_layout(lib, "plan", PlanArgs)
        fns = (lib.dk_plan_search, lib.dk_plan_decide, lib.dk_plan_edges, lib.dk_plan_points)
        for fn in fns:
            fn.restype, fn.argtypes = _I64, [ctypes.POINTER(PlanArgs)]
        _fns[id(lib)] = fns
    return fns


def _run(which: int, args: PlanArgs, what: str) -> bool:
    """Call entry ``which`` of :func:`_functions` (0 search, 1 decide, 2 edges, 3 points) on ``args``: True
    when it ran, False where it refused the call (another interface, a range it does not serve: the torch
    code serves); a MemoryError where its per-thread work space could not be allocated."""
    status = _functions()[which](ctypes.byref(args))
    if status in (native.CONSTANTS["DK_ABI_ERROR"], native.CONSTANTS["DK_RANGE_ERROR"]):
        return False
    if status < 0:
        raise MemoryError(f"motion.plan: the C {what}: no memory for a per-thread work space")
    return True


class NativePlanner:
    """The C search's constants for one :class:`~diffkin.motion._edges.EdgeChecker` and dtype: the chain's
    all-frames FK (:meth:`LinkFrames.native_frames_model <diffkin.collision._poses.LinkFrames>`), each
    capsule end's frame and coordinates there (the blocks of :meth:`RobotCollision._placement`), and the
    :class:`~diffkin.kernels.native.Collide` of the checker's decisions. :meth:`make` returns None where the
    C search does not serve: no library, CUDA, a model with robot boxes, convex meshes or entries the C
    decisions leave to torch."""

    def __init__(self, model, base: Tensor, collide, keep: list, frame: Tensor, h: Tensor, dtype,
                 pruned=None):
        self.model, self.collide, self._keep, self.frame, self.h = model, collide, keep, frame, h
        self.base12, self.dtype = base[:3].to(dtype).contiguous(), dtype
        self._template = None  # the constants' PlanArgs (:meth:`search_args`), made once
        #: ``(collide, lo, hi, slack)`` of :func:`_without_pairs_apart`, or None: for :meth:`collide_for`
        self.pruned = pruned

    def collide_for(self, q: Tensor, slack: float) -> int:
        """The address of the Collide to decide configurations ``q (..., nq)`` with (and every configuration
        on the straight edges between them) at slacks up to ``slack``: :attr:`pruned`'s where its proof
        covers them all (each in its box: the box is convex), else every pair's."""
        got = self.pruned
        if got is not None and slack <= got[3]:
            flat = q.detach().reshape(-1, q.shape[-1])
            if bool(((flat >= got[1]) & (flat <= got[2])).all()):
                return ctypes.addressof(got[0])
        return ctypes.addressof(self.collide)

    @classmethod
    def make(cls, checker, q: Tensor) -> NativePlanner | None:
        rc = checker.collision
        if q.device.type != "cpu" or q.dtype not in (torch.float32, torch.float64) or not native.available():
            return None
        try:
            _functions()
        except (AttributeError, native.AbiMismatch):
            return None
        nc, nb = rc._counts
        world = checker.world
        keep_self, keep_world = rc._kept(world, checker.moving)
        if nb or rc._nconvex or keep_self is not None or nc == 0 or rc.capsule_a.dtype != q.dtype \
                or (world is not None and len(world.batch_shape) > 1):
            return None
        made = rc._frames.native_frames_model(rc.chain, q)
        if made is None:
            return None
        model, base = made
        skip = None if world is None else rc._world_skip(world, keep_world)
        empty = q.new_zeros(nc, 3, 0)
        objects, hs, skip_r, skip_h, extra, left, _ = rc._native_inputs(world, checker.margin, 0.0, skip,
                                                                        None, empty)
        if left:
            return None
        extra.pop("world_index", None)
        collide = native.collide_struct(empty, empty, rc.capsule_radius.detach(), rc._pairs_00, objects, hs,
                                        skip_r, skip_h, checker.margin, 0.0, None, **extra)
        if collide is None:
            return None
        # each capsule end's frame and coordinates there (2 G, 4): found once for the copies allow_collisions
        # makes per scene (about 1 ms a plan)
        frame, h = checker.remembered(f"planner columns {q.dtype}", lambda: capsule_end_frames(rc, q.dtype))
        # the decisions without the pairs proven apart: part of the scene's preparation, as the rest
        pruned = _without_pairs_apart(collide[0], rc, checker.margin, checker.eta, q.dtype)
        keep = [*collide[1], empty, *(() if pruned is None else pruned[4:])]
        return cls(model, base, collide[0], keep, frame, h, q.dtype, None if pruned is None else pruned[:4])

    def args(self, collide: int | None = None, **fields) -> PlanArgs:
        """A :class:`PlanArgs` with the constants and ``fields`` set (tensors by their address; ``collide``:
        the address of the decisions' Collide, :meth:`collide_for`'s; None: every pair's)."""
        collide = ctypes.addressof(self.collide) if collide is None else collide
        return native.new_struct(PlanArgs, chain=ctypes.addressof(self.model.args[self.dtype]),
                                 collide=collide, C=self.frame.shape[0],
                                 col_frame=self.frame, col_h=self.h, base=self.base12, **fields)

    def search_args(self) -> PlanArgs:
        """A fresh copy of a :class:`PlanArgs` holding the constants (:meth:`args` without fields, made once:
        a one-problem search's Python costs less than its C)."""
        if self._template is None:
            self._template = self.args()
        return PlanArgs.from_buffer_copy(self._template)

    def decide(self, q: Tensor, world_row: Tensor | None, slack: float) -> Tensor | None:
        """``(N,)`` bool: configurations ``q (N, nq)`` clear of margin + ``slack``, each in its world row
        ``world_row (N,)`` (None: row 0); None where the call is refused (another interface)."""
        N = q.shape[0]
        q = q.detach().to(self.dtype).contiguous()
        ok = torch.zeros(N, dtype=torch.uint8)
        wid = None if world_row is None else world_row.to(torch.int64).contiguous()
        if N == 0:
            return ok.bool()
        a = self.args(self.collide_for(q, float(slack)), nthreads=native.thread_count(N), N=N, q=q, wid=wid,
                      slack=float(slack), ok=ok, max_iterations=0)
        return ok.bool() if _run(1, a, "decisions") else None

    def edges(self, qa: Tensor, qb: Tensor, steps: Tensor, slack: Tensor, world_row: Tensor | None,
              prefix: bool) -> tuple[Tensor, Tensor] | None:
        """The subdivision samples i = 0 .. ``steps[e]`` of the straight edges ``qa → qb (E, nq)`` decided
        in C (``dk_plan_edges``: in order with ``prefix``, else coarse, then in order; an edge leaves at its
        first colliding block), each with the slack ``slack[e]`` in its world row ``world_row[e]`` (None:
        row 0): ``(first_bad (E,), decided (E,))`` long, first_bad the colliding sample found (``steps + 1``:
        every sample clear; with ``prefix`` the first one along the edge); None where the call is refused."""
        E = qa.shape[0]
        qa, qb = (t.detach().to(self.dtype).contiguous() for t in (qa, qb))
        steps = steps.to(torch.int64).contiguous()
        slack = slack.detach().to(self.dtype).contiguous()
        wid = None if world_row is None else world_row.to(torch.int64).contiguous()
        first_bad, decided = torch.empty(E, dtype=torch.int64), torch.zeros(E, dtype=torch.int64)
        # (a cover decides at COVER_SLACK times the edge's slack)
        most = native.CONSTANTS["COVER_SLACK"] * float(slack.max()) if E else 0.0
        a = self.args(self.collide_for(torch.cat((qa, qb)), most), nthreads=native.thread_count(int(E) * 64),
                      N=E, q=qa, qb=qb, steps=steps, slacks=slack, wid=wid, prefix=int(prefix),
                      first_bad=first_bad, checked=decided, max_iterations=0)
        return (first_bad, decided) if _run(2, a, "edge decisions") else None


def _without_pairs_apart(collide, rc, margin: float, eta: float, dtype):
    """``(collide, lo, hi, slack, pi, pj)``: a copy of the :class:`~diffkin.kernels.native.Collide`
    ``collide`` of ``rc``'s decisions without the self pairs proven apart by ``margin + COVER_SLACK · η``
    (:func:`~diffkin.motion._reach.pairs_apart`) in every configuration of the box ``lo <= q <= hi`` (the
    chain's limits), so the same decisions at any slack up to ``slack`` = COVER_SLACK · η for configurations
    in that box (:meth:`NativePlanner.collide_for`), and the pair arrays it points into (keep them alive);
    None where no pair is proven apart. On the Panda 264 of its 690 pairs, about 20 % of a search's time."""
    slack = native.CONSTANTS["COVER_SLACK"] * eta
    apart, lo, hi = pairs_apart(rc, rc._pairs_00, margin + slack)
    if not bool(apart.any()):
        return None
    kept = rc._pairs_00[~apart]
    pi, pj = kept[:, 0].contiguous(), kept[:, 1].contiguous()
    c = type(collide).from_buffer_copy(collide)  # the same constants, the other pairs
    c.P, c.pi, c.pj = kept.shape[0], pi.data_ptr() if len(pi) else None, pj.data_ptr() if len(pj) else None
    return c, lo.to(dtype), hi.to(dtype), slack, pi, pj


def shortcut_points_native(checker, path: Tensor, n: Tensor, problem: Tensor, rounds: int, key: Tensor,
                           tries: int, stop_after: int) -> tuple[Tensor, Tensor] | None:
    """:func:`diffkin.motion._search.shortcut_points` in C (``dk_plan_points``: each path's rounds in
    one thread, its edges decided there): the same draws, choices and splices, the points' coordinates
    to rounding (the segment lengths summed in C's order). ``path (B, L, nq)``, ``n (B,)``, ``problem
    (B,)``, ``key (B,)`` (:func:`~diffkin.motion._search.row_keys`); returns ``(path (B, L + rounds, nq),
    n (B,))``, or None where the C decisions do not serve (then the torch loop does)."""
    planner = checker.native(path) if checker.use_c else None
    if planner is None or path.shape[0] == 0:
        return None
    B, L, nq = path.shape
    cap = L + max(int(rounds), 0)
    out = torch.cat((path, path[:, -1:].expand(B, cap - L, nq)), 1).to(planner.dtype).contiguous()
    count = n.to(torch.int64).contiguous().clone()
    eta = checker.eta_of(problem).to(planner.dtype).contiguous()
    world = problem.to(torch.int64).contiguous() if checker.per_row else None
    reach, keys = checker.reach.to(planner.dtype).contiguous(), key.to(torch.int64).contiguous()  # kept alive
    most = native.CONSTANTS["COVER_SLACK"] * float(eta.max())  # (a cover decides at COVER_SLACK times η)
    a = planner.args(planner.collide_for(out, most), nthreads=native.thread_count(B * 4096), B=B, path=out,
                     n_way=count, world=world, eta=eta,
                     reach=reach, capacity=cap, keys=keys, rounds=int(rounds), tries=int(tries),
                     stop_after=int(stop_after), max_iterations=0)
    if not _run(3, a, "shortcuts"):
        return None
    return out.to(path.dtype), count.to(n.dtype)


def serves(checker, q: Tensor) -> bool:
    """Whether :func:`search_native` serves the checker's model and world for tensors like ``q``."""
    return checker.native(q) is not None


def search_native(checker, q_start: Tensor, q_goal: Tensor, lo: Tensor, hi: Tensor, problem: Tensor,
                  eta: Tensor | None, *, max_iterations: int, step: float, shortcut_tries: int, seed: int,
                  goal_bias: float = 0.0, restart: int = 0, capacity: int = 256,
                  rungs: int = 0, hints: bool = True) -> tuple[Tensor, Tensor, Tensor, dict] | None:
    """Paths ``(B, L, nq)`` (rows padded with their goal) from ``q_start`` to ``q_goal`` ``(B, nq)`` of
    problems ``problem (B,)`` (rows of the checker's world), each edge subdivided at the row's resolution
    ``eta (B,)`` (both trees grown anew every ``restart`` iterations without a join; 0: never), their
    waypoint counts ``(B,)``, ``found (B,)`` and statistics (``iterations``, ``checked``: configurations
    decided, ``nodes``: the two trees' nodes at the end, ``too_long``: rows whose path kept more than
    ``capacity`` waypoints, ``nanoseconds``: each problem's wall time in C, read from a monotonic clock in
    its thread, as VAMP's planners time themselves); None where the C search does not serve
    (:func:`serves`). Start and goal must be clear of ``margin + eta``
    (:func:`diffkin.motion.plan._row_resolution`): the edges ending at them take them as clear (the direct
    edge decides the goal, but its verdict is read only where the whole edge is clear).

    With ``rungs`` >= 1 the C search decides the starts and goals itself, as
    :func:`~diffkin.motion.plan._row_resolution` does (``eta`` is not read: give None): each problem's
    resolution the largest ``checker.eta / 2^i``, i < ``rungs``, that both clear; ``stats`` then holds
    ``eta (B,)`` and ``start_ok``, ``goal_ok (B,)`` bool, each end's own verdict (a row failing either is
    not searched). ``checked`` counts the search's decisions, not those of the ends.

    ``hints=False`` makes the search forget the collisions it found (each first block of an edge decides
    the last ones found first): the same paths and counts, in more time (a test's reference); ``stats``
    holds ``hinted (B,)``, the blocks found colliding by a remembered collision alone."""
    planner = checker.native(q_start)
    if planner is None:
        return None
    dtype = planner.dtype
    B, nq = q_start.shape
    qs, qg, lo_, hi_ = (native.contiguous_as(t, dtype) for t in (q_start, q_goal, lo, hi))
    # every configuration the search decides lies in the box lo_ .. hi_ (its samples, the starts and goals
    # where they lie in it, the edges between them), at slacks up to COVER_SLACK times the largest resolution
    slack = native.CONSTANTS["COVER_SLACK"] * (checker.eta if rungs > 0 or B == 0 else float(eta.max()))
    inside = bool(((qs >= lo_) & (qs <= hi_) & (qg >= lo_) & (qg <= hi_)).all())
    collide = planner.collide_for(torch.stack((lo_, hi_)), slack) if inside and B else None
    reach = checker.remembered(f"planner reach {dtype}", lambda: checker.reach.to(dtype).contiguous())
    eta_ = torch.empty(B, dtype=dtype) if rungs > 0 else native.contiguous_as(eta, dtype)
    L = max(2, int(capacity))
    path = torch.empty(B, L, nq, dtype=dtype)
    # n_way, status, iterations, checked, nodes, nanoseconds, hinted
    out = torch.zeros(7, B, dtype=torch.int64)
    a = planner.search_args()
    if collide is not None:
        a.collide = collide
    a.nthreads, a.B, a.step, a.goal_bias = native.thread_count(B * 4096), B, float(step), float(goal_bias)
    a.max_iterations, a.restart, a.shortcut_tries = int(max_iterations), int(restart), int(shortcut_tries)
    a.seed, a.capacity, a.ends, a.resolution = int(seed), L, max(int(rungs), 0), float(checker.eta)
    a.no_hints = int(not hints)
    for name, t in (("q_start", qs), ("q_goal", qg), ("eta", eta_), ("lo", lo_), ("hi", hi_),
                    ("reach", reach), ("path", path)):
        setattr(a, name, t.data_ptr())
    row = out.data_ptr()
    a.n_way, a.status, a.iterations, a.checked, a.nodes, a.nanoseconds, a.hinted = \
        (row + 8 * B * k for k in range(7))
    world = problem.to(torch.int64).contiguous() if checker.per_row else None  # kept alive to the call
    a.world = None if world is None else world.data_ptr()
    if B and not _run(0, a, "search"):
        return None
    n_way, status, its, checked, nodes, nanoseconds, hinted = out
    if bool((status == NO_MEMORY).any()):
        raise MemoryError("motion.plan: the C search ran out of memory growing its trees")
    stats = {"iterations": its, "checked": checked, "nodes": nodes, "too_long": status == TOO_LONG,
             "nanoseconds": nanoseconds, "hinted": hinted}
    if rungs > 0:
        both = status == ENDS_BAD
        stats.update(eta=eta_, start_ok=(status != START_BAD) & ~both, goal_ok=(status != GOAL_BAD) & ~both)
    return path, n_way, status == FOUND, stats
