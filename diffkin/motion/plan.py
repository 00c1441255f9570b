"""Batched motion planning: collision-free, limit-respecting timed trajectories from start to goal (§4.2–4.3
timing laws through a cluttered scene).

Pipeline of :func:`plan` (every stage batched over the problems; loops run over iterations, never rows):

1. **Goals**: joint goals as given, or pose goals solved by :func:`diffkin.ik.solve` with the collision model
   (seeded with the start).
2. **Per-row checks**: the start and goal within the joint limits and clear of ``margin + η_b`` with η_b
   the problem's resolution (the subdivision's slack, :mod:`diffkin.motion._edges`): ``resolution``, or
   ``resolution / 2^k`` where a start or goal is closer than that to an obstacle (decided in the C search's
   call where it serves, else in torch before the search); the limits > 0: a failing row gets its
   ``reason``; nothing is raised for the batch.
3. **Search**: the straight edge first, then RRT-Connect; in C on the CPU
   (:mod:`diffkin.motion._native_search`: one problem per thread, problems over OpenMP threads), else in
   torch vectorised over the unsolved problems (:mod:`diffkin.motion._search`; CUDA, no compiler). Every
   edge is checked by a subdivision whose joint step bounds the travel of every geom point by twice the
   problem's resolution η, every sample clear of ``margin + η`` (so the continuous edge is clear of
   ``margin``: :mod:`diffkin.motion._edges`).
4. **Shortcutting**: random straight shortcuts between waypoints, each edge checked the same way (in C with
   the C search); then :data:`POINT_ROUNDS` × ``shortcut_rounds`` rounds of shortcuts between points
   anywhere on the path
   (:func:`~diffkin.motion._search.shortcut_points`: the detours a path of few waypoints keeps; each
   problem's draws its own stream, seeded by ``seed`` and its start and goal; where the C decisions serve,
   its rounds run in C too, ``dk_plan_points``: the same choices, the points to rounding).
5. **Geometric path**: the cubic spline through the waypoints (chord-length knots, zero path slope at both
   ends), checked continuously by the same bound (along its length in the bound's metric); where it leaves
   the clear region (or the limits), the knot intervals it fails on and their neighbours are split at their
   midpoints (points of the checked polyline, which the new spline hugs closer) and the spline checked
   again, up to :data:`REFINE_ROUNDS` times (0 by default: off, see there); a refined row is timed both
   ways and keeps the faster; a row no round proves falls back to the checked polyline itself (a stop at
   every waypoint).
6. **Optimisation** (``optimize=True``, :mod:`diffkin.motion.optimize`): the path resampled to knots and
   optimised for smoothness with the distances and limits as constraints; kept where its segments and
   spline are proven clear as above, else the path of 5. The optimised knots carry the implicit gradient
   w.r.t. the start, the goal and the world's tensors where the iterations converged.
7. **Timing** (:func:`diffkin.trajectories.time_optimal`): TOPP-RA under the velocity and acceleration
   limits, smoothed for the jerk limit (zero acceleration at both ends), limits held on dense samples.

A row succeeds when all of that holds: it starts exactly at ``q_start``, rests at both ends (zero velocity
and acceleration), ends at the goal (exactly for joint goals; within the IK tolerances for pose goals),
keeps every limit on the samples, and its continuous motion is proven clear of ``margin``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import ConventionError, OptionError, ShapeError
from ..trajectories import Trajectory
from ..trajectories.time_optimal import CHECK_PER_INTERVAL, _timed, unit_knots
from ..validation import check_count, check_number, shape_str, tensors
from ._edges import EdgeChecker
from ._native_search import search_native
from ._search import row_keys, search, shortcut, shortcut_points
from ._spline import _knots, _spline, _spline_failures
from .optimize import OptimizeConfig, optimize_stage, sample_with

__all__ = ["MotionResult", "plan"]

#: the jerk bound of the smoothing when no ``jerk_limit`` is given: this many times the acceleration limit
#: per second (the motion still starts and ends with zero acceleration)
DEFAULT_JERK_PER_ACCELERATION = 100.0
#: a start or goal clear of margin + η / 2^k but not of margin + η gets the resolution η / 2^k for its whole
#: problem, k ≤ ETA_LEVELS (η / 1024: 5 µm at the default 5 mm); closer ones fail as in collision
ETA_LEVELS = 10
#: shortcut attempts per path per round of ``shortcut_rounds``
SHORTCUT_TRIES = 4
#: waypoints a path of the C search may keep after its shortcuts (its rows of the output); a longer one fails
#: with its reason (CONNECT's steps make a searched path a tree's nodes: up to about 2 max_iterations times
#: the steps of one CONNECT before the shortcuts)
PATH_CAPACITY = 1024
#: rounds of spline refinement (module docstring, 5): each splits the knot intervals where the spline is not
#: proven clear, and their neighbours, at their midpoints (the spacing there halves each round)
#: 0 by default: refined splines timed by time_optimal can carry a jump of q̈ between its samples (cage/0035
#: of the 700 MotionBenchMaker problems in one call: 21 400 rad/s³ at 1 ms against the 10 000 limit, the row
#: reported a success); a round count > 0 turns the refinement on for experiments until that is found.
#: With the timing's knot-interval samples (time_optimal, 4 December) 6 rounds still left cage/0060 at 8.2x
#: and bookshelf_thin/0066 at 1.13x their jerk limit on 0.1 ms samples (while the cage's median duration
#: fell from 3.30 s to 2.63 s): still off
REFINE_ROUNDS = 0
#: rounds of shortcuts between points anywhere on the searched path (:func:`~._search.shortcut_points`) per
#: round of ``shortcut_rounds``, and the shortcuts tried per path per round (each clear one taken costs its
#: edge's whole subdivision: on the cage problems this stage costs about what the search does)
POINT_ROUNDS, POINT_TRIES = 1, 8  # 2 rounds: 1.7x the time, no shorter (docs/motion.md, Measured)


def _row_resolution(checker: EdgeChecker, q_start: Tensor, q_goal: Tensor, rows: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """Each problem's resolution ``(B,)``: the largest η / 2^k (k ≤ :data:`ETA_LEVELS`) whose slack both
    its start and goal clear, and ``start_ok``, ``goal_ok (B,)`` (clear of margin + η / 2^ETA_LEVELS). Only
    the rows that fail a level are decided again at the next (usually none past the first)."""
    B = q_start.shape[0]
    eta = torch.full((B,), checker.eta, dtype=checker.reach.dtype, device=q_start.device)
    ok = torch.zeros(2 * B, dtype=torch.bool, device=q_start.device)  # the starts', then the goals'
    q = torch.cat((q_start, q_goal))
    todo = torch.cat((rows, rows + B))  # entries of q (and ok) left to decide
    for k in range(ETA_LEVELS + 1):
        s = checker.eta / 2 ** k
        r = todo % B
        good = checker.clear(q[todo], r, slack=s)  # the starts and goals in one decision
        ok[todo[good]] = True
        eta[r[good]] = torch.minimum(eta[r[good]], eta.new_tensor(s))
        todo = todo[~good]
        if not todo.numel():
            break
    return eta, ok[:B], ok[B:]


@dataclass
class MotionResult:
    """Batched result of :func:`plan`.

    Attributes:
        success: ``(B,)`` bool (see :func:`plan`).
        duration: ``(B,)`` seconds (0 for failed rows).
        t: ``(B, S)`` sample times ``0, dt, 2 dt, …`` up to the longest duration.
        q, qd, qdd: ``(B, S, nq)`` positions, velocities, accelerations at ``t`` (rows past their duration
            hold the goal at rest; failed rows hold the start).
        reason: per row, ``""`` on success or why it failed.
        q_goal: ``(B, nq)`` the goal configuration (IK's solution for pose goals).
        waypoints: ``(B, L, nq)`` the shortcut collision-checked path (rows padded with their goal) and
            ``n_waypoints (B,)`` its waypoint counts.
        interpolation: per row ``"spline"`` or ``"linear"`` (the fallback), ``""`` for failed rows.
        optimized: ``(B,)`` bool, the rows timed along their optimised knots (``optimize=True``; then
            ``waypoints`` holds those knots).
    """

    success: Tensor
    duration: Tensor
    t: Tensor
    q: Tensor
    qd: Tensor
    qdd: Tensor
    reason: list[str]
    q_goal: Tensor
    waypoints: Tensor
    n_waypoints: Tensor
    interpolation: list[str]
    optimized: Tensor
    _timing: list

    def state(self, t) -> Trajectory:
        """q, q̇, q̈ ``(B, T, nq)`` at times ``t`` ``(T,)`` or ``(B, T)`` [s] (failed rows hold the start)."""
        B = self.success.shape[0]
        t = tensors(("t", t, None), like=self.q)[0].to(torch.float64)
        t = t.reshape(1) if t.ndim == 0 else t
        if t.ndim == 1:
            t = t.expand(B, -1)
        if t.ndim != 2 or t.shape[0] != B:
            raise ShapeError(f"expected t of shape (T,) or ({B}, T), got {shape_str(t.shape)}")
        return self._state(t)

    def _state(self, t: Tensor) -> Trajectory:
        """:meth:`state` at float64 times (B, T), unchecked."""
        B, nq = self.success.shape[0], self.q.shape[-1]
        q = self.q[:, :1].detach().expand(B, t.shape[1], nq).clone()  # samples carry no gradient
        qd, qdd = torch.zeros_like(q), torch.zeros_like(q)
        for rows, timed in self._timing:  # a few timings (optimised, spline, refined splines, polyline)
            tr = timed._sample(t[rows])
            q[rows], qd[rows], qdd[rows] = tr.position, tr.velocity, tr.acceleration
        return Trajectory(q, qd, qdd)

    def sample(self, t) -> Tensor:
        """Positions ``(B, T, nq)`` at times ``t`` ``(T,)`` or ``(B, T)`` [s] (see :meth:`state`)."""
        return self.state(t).position


def _limits(x, B: int, nq: int, name: str, like: Tensor) -> Tensor:
    x = tensors((name, x, None), like=like, finite=False)[0]
    if x.ndim > 2 or (x.ndim and x.shape[-1] != nq) or (x.ndim == 2 and x.shape[0] != B):
        raise ShapeError(f"expected {name} as a number, ({nq},) or ({B}, {nq}), got {shape_str(x.shape)}")
    return x.expand(B, nq)


def _pad(path: Tensor, n: Tensor) -> Tensor:
    """Paths (B, L, nq) with n (B,) waypoints, each row brought to L waypoints by splitting its longest
    segment at the midpoint (the polyline is unchanged)."""
    B, L, nq = path.shape
    rows = torch.arange(B, device=path.device)
    cols = torch.arange(L, device=path.device)[None]
    while bool((n < L).any()):
        seg = (path[:, 1:] - path[:, :-1]).norm(dim=-1)
        seg = torch.where(cols[:, :-1] < (n - 1)[:, None], seg, -1.0)
        i = seg.argmax(1)
        need = n < L
        mid = (path[rows, i] + path[rows, i + 1]) / 2
        src = torch.where(cols > i[:, None], cols - 1, cols).clamp(min=0)
        new = path[rows[:, None], src]
        new[rows, i + 1] = mid
        path = torch.where(need[:, None, None], new, path)
        n = n + need.long()
    return path


def _split(path: Tensor, cut: Tensor) -> Tensor:
    """Paths (R, L, nq) with the segments ``cut`` (R, L − 1) split at their midpoints: (R, L', nq), rows
    with fewer cuts brought to L' by :func:`_pad` (the polyline is unchanged)."""
    R, L, nq = path.shape
    extra = cut.long().cumsum(1)
    at = torch.arange(L, device=path.device)[None] + torch.cat((extra.new_zeros(R, 1), extra), 1)  # (R, L)
    n = L + extra[:, -1]
    out = path.new_zeros(R, int(n.max()) if R else L, nq)
    out.scatter_(1, at[..., None].expand(R, L, nq), path)
    mid = (path[:, 1:] + path[:, :-1]) / 2
    r, k = cut.nonzero(as_tuple=True)
    out[r, at[r, k] + 1] = mid[r, k]
    return _pad(out, n)


def _refine_spline(checker: EdgeChecker, path: Tensor, bad: Tensor, todo: Tensor, lo: Tensor, hi: Tensor,
                   problem: Tensor) -> tuple[list[tuple[Tensor, Tensor]], Tensor]:
    """The rows ``todo`` (R,) bool of ``path`` (R, L, nq) whose spline fails on the knot intervals ``bad``
    (R, L − 1) (:func:`~diffkin.motion._spline._spline_failures`), refined: each of
    :data:`REFINE_ROUNDS` rounds splits the failing intervals and their neighbours at their midpoints (points
    of the checked polyline, so the spline through them hugs it closer where it left the clear region) and
    checks the new spline again. Returns the rounds' proven rows as ``(rows (R,) bool, path)`` and the rows
    no round proved (R,) bool."""
    left, found = todo.clone(), []
    idx = todo.nonzero().squeeze(1)
    p, b = path[idx], bad[idx]
    for _ in range(REFINE_ROUNDS):
        if idx.numel() == 0:
            break
        cut = b.clone()
        cut[:, 1:] |= b[:, :-1]
        cut[:, :-1] |= b[:, 1:]
        p = _split(p, cut)
        b = _spline_failures(checker, p, _knots(p), lo, hi, problem[idx])
        ok = ~b.any(1)
        if bool(ok.any()):
            found.append((torch.zeros_like(todo).index_fill(0, idx[ok], True), p[ok]))
            left[idx[ok]] = False
        idx, p, b = idx[~ok], p[~ok], b[~ok]
    return found, left


def plan(chain, q_start, goal, *, collision, world=None, margin: float = 0.0, velocity_limit=None,
         acceleration_limit=None, jerk_limit=None, dt: float = 0.01, resolution: float = 0.005,
         max_iterations: int = 2000, step: float = 0.3, shortcut_rounds: int = 8, seed: int = 0,
         goal_bias: float = 0.0, search_in_c: bool = True, position_tolerance: float = 1e-4,
         orientation_tolerance: float = 1e-3, optimize: bool | OptimizeConfig = False) -> MotionResult:
    """Collision-free, limit-respecting timed trajectories from ``q_start`` to ``goal``, batched (module
    docstring: goals, per-row checks, search, shortcut, timing, continuous re-check).

    Args:
        chain: a chain of revolute joints (a URDF or MJCF arm).
        q_start: ``(B, nq)`` start configurations.
        goal: ``(B, nq)`` goal configurations, or goal poses ``(B, 4, 4)`` (``(B, K, 4, 4)`` for K end links)
            solved by :func:`diffkin.ik.solve` with the collision model.
        collision: the robot's :class:`~diffkin.collision.RobotCollision` on ``chain`` (self pairs and
            geoms of the links fixed to the chain included).
        world: the obstacles (:class:`~diffkin.collision.World`): one for all problems, one scene per
            problem (a world of batch shape ``(B,)``, :meth:`World.stack <diffkin.collision.World.stack>`),
            or None.
        margin: the least clearance [m] of the continuous motion.
        velocity_limit / acceleration_limit / jerk_limit: a number, ``(nq,)`` or ``(B, nq)``.
            ``velocity_limit`` None: the URDF's ``<limit velocity=>``; the URDF holds no acceleration limit,
            so ``acceleration_limit`` must be given. ``jerk_limit`` None: the smoothing bound
            ``DEFAULT_JERK_PER_ACCELERATION · acceleration_limit`` (1/s) — the motion still rests with zero
            acceleration at both ends. A row with a limit ≤ 0 or NaN fails with its reason.
        dt: sampling period of ``t``, ``q``, ``qd``, ``qdd`` [s].
        resolution: η [m], the slack of every collision check: each sample is clear of ``margin + η``, and
            every geom point travels at most 2η between two samples, so within η of the nearer one (module
            docstring of :mod:`diffkin.motion._edges`); a problem whose start or goal is clear of
            ``margin + η / 2^k`` but not of ``margin + η`` is planned at the resolution η / 2^k
            (k ≤ :data:`ETA_LEVELS`; closer: the row fails as in collision).
        max_iterations / step / shortcut_rounds / seed / goal_bias: search budget per problem, RRT step
            (metres of geom travel in the bound's metric), shortcut rounds (:data:`SHORTCUT_TRIES` tries per
            path each between waypoints, and :data:`POINT_ROUNDS` rounds of :data:`POINT_TRIES` between any
            points of the path each; 8 by default: 16 took about 3 ms more a plan one at a time for the same
            durations on 70 MotionBenchMaker problems), randomness, the probability of extending towards
            the other tree's root.
        search_in_c: the search stage by the C RRT-Connect (:mod:`diffkin.motion._native_search`: one
            problem per thread, each problem's randomness its own, so a problem planned alone equals its
            row in a batch) where it serves (CPU, the library built, capsule and sphere models whose
            decisions are all in C); else, or with False, the torch search (batched over problems, one
            random stream for the batch; CUDA); with it the other stages' decisions go through the C
            placement too.
        position_tolerance / orientation_tolerance: of the pose goals' IK.
        optimize: True (or an :class:`~diffkin.motion.optimize.OptimizeConfig`) for the optimisation stage
            (module docstring, :mod:`diffkin.motion.optimize`).

    Returns:
        :class:`MotionResult`.

    **Gradients** (``optimize`` on, grad mode on, and ``q_start``, a joint ``goal`` or a tensor of ``world``
    requiring grad): ``q``, ``qd``, ``qdd`` and ``waypoints`` of the rows with ``optimized`` True are
    differentiable w.r.t. them, through the implicit gradient of the optimised knots (the KKT point of
    :mod:`diffkin.motion.optimize`) and the spline through them; the timing (the time law s(t) and the
    spline's knot parameters) is held fixed at the solution. The gradient is the local one: it is not
    defined where the perturbation changes the set of distance rows held, and says nothing about another
    homotopy class (a re-plan that goes round the other side of an obstacle). Other rows, rows whose
    optimisation did not converge within ``OptimizeConfig.iterations`` (kept when proven clear, but no
    KKT point), and pose goals (their IK solution) get no gradient.
    """
    from ..ik import solve as ik_solve

    dt = check_number(dt, "dt")
    resolution = check_number(resolution, "resolution")
    margin = check_number(margin, "margin", positive=False)
    step = check_number(step, "step")
    check_count(max_iterations, "max_iterations", 0)
    goal_bias = check_number(goal_bias, "goal_bias", positive=False)
    if goal_bias > 1:
        raise OptionError(f"expected goal_bias as a probability in [0, 1], got {goal_bias!r}")
    check_count(shortcut_rounds, "shortcut_rounds", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or not -(1 << 63) <= seed < 1 << 63:
        raise OptionError(f"expected seed as an integer that fits an int64, got {seed!r}")
    collision._check_chain(chain, "motion.plan")
    q_start = chain.check_q(q_start, "q_start")
    if q_start.ndim != 2:
        raise ShapeError(f"expected q_start of shape (B, {chain.nq}), got {shape_str(q_start.shape)}")
    B, nq = q_start.shape
    goal = tensors(("goal", goal, None), like=chain)[0]
    cfg = optimize if isinstance(optimize, OptimizeConfig) else OptimizeConfig() if optimize is True else None
    if cfg is None and optimize is not False:
        raise ConventionError(f"motion.plan: optimize is a bool or an OptimizeConfig, got {optimize!r}")
    pose_goal = goal.ndim >= 3 and goal.shape[-2:] == (4, 4)
    if not pose_goal and goal.shape != (B, nq):
        raise ShapeError(f"expected goal of shape ({B}, {nq}) (joints), ({B}, 4, 4) or ({B}, K, 4, 4) "
                         f"(poses), got {shape_str(goal.shape)}")
    if pose_goal and goal.shape[0] != B:
        raise ShapeError(f"expected {B} goal poses, got {shape_str(goal.shape)}")
    if world is not None and tuple(world.batch_shape) not in ((), (B,)):
        raise ShapeError(f"expected one world for all problems or one per problem (batch shape ({B},)), "
                         f"got a world of batch shape {shape_str(world.batch_shape)}")
    if velocity_limit is None:
        velocity_limit = chain.velocity_limits() if hasattr(chain, "velocity_limits") else None
        if velocity_limit is None:
            raise ConventionError("motion.plan: the chain carries no velocity limits: give velocity_limit")
    if acceleration_limit is None:
        raise ConventionError("motion.plan: give acceleration_limit (a URDF holds none)")
    vmax = _limits(velocity_limit, B, nq, "velocity_limit", q_start)
    amax = _limits(acceleration_limit, B, nq, "acceleration_limit", q_start)
    jmax = DEFAULT_JERK_PER_ACCELERATION * amax if jerk_limit is None else \
        _limits(jerk_limit, B, nq, "jerk_limit", q_start)
    dev, dtype = q_start.device, q_start.dtype
    reason = [""] * B

    def fail(mask: Tensor, why: str) -> None:
        for r, bad in enumerate(mask.tolist()):
            if bad and not reason[r]:
                reason[r] = why

    with torch.no_grad():
        checker = EdgeChecker(collision, world, margin, resolution)
        checker.use_c = search_in_c
        gen = torch.Generator().manual_seed(seed)
        limits = torch.stack((vmax, amax, jmax))  # (3, B, nq)
        lim_ok = ((limits > 0) & limits.isfinite()).all(2).all(0)
        fail(~lim_ok, "infeasible limits (each must be a finite number > 0)")
        if pose_goal:
            ik = ik_solve(chain, goal, q0=q_start, collision=collision, world=world,
                          margin=margin + resolution, position_tolerance=position_tolerance,
                          orientation_tolerance=orientation_tolerance, seed=seed)
            q_goal = ik.q.detach().to(dtype)
            goal_in = q_goal
            fail(~ik.success.reshape(B), "goal pose unreachable (no collision-free IK solution)")
        else:
            q_goal = goal.detach()
            goal_in = goal  # the joint goal as given (its gradient reaches the optimised knots)
        lim = chain.q_limits
        if lim is not None:
            lo_l, hi_l = lim[:, 0].to(dtype), lim[:, 1].to(dtype)
            fail(((q_start < lo_l) | (q_start > hi_l)).any(1), "start outside the joint limits")
            fail(((q_goal < lo_l) | (q_goal > hi_l)).any(1), "goal outside the joint limits")
        else:
            lo_l = torch.full((nq,), -math.inf, dtype=dtype, device=dev)
            hi_l = -lo_l
        # the sampling box: the limits, and one turn about zero where a joint has none
        lo = torch.where(torch.isfinite(lo_l), lo_l, torch.full_like(lo_l, -math.pi))
        hi = torch.where(torch.isfinite(hi_l), hi_l, torch.full_like(hi_l, math.pi))
        searched = None
        if search_in_c:  # the starts and goals decided in the C search (its resolution ladder), its rows
            # those without a reason so far
            rows = torch.tensor([not r for r in reason], dtype=torch.bool, device=dev).nonzero().squeeze(1)
            searched = search_native(checker, q_start[rows], q_goal[rows], lo, hi, rows, None,
                                     max_iterations=max_iterations, step=step,
                                     shortcut_tries=SHORTCUT_TRIES * shortcut_rounds, seed=seed,
                                     goal_bias=goal_bias, capacity=PATH_CAPACITY,
                                     rungs=ETA_LEVELS + 1)
        if searched is not None:
            row_eta = torch.full((B,), checker.eta, dtype=checker.reach.dtype, device=dev)
            start_ok = torch.ones(B, dtype=torch.bool, device=dev)
            goal_ok = start_ok.clone()
            stats = searched[3]
            row_eta[rows] = stats["eta"].to(row_eta.dtype)
            start_ok[rows], goal_ok[rows] = stats["start_ok"], stats["goal_ok"]
        else:
            every = torch.arange(B, device=dev)
            row_eta, start_ok, goal_ok = _row_resolution(checker, q_start, q_goal, every)
        fail(~start_ok, f"start in collision (closer than margin + resolution / {2 ** ETA_LEVELS})")
        fail(~goal_ok, f"goal in collision (closer than margin + resolution / {2 ** ETA_LEVELS})")
        checker.set_row_resolution(row_eta)
        valid = torch.tensor([not r for r in reason], dtype=torch.bool, device=dev)
        if searched is not None:  # the searched rows that kept no reason (their starts and goals clear)
            keep = valid[rows]
            searched = tuple(t[keep] for t in searched[:3]) + ({k: v[keep] for k, v in stats.items()},)
        rows = valid.nonzero().squeeze(1)
        L = 2
        waypoints = torch.stack((q_start, q_goal), 1)
        n_way = torch.full((B,), 2, dtype=torch.long, device=dev)
        timing, interp = [], [""] * B
        optimized = torch.zeros(B, dtype=torch.bool, device=dev)
        knots = None
        success = torch.zeros(B, dtype=torch.bool, device=dev)
        duration = torch.zeros(B, dtype=dtype, device=dev)
        if rows.numel():
            if searched is not None:  # the C search (its paths already shortcut)
                path, n, found, stats = searched
                long_rows = rows[stats["too_long"]]
                fail(torch.zeros(B, dtype=torch.bool, device=dev).index_fill(0, long_rows, True),
                     f"path longer than {PATH_CAPACITY} waypoints after shortcutting")
            else:  # the torch path: CUDA, no compiler, models the C decisions do not serve
                path, n, found = search(checker, q_start[rows], q_goal[rows], lo, hi, rows,
                                        max_iterations=max_iterations, step=step, generator=gen,
                                        goal_bias=goal_bias)
                path, n = shortcut(checker, path, n, rows, shortcut_rounds, gen, tries=SHORTCUT_TRIES)
            fail(torch.zeros(B, dtype=torch.bool, device=dev).index_fill(0, rows[~found], True),
                 f"no collision-free path found in {max_iterations} iterations")
            if bool(found.any()):  # shortcuts between any points of the paths (detours between waypoints)
                sp, sn = shortcut_points(checker, path[found], n[found], rows[found],
                                         POINT_ROUNDS * shortcut_rounds,
                                         row_keys(q_start[rows[found]], q_goal[rows[found]], seed),
                                         tries=POINT_TRIES)
                if sp.shape[1] > path.shape[1]:
                    path = torch.cat((path, path[:, -1:].expand(-1, sp.shape[1] - path.shape[1], nq)), 1)
                path = path.clone()
                path[found] = torch.cat((sp, sp[:, -1:].expand(-1, path.shape[1] - sp.shape[1], nq)), 1)
                n = n.clone()
                n[found] = sn
            L = int(n[found].max()) if bool(found.any()) else 2
            path = path[:, :L]
            waypoints = q_goal[:, None].expand(B, L, nq).clone()
            waypoints[:, 0] = q_start
            waypoints[rows] = path
            n_way[rows] = n
            good = rows[found]
            if good.numel():
                p = _pad(path[found], n[found])
                kn = _knots(p)
                spline = _spline(p, kn)  # checked here, timed below (the rows proven clear)
                bad = _spline_failures(checker, p, kn, lo_l, hi_l, good, spline=spline)
                smooth = ~bad.any(1)
                groups = []
                if cfg is not None:  # the optimised knots where they are proven clear (grad mode on)
                    with torch.enable_grad():
                        knots, kept = optimize_stage(checker, world, q_start[good], goal_in[good], p, good,
                                                     lo_l, hi_l, cfg)
                    optimized[good[kept]] = True
                    smooth, p_opt = smooth & ~kept, knots.detach()[kept]
                    groups.append((kept, "spline", p_opt, _knots(p_opt), None))
                    notkept = ~kept
                else:
                    notkept = torch.ones_like(smooth)
                refined, rough = _refine_spline(checker, p, bad, notkept & ~smooth, lo_l, hi_l, good)
                own = spline if bool(smooth.all()) else spline.rows(smooth.nonzero()[:, 0])
                groups += [(smooth, "spline", p[smooth], kn[smooth], own)]

                def timed_group(keep: Tensor, how: str, pp: Tensor, kk: Tensor, path=None):
                    """time_optimal of the rows ``keep`` of ``good`` (their limits checked above; ``path``:
                    their spline where it is made already)."""
                    rr = good[keep]
                    lim = [x[rr].to(torch.float64) for x in (vmax, amax, jmax)]
                    s = unit_knots(kk) if path is None else path.s
                    return rr, _timed(pp.to(torch.float64), s, *lim, how, "clamped", None, CHECK_PER_INTERVAL,
                                      pp.dtype, path)

                def take(rr: Tensor, timed, how: str) -> None:
                    timing.append((rr, timed))
                    success[rr] = True
                    duration[rr] = timed.duration.to(dtype)
                    for r in rr.tolist():
                        interp[r] = how

                for keep, how, pp, kk, path in groups:
                    if bool(keep.any()):
                        take(*timed_group(keep, how, pp, kk, path), how)
                # the refined splines (their many knots near a tight corner can make them slower than stops
                # at the waypoints): each row timed both ways, the faster finite one taken (the polyline's
                # timing first, so the spline's entries, later, win where they are taken)
                spl = [timed_group(keep, "spline", pp, _knots(pp)) for keep, pp in refined]
                spline_wins = torch.zeros_like(rough)
                for keep, (_, timed) in zip((k for k, _ in refined), spl):
                    spline_wins[keep] = timed.duration.isfinite()
                both = rough | torch.stack([k for k, _ in refined] + [rough]).any(0)
                if bool(both.any()):
                    rr, lin = timed_group(both, "linear", p[both], kn[both])
                    take(rr, lin, "linear")
                    d_lin = torch.zeros(len(spline_wins), dtype=lin.duration.dtype, device=dev)
                    d_lin[both] = lin.duration
                    for keep, (_, timed) in zip((k for k, _ in refined), spl):
                        spline_wins[keep] &= timed.duration < d_lin[keep]
                for (keep, pp), (rr, timed) in zip(refined, spl):
                    win = spline_wins[keep]
                    if bool(win.all()):
                        take(rr, timed, "spline")
                    elif bool(win.any()):  # the rows where the polyline was faster drop out (timed anew)
                        w = keep.clone()
                        w[keep] = win
                        take(*timed_group(w, "spline", pp[win], _knots(pp[win])), "spline")
        S = int(math.ceil(float(duration.max()) / dt - 1e-9)) + 1 if B else 1
        t = (torch.arange(S, dtype=torch.float64, device=dev) * dt)
        zero = torch.zeros(B, S, nq, dtype=dtype, device=dev)
        result = MotionResult(success, duration, t.to(dtype).expand(B, S), q_start[:, None].expand(B, S, nq),
                              zero, zero, reason, q_goal, waypoints, n_way, interp, optimized, timing)
        tr = result._state(t.expand(B, S))
        result.q, result.qd, result.qdd = tr.position, tr.velocity, tr.acceleration
    if knots is not None and bool(optimized.any()):
        _with_knots(result, knots[optimized[good]], t)
    return result


def _with_knots(result: MotionResult, knots: Tensor, t: Tensor) -> None:
    """The optimised rows' waypoints and samples from their knots ``(R, M + 2, nq)`` (which may carry the
    implicit gradient; the timing held fixed: :func:`~diffkin.motion.optimize.sample_with`)."""
    rr, timed = result._timing[0]
    R, N, nq = knots.shape
    B, L = result.waypoints.shape[:2]
    way = result.waypoints.detach()
    if N > L:
        way = torch.cat((way, way[:, -1:].expand(B, N - L, nq)), 1)
    pad = torch.cat((knots, knots[:, -1:].expand(R, way.shape[1] - N, nq)), 1)
    result.waypoints = way.index_put((rr,), pad.to(way.dtype))
    result.n_waypoints = result.n_waypoints.index_fill(0, rr, N)
    q, qd, qdd = sample_with(timed, knots, t.expand(R, -1))
    result.q = result.q.index_put((rr,), q.to(result.q.dtype))
    result.qd = result.qd.index_put((rr,), qd.to(result.q.dtype))
    result.qdd = result.qdd.index_put((rr,), qdd.to(result.q.dtype))
