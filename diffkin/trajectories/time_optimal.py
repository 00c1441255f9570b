"""Time-optimal timing of a given joint path under velocity, acceleration and jerk limits (§4.2–4.3 timing
laws along a geometric path), batched over paths.

The geometric path through the waypoints ``path (B, N, n)`` at the path parameters ``knots`` (default
``linspace(0, 1, N)``, as toppra's examples) is

* ``interpolation="spline"`` (default): the C² cubic spline through the waypoints with scipy's
  ``CubicSpline`` boundary condition ``bc`` (``"not-a-knot"``, toppra's ``SplineInterpolator`` default, or
  ``"clamped"``: zero path derivative at both ends) — the same geometric path as
  ``toppra.SplineInterpolator(knots, path[b], bc_type=bc)``;
* ``interpolation="linear"``: the polyline itself (each segment a straight line in joint space). Its path
  derivative jumps at an interior waypoint, so the motion stops there (ṡ = 0): the timing of a collision-
  checked polyline that never leaves its segments. With a jerk limit each segment is timed and smoothed on
  its own (rest to rest, zero acceleration at every corner) and the segments are played in turn.

Method: time-optimal path parameterisation by reachability analysis (TOPP-RA, Pham & Pham 2018, toppra's
algorithm). On a grid s_0 < … < s_M (``grid_per_segment`` points per waypoint interval, so the waypoints are
grid points) with x = ṡ², u = s̈ and x_{i+1} = x_i + 2 Δ_i u_i, the constraints at grid point i
(collocation) are |q'_j(s_i)| √x ≤ v_j and |q'_j(s_i) u + q''_j(s_i) x| ≤ a_j. A backward pass computes the
largest x_i from which the end is reachable at rest (each a two-variable LP, solved exactly by its vertices,
all paths at once); a forward pass from x_0 = 0 takes the largest u_i that stays controllable. Between grid
points s̈ is constant (toppra's ``ParametrizeConstAccel``), so interval i lasts 2Δ_i / (ṡ_i + ṡ_{i+1}). The
two passes go one grid point at a time: in C on the CPU (``kernels/_native_topp.c``, paths over threads, the
same floats), else in torch (CUDA, no compiler); so does the bound of each interval's fixed rows.

Without a jerk limit this is bang-bang: the acceleration jumps at the switching points (and at t = 0 and
at the end). With ``jerk_limit``, the profile s(t) is smoothed by a moving average of width τ,
s̄(t) = (1/τ)∫_{t-τ}^{t} s (s = 0 before the start, 1 after the end): s̄ starts and ends at rest with zero
acceleration, its acceleration is continuous and its jerk bounded ((s̈(t) − s̈(t−τ))/τ); τ is chosen per
path among a few multiples of 2·max_j a_j / j_j (the shortest result wins; a candidate whose duration
checked at one in gcd(``check_per_interval``, 16) of the samples (by default each profile interval's ends) —
a lower bound — cannot win is not checked densely, and a dense check evaluates only the samples the coarse
check did not, on the rows where its candidate can still win; the candidates share one profile,
retimed). The smoothed motion is not time-optimal under the jerk limit (an upper bound on it).

Limits exactly: every result is finally stretched uniformly in time by the smallest factor k ≥ 1 that puts
every velocity, acceleration and jerk (with ``jerk_limit``) within its limit on a dense check (all the
breakpoints of the profile, ``check_per_interval`` points inside each interval, and 65 points over the
span of time in which the smoothed profile can be inside each of the 8 knot intervals the unsmoothed one
crosses fastest: a short knot interval, where the spline turns sharply, can otherwise fall between two of
the grid's samples), times 1 + 2e-4 for the values between the check samples; without that step the
discretised constraints would hold at the grid points only. Without a jerk limit k is within ~0.5 % of 1
(the durations stay within 1 % of toppra's on the same path). The dense check runs in C on the CPU
(``kernels/_native_topp.c``, each sample one pass, the same floats), else in torch.

No gradient flows through the timing (it is a decision, like the LP it solves); it is computed in float64
and sampled in the dtype of ``path``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import ConventionError, ShapeError
from ..kernels import native
from ..validation import check_count, check_number, shape_str, tensors
from ._common import InfeasibleTrajectoryError, Trajectory, cubic_coeffs, poly_eval, spline_slopes

__all__ = ["TimedPath", "time_optimal"]

#: the knot intervals crossed fastest, and the check samples in each one's span of time
#: (:meth:`TimedPath._knot_samples`), besides the grid's
_SHORT_INTERVALS, _KNOT_SAMPLES = 8, 64

_X_BIG = 1e12  # bound on ṡ² where no limit binds (a path derivative of zero)
# relative stretch on top of the dense check: covers the interpolation between check samples (measured up to
# 1e-4 of the acceleration limit at 16 samples per interval with a jerk limit, 1e-6 without)
_STRETCH = 2e-4
_BLOCK = 1 << 16  # samples per block of the limit check (:func:`_peaks`)
#: the most rows × τ candidates whose coarse checks run as one call (each candidate's rows a copy of the
#: profile): a small batch pays per call (B = 1: ~4 ms a plan), a large one for the copies (+44 % memory)
_ONE_CHECK = 256
#: the coarse check of the τ candidates takes one in gcd(check_per_interval, _COARSE) of the dense check's
#: samples (with the default 16: each profile interval's ends). The same result as any coarser or finer
#: check (the pruning is exact); the timing of 35 MotionBenchMaker plans took 12 % less time than with one
#: in 4 (the candidates' coarse checks cost less than the weaker bounds add in dense checks)
_COARSE = 16
#: samples per profile interval of the final limit stretch (``check_per_interval``'s default)
CHECK_PER_INTERVAL = 16
#: the most row entries :func:`_search_rows` gathers for one searchsorted (more: its binary search by
#: gathers)
_GATHERED = 1 << 16


def _search_rows(seq: Tensor, rows: Tensor, x: Tensor, right: bool = True) -> Tensor:
    """``torch.searchsorted(seq[rows], x, right=right)`` per sample: seq (P, L) sorted along L, rows and x
    (...) (each sample searched in its own row of seq) -> (...). One row, or few samples (their rows
    gathered: at most :data:`_GATHERED` entries): one torch.searchsorted. Else a binary search by gathers
    (log2 L steps), so a sample costs its own row only, not all the rows a batched searchsorted would need."""
    L = seq.shape[1]
    rows, x = torch.broadcast_tensors(rows, x) if rows.shape != x.shape else (rows, x)
    if seq.shape[0] == 1 or rows.numel() * L <= _GATHERED:  # one searchsorted (the same answer)
        if seq.shape[0] == 1:  # one row: every sample's
            i = torch.searchsorted(seq.contiguous(), x.reshape(1, -1).contiguous(), right=right)
        else:  # few samples: their rows gathered
            i = torch.searchsorted(seq[rows.reshape(-1)], x.reshape(-1, 1).contiguous(), right=right)
        return torch.where(x == x, i.view(x.shape), 0)  # a NaN sample: 0, as the search below gives it
    flat, base = seq.reshape(-1), rows * L
    lo, hi = torch.zeros_like(rows), torch.full_like(rows, L)
    for _ in range(L.bit_length()):
        mid = (lo + hi) // 2
        v = flat[base + mid.clamp(max=L - 1)]
        le = v <= x if right else v < x
        go = lo < hi
        lo, hi = torch.where(go & le, mid + 1, lo), torch.where(go & ~le, mid, hi)
    return lo


# ------------------------------------------------------------------------------------ the geometric path
class _Path:
    """Piecewise cubic q(s) = c0 + c1 τ + c2 τ² + c3 τ³ (τ = s − s_k on [s_k, s_{k+1}]), (B, N−1, n)."""

    def __init__(self, s: Tensor, y: Tensor, interpolation: str, bc: str):
        self.s = s
        self.end = y[:, -1]  # returned exactly at s >= s_N
        h = (s[:, 1:] - s[:, :-1])[..., None]
        if interpolation == "linear":
            d = (y[:, 1:] - y[:, :-1]) / h
            zero = torch.zeros_like(d)
            self.c = (y[:, :-1], d, zero, zero)
        else:
            m = spline_slopes(s, y, bc)  # the spline as Hermite cubics of its knot slopes
            self.c = tuple(cubic_coeffs(y[:, :-1], y[:, 1:], m[:, :-1], m[:, 1:], h))

    def rows(self, r: Tensor) -> _Path:
        """The paths of the rows ``r`` (an index tensor)."""
        sub = object.__new__(_Path)
        sub.s, sub.end, sub.c = self.s[r], self.end[r], tuple(c[r] for c in self.c)
        return sub

    def segment(self, s: Tensor) -> Tensor:
        """Segment index (B, T) of path parameters s (B, T) (clamped into the path)."""
        inner = self.s[:, 1:-1].contiguous()
        return torch.searchsorted(inner, s.contiguous(), right=True)

    def eval(self, s: Tensor, k: Tensor | None = None, rows: Tensor | None = None, position_only: bool = False
             ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """q, q', q'', q''' (B, T, n) at s (B, T) (segment k (B, T) if given: the right-hand derivatives at a
        knot are those of the segment that starts there); ``rows`` (B, T): the path of each sample (else
        row b of s is path b); ``position_only``: q alone (the derivatives None)."""
        if rows is None:
            k = self.segment(s) if k is None else k
            tau = (s - torch.gather(self.s, 1, k))[..., None]
            idx = k[..., None].expand(*k.shape, self.c[0].shape[-1])
            coeffs = [torch.gather(c, 1, idx) for c in self.c]
            last, end = self.s[:, -1:], self.end[:, None]
        else:
            k = _search_rows(self.s[:, 1:-1], rows, s) if k is None else k
            tau = (s - self.s[rows, k])[..., None]
            coeffs = [c[rows, k] for c in self.c]
            last, end = self.s[rows, -1], self.end[rows]
        q, q1, q2 = poly_eval(coeffs, tau, position_only)
        q = torch.where((s >= last)[..., None], end, q)
        return q, q1, q2, None if position_only else 6 * coeffs[3]


# ------------------------------------------------------------------------------------ TOPP-RA on a grid
def _rows(P1, P2, Q1, Q2, a, delta):
    """The acceleration constraints α u + β x ≤ γ of grid intervals (leading dims (...) of ``delta``), at
    the interval's start (P) and, with x + 2Δu, at its end (Q: toppra's interpolation scheme), as their
    upper rows (each (..., 2n)): |α|, β of the row of each ± pair with α > 0 (the lower row is −β), γ; and
    the bound on x of the rows without u (α = 0: |β| x ≤ γ), (...)."""
    A = Q1 + 2 * delta[..., None] * Q2
    al = torch.cat((P1.abs(), A.abs()), -1)
    be = torch.cat((torch.where(P1 < 0, -P2, P2), torch.where(A < 0, -Q2, Q2)), -1)
    ga = torch.cat((a, a), -1)
    alone = (al == 0) & (be != 0)
    return al, be, ga, torch.where(alone, ga / torch.where(alone, be.abs(), 1.0), math.inf).amin(-1)


def _lower(al, be, ga, delta):
    """The lower rows (α < 0) as −α, β, γ (each (..., 2n + 1)): the acceleration rows' partners and
    u ≥ −x / 2Δ (the next x ≥ 0); a row with −α = 0 is none."""
    d2 = 2 * delta[..., None]
    return (torch.cat((al, d2), -1), torch.cat((-be, -torch.ones_like(d2)), -1),
            torch.cat((ga, torch.zeros_like(d2)), -1))


def _max_x(al: Tensor, be: Tensor, ga: Tensor, alone: Tensor, delta: Tensor, xv: Tensor) -> Tensor:
    """max x (...) such that some u meets the rows of :func:`_rows` and :func:`_lower` and x ≤ xv, exactly
    (Fourier–Motzkin on u: every pair of an upper row (α > 0) and a lower row (α < 0) bounds x linearly).
    x = 0 is always feasible, and the feasible x form an interval, so the answer is the smallest upper
    bound (clamped into [0, xv])."""
    up = al > 0
    Ap = torch.where(up, al, 0.0)
    Aq, bq, gq = _lower(Ap, be, ga, delta)
    dn = Aq > 0
    c = Ap[..., :, None] * bq[..., None, :] + Aq[..., None, :] * be[..., :, None]  # (..., R_p, R_q)
    d = Aq[..., None, :] * ga[..., :, None] + Ap[..., :, None] * gq[..., None, :]
    pair = up[..., :, None] & dn[..., None, :] & (c > 0)
    bound = torch.where(pair, d / torch.where(pair, c, 1.0), math.inf).flatten(-2).amin(-1)
    return torch.minimum(torch.minimum(bound, alone).clamp_min(0), xv)


def _topp(path: _Path, grid: Tensor, kseg: Tensor, vmax: Tensor, amax: Tensor, stops: Tensor) -> Tensor:
    """x = ṡ² (B, M) at the grid points (B, M); ``stops`` (B, M) bool: grid points where ṡ = 0.

    Every constraint row but one (2Δ u + x ≤ x_next, the next controllable set) is fixed before the
    recursion, so the bounds from all the pairs of fixed rows are computed for all intervals at once (in
    chunks of bounded memory); the backward and forward passes then meet only the moving row."""
    slopes = native.topp_slopes(path.s, path.c, grid, kseg)  # in C on the CPU: the same floats
    if slopes is not None:
        P1, P2, Q1, Q2 = slopes
    else:
        _, P1, P2, _ = path.eval(grid, kseg)  # (B, M, n), right-hand at knots
        _, Q1, Q2, _ = path.eval(grid[:, 1:], kseg[:, :-1])  # interval ends, left-hand
    delta = grid[:, 1:] - grid[:, :-1]
    B, M = grid.shape
    x = native.topp_grid(P1, P2, Q1, Q2, amax, vmax, delta, stops, _X_BIG)  # all below in C: the same floats
    if x is not None:
        return x
    absP1 = P1.abs()
    xv = torch.where(absP1 > 0, (vmax[:, None] / absP1.clamp_min(1e-300)) ** 2, _X_BIG).amin(-1)
    xv = torch.where(stops, 0.0, xv.clamp_max(_X_BIG))
    absQ1 = Q1.abs()
    xq = torch.where(absQ1 > 0, (vmax[:, None] / absQ1.clamp_min(1e-300)) ** 2, _X_BIG).amin(-1)
    n = P1.shape[-1]
    al, be, ga, alone = _rows(P1[:, :-1], P2[:, :-1], Q1, Q2, amax[:, None].expand(B, M - 1, n), delta)
    # the bound from the fixed rows, per interval (B, M - 1)
    step = max(1, (1 << 22) // max(1, B * 2 * n * (2 * n + 1)))
    parts = (al, be, ga, alone, delta, xv[:, :-1])
    fixed = torch.cat([_max_x(*(v[:, j:j + step] for v in parts)) for j in range(0, M - 1, step)], 1)
    # the moving row (α, β, γ) = (2Δ, 1, x_next) with each lower row q:
    # x ≤ (A_q x_next + 2Δ γ_q) / c_q, A_q = −α_q, c_q = 2Δ β_q + A_q (the pair term of _max_x)
    up = al > 0
    Aq, bq, gq = _lower(torch.where(up, al, 0.0), be, ga, delta)
    d2 = (2 * delta)[..., None]
    c = d2 * bq + Aq
    pair = (Aq > 0) & (c > 0)
    Aq = torch.where(pair, Aq, 0.0)
    G = torch.where(pair, d2 * gq, math.inf)
    C = torch.where(pair, c, 1.0)
    # the fixed upper rows for u at x: u ≤ (γ − β x) / α
    Au, Bu, Gu = torch.where(up, al, 1.0), torch.where(up, be, 0.0), torch.where(up, ga, math.inf)
    two_delta = 2 * delta
    # the passes below run one grid point at a time: the per-point columns are taken once (unbind) and kept
    # as (B, 1), so each step is a few small ops (these loops are most of the time of a short batch)
    col = lambda v: v.unbind(1)  # noqa: E731
    Aq, G, C, Au, Bu, Gu = col(Aq), col(G), col(C), col(Au), col(Bu), col(Gu)
    fixed, xq, d2 = col(fixed[..., None]), col(xq[..., None]), col(two_delta[..., None])
    K = [torch.zeros_like(xv[:, :1])] * M  # the controllable ṡ² bound per grid point
    K_next = [None] * (M - 1)
    for i in range(M - 2, -1, -1):
        kn = torch.minimum(K[i + 1], xq[i])
        K_next[i] = kn
        moving = ((Aq[i] * kn + G[i]) / C[i]).amin(1, keepdim=True)
        K[i] = torch.minimum(fixed[i], moving.clamp_min(0))
    x = [torch.zeros_like(K[0])]
    for i in range(M - 1):
        xi = torch.minimum(x[i], K[i])
        x[i] = xi
        d = d2[i]
        u = torch.minimum(((Gu[i] - Bu[i] * xi) / Au[i]).amin(1, keepdim=True), (K_next[i] - xi) / d)
        u = u.clamp(min=-xi / d)
        x.append((xi + d * u).clamp(min=0).minimum(K[i + 1]))
    return torch.cat(x, 1)


# ------------------------------------------------------------------------------------ the timed result
class TimedPath:
    """A path with its time law: ``duration (B,)``, :meth:`sample` (q, q̇, q̈), :meth:`jerk`, :meth:`at_rate`.

    Times past the duration hold the last waypoint at rest; times before 0 the first.
    """

    def __init__(self, path: _Path, grid: Tensor, x: Tensor, tau: Tensor, k: Tensor, dtype: torch.dtype):
        self._path, self._grid, self._x, self._dtype = path, grid, x, dtype
        self._B, self._device, self._batch = grid.shape[0], grid.device, (grid.shape[0],)
        sd = x.clamp_min(0).sqrt()
        delta = grid[:, 1:] - grid[:, :-1]
        dt = 2 * delta / (sd[:, 1:] + sd[:, :-1]).clamp_min(1e-300)
        self._u = (x[:, 1:] - x[:, :-1]) / (2 * delta)  # s̈ per interval
        self._sd = sd
        self._t = torch.cat((torch.zeros_like(dt[:, :1]), dt.cumsum(1)), 1)  # (B, M) profile knot times
        # ∫ s dt at the knots (for the moving average)
        inc = grid[:, :-1] * dt + sd[:, :-1] * dt**2 / 2 + self._u * dt**3 / 6
        self._S = torch.cat((torch.zeros_like(dt[:, :1]), inc.cumsum(1)), 1)
        self._law(tau, k)

    def _law(self, tau: Tensor, k: Tensor) -> None:
        """The smoothing width τ and the stretch k (B,) of the profile."""
        self._tau, self._k = tau, k
        self._duration = None  # made when read (the candidates' retimed profiles never read it)
        #: the geometric path's waypoints (B, N, n) and knots (B, N)
        self.knots = self._path.s.to(self._dtype)

    @property
    def duration(self) -> Tensor:
        """Seconds per path (B,) (the path's batch dims once returned by :func:`time_optimal`)."""
        if self._duration is None:
            self._duration = ((self._t[:, -1] + self._tau) * self._k).to(self._dtype)
        return self._duration

    @duration.setter
    def duration(self, value: Tensor) -> None:
        self._duration = value

    def _retimed(self, tau: Tensor, k: Tensor, rows: Tensor | None = None) -> TimedPath:
        """This profile with τ and k of the rows ``rows`` (an index tensor; all if None): the profile's
        arrays shared or indexed, not computed again (each row's are its own: the same floats)."""
        new = object.__new__(TimedPath)
        new.__dict__.update(self.__dict__)
        if rows is not None:
            new._path = self._path.rows(rows)
            for name in ("_grid", "_x", "_u", "_sd", "_t", "_S"):
                setattr(new, name, getattr(self, name)[rows])
            new._B = new._grid.shape[0]
            new._batch = (new._B,)
        new._law(tau, k)
        return new

    def _base(self, t: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """s, ṡ, s̈, ∫s of the unsmoothed profile at times t (B, T) (any real t; ``rows`` (B, T): the
        path of each sample, else row b of t is path b)."""
        if rows is None:
            T_end = self._t[:, -1:]
            tc = t.clamp(min=0).minimum(T_end)
            i = torch.searchsorted(self._t[:, 1:-1].contiguous(), tc.contiguous(), right=True)
            g = lambda v: torch.gather(v, 1, i)  # noqa: E731
        else:
            T_end = self._t[rows, -1]
            tc = t.clamp(min=0).minimum(T_end)
            i = _search_rows(self._t[:, 1:-1], rows, tc)
            g = lambda v: v[rows, i]  # noqa: E731
        d = tc - g(self._t)
        s0, v0, u = g(self._grid), g(self._sd), g(self._u)
        s = s0 + v0 * d + u * d**2 / 2
        S = g(self._S) + s0 * d + v0 * d**2 / 2 + u * d**3 / 6
        inside = (t >= 0) & (t <= T_end)
        S = torch.where(t > T_end, S + (t - T_end) * s, torch.where(t < 0, torch.zeros_like(S), S))
        v = torch.where(inside, v0 + u * d, torch.zeros_like(s))
        a = torch.where(inside & (t < T_end), u, torch.zeros_like(s))
        return s, v, a, S

    def _profile(self, t: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """s, ṡ, s̈, s⃛ of the (smoothed, unscaled) profile at times t (B, T) (``rows``: :meth:`_base`)."""
        tau = self._tau[:, None] if rows is None else self._tau[rows]
        s, v, a, S = self._base(t, rows)
        smooth = tau > 0
        taus = torch.where(smooth, tau, torch.ones_like(tau))
        s2, v2, a2, S2 = self._base(t - taus, rows)
        sb = torch.where(smooth, (S - S2) / taus, s)
        vb = torch.where(smooth, (s - s2) / taus, v)
        ab = torch.where(smooth, (v - v2) / taus, a)
        jb = torch.where(smooth, (a - a2) / taus, torch.zeros_like(a))
        done = t >= (self._t[:, -1:] if rows is None else self._t[rows, -1]) + tau  # at the end, at rest
        zero = torch.zeros_like(sb)
        return (torch.where(done, torch.ones_like(sb), sb), torch.where(done, zero, vb),
                torch.where(done, zero, ab), torch.where(done, zero, jb))

    def _joint(self, t: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """q, q̇, q̈, q⃛ (B, T, n) at real times t (B, T), float64 (``rows`` (B, T): the path of each
        sample, else row b of t is path b)."""
        k = self._k[:, None] if rows is None else self._k[rows]
        s, v, a, j = self._profile(t / k, rows)
        v, a, j = v / k, a / k**2, j / k**3
        s = s.clamp(min=0, max=1)
        q, q1, q2, q3 = self._path.eval(s, rows=rows)
        v, a, j = v[..., None], a[..., None], j[..., None]
        return q, q1 * v, q1 * a + q2 * v**2, q1 * j + 3 * q2 * v * a + q3 * v**3

    def _times(self, t) -> Tensor:
        B, batch = self._B, self._batch
        t = tensors(("t", t, None), like=torch.empty(0, dtype=self._dtype, device=self._device))[0]
        t = t.to(torch.float64)
        if t.ndim == 0:
            t = t.reshape(1)
        if t.ndim == 1:
            return t.expand(B, -1)
        if tuple(t.shape[:-1]) != tuple(batch):
            raise ShapeError(f"expected t of shape (T,) or {shape_str((*batch, 'T'))}, "
                             f"got {shape_str(t.shape)}")
        return t.reshape(B, t.shape[-1])

    def _out(self, x: Tensor) -> Tensor:
        return x.reshape(*self._batch, *x.shape[1:]).to(self._dtype)

    def sample(self, t) -> Trajectory:
        """q, q̇, q̈ ``(..., T, n)`` at times ``t`` ``(T,)`` or ``(..., T)`` [s] (the path's dtype)."""
        return self._sample(self._times(t))

    def _sample(self, t: Tensor) -> Trajectory:
        """:meth:`sample` at float64 times (B, T), unchecked."""
        q, qd, qdd = self._state(t)
        return Trajectory(self._out(q), self._out(qd), self._out(qdd))

    def _state(self, t: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """q, q̇, q̈ of :meth:`_joint`: in C on the CPU (each sample one pass; the same floats), else
        :meth:`_joint`'s torch evaluation."""
        profile = (self._t, self._grid, self._sd, self._S, self._u)
        out = native.topp_sample(t, rows, profile, self._tau, self._k, self._path.s, self._path.c,
                                 self._path.end)
        return self._joint(t, rows)[:3] if out is None else out

    def jerk(self, t) -> Tensor:
        """q⃛ ``(..., T, n)`` at times ``t`` ``(T,)`` or ``(..., T)`` (piecewise continuous; 0 at rest)."""
        return self._out(self._joint(self._times(t))[3])

    def at_rate(self, dt: float) -> tuple[Tensor, Trajectory]:
        """Samples every ``dt`` seconds up to the longest duration: t ``(..., S)`` and q, q̇, q̈ ``(..., S, n)``
        (rows past their duration hold the end at rest). S = ceil(max duration / dt) + 1."""
        dt = check_number(dt, "dt", unit=" s")
        S = int(math.ceil(float(self.duration.max()) / dt - 1e-9)) + 1 if self.duration.numel() else 1
        t = torch.arange(S, dtype=torch.float64, device=self._device) * dt
        return t.to(self._dtype).expand(*self._batch, S), self._sample(t.expand(self._B, S))

    def _breakpoints(self, per_interval: int, skip: int = 0) -> Tensor:
        """Profile times (B, ·) for the limit check: the knots, the knots + τ, ``per_interval`` inside
        (``skip`` > 0: without the fractions j / per_interval with j a multiple of ``skip``, the samples of
        the check at ``per_interval / skip``: the same floats, j / per_interval = (j / skip) / (per_interval /
        skip) exactly for the powers of two used)."""
        f = torch.arange(per_interval + 1, dtype=torch.float64, device=self._t.device)
        f = (f[f.remainder(skip) != 0] if skip else f) / per_interval
        t0, dt = self._t[:, :-1, None], (self._t[:, 1:] - self._t[:, :-1])[..., None]
        inner = (t0 + f * dt).flatten(1)
        out = torch.cat((inner, inner + self._tau[:, None]), 1)
        if skip == 0 and self._path.s.shape[1] > 2:  # (with skip: in the coarser check's samples already)
            out = torch.cat((out, self._knot_samples(_KNOT_SAMPLES)), 1)
        return out

    def _knot_samples(self, m: int) -> Tensor:
        """Times (B, K (m + 1)): m + 1 equally spaced over [t_k, t_(k+1) + τ] for the K = min(N − 1,
        :data:`_SHORT_INTERVALS`) knot intervals [s_k, s_(k+1)] of each path that the unsmoothed profile
        crosses fastest (t_k: when it reaches knot k, a grid point). The smoothed s̄(t), the mean of s over
        [t − τ, t], is in [s_k, s_(k+1)] only within [t_k, t_(k+1) + τ]. A knot interval crossed in much less
        than τ (two waypoints close together: a sharp turn of the spline, its third derivative large) can
        fall between two of the grid's check samples, which the smoothing moved off its times; its jerk is
        sampled here."""
        knots = self._path.s.to(torch.float64)  # (B, N)
        i = torch.searchsorted(self._grid.contiguous(), knots.contiguous()).clamp(max=self._grid.shape[1] - 1)
        tk = self._t.gather(1, i)  # the knots are grid points (time_optimal's grid)
        span = tk[:, 1:] - tk[:, :-1]  # (B, N - 1)
        K = min(span.shape[1], _SHORT_INTERVALS)
        k = span.topk(K, dim=1, largest=False).indices
        t0, t1 = tk[:, :-1].gather(1, k), tk[:, 1:].gather(1, k) + self._tau[:, None]
        f = torch.arange(m + 1, dtype=torch.float64, device=knots.device) / m
        return (t0[..., None] + f * (t1 - t0)[..., None]).flatten(1)


class _Chained(TimedPath):
    """Rest-to-rest straight segments played one after another: the polyline with a jerk limit (each
    segment smoothed on its own, so the motion stops at every corner with zero acceleration)."""

    def __init__(self, parts: TimedPath, B: int, K: int, dtype: torch.dtype):
        self._parts, self._K, self._dtype = parts, K, dtype
        self._B, self._device, self._batch = B, parts._device, (B,)
        d = parts.duration.to(torch.float64).view(B, K)
        self._start = torch.cat((torch.zeros_like(d[:, :1]), d.cumsum(1)[:, :-1]), 1)  # (B, K)
        self.duration = d.sum(1).to(dtype)
        self.knots = None

    def _own_part(self, t: Tensor, rows: Tensor | None) -> tuple[Tensor, Tensor]:
        """Each sample's time in its own part and that part's row of ``_parts``: the last part that starts
        at or before it (a part rests outside its own time span, so the others would add nothing)."""
        B, K = t.shape[0], self._K
        if rows is None:
            chain = torch.arange(B, device=t.device)[:, None]
            seg = torch.searchsorted(self._start[:, 1:].contiguous(), t.contiguous(), right=True)  # (B, T)
        else:
            chain, seg = rows, _search_rows(self._start[:, 1:], rows, t)
        return t - self._start[chain, seg], chain * K + seg

    def _joint(self, t: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return self._parts._joint(*self._own_part(t, rows))

    def _state(self, t: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        return self._parts._state(*self._own_part(t, rows))


def _peaks(timed: TimedPath, t: Tensor, limits: list[Tensor]) -> Tensor:
    """The largest |q̇| / v, |q̈| / a (and |q⃛| / j with a jerk limit) of each row over the profile times t
    (B, T): (B, 2 or 3). The samples go in column blocks of about :data:`_BLOCK` samples in all, so the
    (B, ·, n) temporaries stay small (a whole check at once allocates and faults in hundreds of MB)."""
    B, T = t.shape
    # in C on the CPU (each sample one pass, no temporaries): the same floats
    peak = native.topp_peaks(t, (timed._t, timed._grid, timed._sd, timed._S, timed._u), timed._tau, timed._k,
                             timed._path.s, timed._path.c, limits)
    if peak is not None:
        return peak
    w = max(64, _BLOCK // max(B, 1))
    peak = None
    for c in range(0, T, w):
        q_dots = timed._joint(t[:, c:c + w])[1:]
        r = torch.stack([(qd.abs() / lim[:, None]).amax((1, 2)) for qd, lim in zip(q_dots, limits)], 1)
        peak = r if peak is None else torch.maximum(peak, r)
    return peak


def _cube_root(x: Tensor) -> Tensor:
    """x^(1/3) of each entry of ``x (R,)`` by the C library's pow, one entry at a time. torch's pow can differ
    in the last bit between its vectorised loop and its scalar one, which it picks by the tensor's size,
    layout and an entry's place in it: a row's stretch k (and duration) would then depend on the rows it is
    checked with (a pruned dense check of some rows against one of every row, a plan alone against its row in
    a batch)."""
    return torch.tensor([v ** (1 / 3) for v in x.tolist()], dtype=x.dtype, device=x.device)


def unit_knots(knots: Tensor) -> Tensor:
    """Knots ``(B, N)`` brought to run from 0 to 1 (the same path: s is normalised), float64."""
    s = knots.to(torch.float64)
    return (s - s[:, :1]) / (s[:, -1:] - s[:, :1])


def _check_limit(x: Tensor, batch: tuple, n: int, name: str) -> Tensor:
    """A limit given as a number, ``(n,)`` or ``(..., n)`` broadcasting to the path's batch -> (B, n)."""
    try:
        x = torch.broadcast_to(x, (*batch, n))
    except RuntimeError:
        raise ShapeError(f"expected {name} as a number, ({n},) or {shape_str((*batch, n))}, "
                         f"got {shape_str(x.shape)}") from None
    if bool((x <= 0).any()):
        raise InfeasibleTrajectoryError(f"{name} must be > 0 everywhere (no motion is possible otherwise)")
    return x.reshape(-1, n).to(torch.float64)


def time_optimal(path, velocity_limit, acceleration_limit, jerk_limit=None, *, knots=None,
                 interpolation: str = "spline", bc: str = "not-a-knot", grid_per_segment: int | None = None,
                 check_per_interval: int = CHECK_PER_INTERVAL) -> TimedPath:
    """Time-optimal timing of the path through ``path``'s waypoints (module docstring: TOPP-RA, then an
    optional jerk smoothing and an exact limit stretch).

    Args:
        path: waypoints ``(B, N, n)`` (any leading batch dims ``(..., N, n)``, ``()`` included), N >= 2.
        velocity_limit / acceleration_limit: q̇_max / q̈_max > 0: a number, ``(n,)`` or ``(B, n)`` (leading
            dims broadcasting to the path's).
        jerk_limit: q⃛_max > 0 (same shapes) or None (bang-bang acceleration).
        knots: path parameters of the waypoints ``(N,)`` or ``(B, N)`` (the path's batch dims), strictly
            increasing (default
            ``linspace(0, 1, N)``); the path is the same whatever their scale (s is normalised to [0, 1]),
            but the spline's shape depends on their spacing.
        interpolation: ``"spline"`` (scipy's / toppra's cubic spline with boundary condition ``bc``,
            ``"not-a-knot"`` or ``"clamped"``) or ``"linear"`` (the polyline, stopping at each waypoint).
        grid_per_segment: TOPP grid intervals per waypoint interval (default: about 512 in all, at least 2).
        check_per_interval: samples per profile interval for the final limit stretch.

    Returns:
        :class:`TimedPath` (``duration (B,)``, ``sample(t)``, ``jerk(t)``, ``at_rate(dt)``), batch dims as
        the path's.
    """
    if interpolation not in ("spline", "linear"):
        raise ConventionError(f"time_optimal: interpolation is 'spline' or 'linear', got {interpolation!r}")
    if bc not in ("not-a-knot", "clamped"):
        raise ConventionError(f"time_optimal: bc is 'not-a-knot' or 'clamped', got {bc!r}")
    path, vmax, amax, jmax, knots = tensors(
        ("path", path, (None, None)), ("velocity_limit", velocity_limit, None),
        ("acceleration_limit", acceleration_limit, None), ("jerk_limit", jerk_limit, None),
        ("knots", knots, None))
    dtype = path.dtype
    if path.ndim < 2 or path.shape[-2] < 2:
        raise ShapeError(f"expected path of shape (..., N, n) with N >= 2, got {shape_str(path.shape)}")
    batch, (N, n) = tuple(path.shape[:-2]), path.shape[-2:]
    check_count(check_per_interval, "check_per_interval")
    with torch.no_grad():
        y = path.detach().to(torch.float64).reshape(-1, N, n)
        B = y.shape[0]
        vmax = _check_limit(vmax, batch, n, "velocity_limit")
        amax = _check_limit(amax, batch, n, "acceleration_limit")
        jmax = None if jmax is None else _check_limit(jmax, batch, n, "jerk_limit")
        if knots is None:
            s = torch.linspace(0, 1, N, dtype=torch.float64, device=y.device).expand(B, N)
        else:
            s = knots.detach().to(torch.float64)
            if s.ndim and s.shape[-1] == N and tuple(s.shape[:-1]) in ((), batch):
                s = s.expand(*batch, N).reshape(B, N)
            else:
                raise ShapeError(f"expected knots of shape ({N},) or {shape_str((*batch, N))}, "
                                 f"got {shape_str(knots.shape)}")
            if bool((s[:, 1:] <= s[:, :-1]).any()):
                raise ConventionError("time_optimal: knots must be strictly increasing")
        s = unit_knots(s)
        timed = _timed(y, s, vmax, amax, jmax, interpolation, bc, grid_per_segment, check_per_interval, dtype)
        return _batched(timed, batch)


def _timed(y: Tensor, s: Tensor, vmax: Tensor, amax: Tensor, jmax: Tensor | None, interpolation: str, bc: str,
           grid_per_segment: int | None, check_per_interval: int, dtype: torch.dtype,
           path: _Path | None = None) -> TimedPath:
    """:func:`time_optimal` of checked arguments, without grad: the waypoints ``y (B, N, n)`` and their
    normalised knots ``s (B, N)`` (from 0 to 1, strictly increasing), float64 limits ``(B, n)`` (``jmax``
    None: no jerk limit), ``dtype`` the result's; ``path``: the :class:`_Path` of ``y`` at ``s`` with
    ``interpolation`` and ``bc`` where the caller has it already (:func:`diffkin.motion.plan`'s checked
    spline). The result is batched as ``(B,)``."""
    B, N, n = y.shape
    if interpolation == "linear" and jmax is not None and N > 2:  # each segment rest to rest
        K = N - 1
        seg = torch.stack((y[:, :-1], y[:, 1:]), 2).reshape(B * K, 2, n)
        rep = lambda x: x.repeat_interleave(K, 0)  # noqa: E731
        m = grid_per_segment if grid_per_segment is not None else max(2, -(-512 // K))
        unit = torch.tensor([0.0, 1.0], dtype=torch.float64, device=y.device).expand(B * K, 2)
        parts = _timed(seg, unit, rep(vmax), rep(amax), rep(jmax), "linear", bc, m, check_per_interval,
                       torch.float64)  # the parts in float64 whatever the result's dtype (_Chained adds them)
        return _Chained(parts, B, K, dtype)
    p = _Path(s.contiguous(), y, interpolation, bc) if path is None else path
    m = grid_per_segment if grid_per_segment is not None else max(2, -(-512 // (N - 1)))
    check_count(m, "grid_per_segment", 2 if interpolation == "linear" else 1)
    f = torch.arange(m, dtype=torch.float64, device=y.device) / m
    grid = torch.cat(((s[:, :-1, None] + f * (s[:, 1:] - s[:, :-1])[..., None]).flatten(1), s[:, -1:]), 1)
    seg = torch.arange(N - 1, device=y.device).repeat_interleave(m)
    kseg = torch.cat((seg, seg[-1:])).expand(B, -1).contiguous()
    stops = torch.zeros_like(grid, dtype=torch.bool)
    if interpolation == "linear":
        stops[:, m:-1:m] = True
    x = _topp(p, grid, kseg, vmax, amax, stops)
    if jmax is None:
        taus = [torch.zeros(B, dtype=torch.float64, device=y.device)]
    else:
        base = 2 * (amax / jmax).amax(1)
        taus = [c * base for c in (0.25, 0.5, 1.0, 2.0)]
    limits = [vmax, amax] if jmax is None else [vmax, amax, jmax]

    profile = TimedPath(p, grid, x, taus[0], torch.ones_like(taus[0]), dtype)  # made once, retimed below

    def stretch(tau: Tensor, per_interval: int, r: Tensor | None = None, skip: int = 0,
                prior: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """k, the duration and the peaks (:func:`_peaks`) of the profile smoothed by τ, checked at
        ``per_interval``, of the rows ``r`` (all if None; τ of those rows); ``prior``: the peaks of the
        samples left out by ``skip`` (:meth:`TimedPath._breakpoints`)."""
        timed = profile._retimed(tau, torch.ones_like(tau), r)
        lim = limits if r is None else [v[r] for v in limits]
        peak = _peaks(timed, timed._breakpoints(per_interval, skip), lim)
        peak = peak if prior is None else torch.maximum(peak, prior)
        k = torch.maximum(peak[:, 0], peak[:, 1].sqrt())
        if jmax is not None:
            k = torch.maximum(k, _cube_root(peak[:, 2]))
        k = k.clamp_min(1) * (1 + _STRETCH)
        return k, (timed._t[:, -1] + tau) * k, peak

    taus = torch.stack(taus, 1)  # (B, C) candidates, the shortest wins (the first of equals)
    B, C = taus.shape
    # Pruning, exact: the check at one in `coarse` of the samples (a subset of the dense samples, the same
    # floats) gives a lower bound on each candidate's duration; the candidates are checked densely in
    # the order of their bounds until no row's next bound can beat its best.
    coarse = math.gcd(check_per_interval, _COARSE)
    prune = C > 1 and coarse > 1
    # A dense check then only evaluates the samples the coarse check left out (the peaks of the union
    # are the larger of both), and only on the rows where its candidate can still win (its duration is
    # at least its bound, so elsewhere it cannot): the same result as checking every row densely.
    if prune:
        if B * C <= _ONE_CHECK:  # every candidate of every row in one check (row b's: rows b C ..)
            every = torch.arange(B, device=taus.device).repeat_interleave(C)
            _, lower, peaks = stretch(taus.reshape(-1), check_per_interval // coarse, every)
            lower, peaks = lower.view(B, C), peaks.view(B, C, -1)  # (B, C), (B, C, 2 or 3)
        else:  # a check per candidate, the profile shared (C copies of it: C times the memory)
            checks = [stretch(taus[:, c], check_per_interval // coarse) for c in range(C)]
            lower = torch.stack([q[1] for q in checks], 1)
            peaks = torch.stack([q[2] for q in checks], 1)  # (B, C, 2 or 3)
        order = lower.argsort(dim=1, stable=True)
        lower = lower.gather(1, order)
    else:
        order = torch.arange(C, device=taus.device).expand(B, C)
    def beats(total: Tensor, c: Tensor, best: tuple) -> Tensor:
        return (total < best[2]) | ((total == best[2]) & (c < best[3]))

    best = None
    for r in range(C):
        c = order[:, r]
        tau = taus.gather(1, c[:, None])[:, 0]
        skip, prior = (coarse, peaks.gather(1, c[:, None, None].expand(-1, 1, peaks.shape[-1]))[:, 0]) \
            if prune else (0, None)
        if prune and best is not None:
            maybe = beats(lower[:, r], c, best)
            if not bool(maybe.any()):
                break  # the later bounds are larger still
            rows = maybe.nonzero()[:, 0]
            k_r, total_r, _ = stretch(tau[rows], check_per_interval, rows, skip, prior[rows])
            k, total = best[1].index_put((rows,), k_r), best[2].index_put((rows,), total_r)
            better = maybe & beats(total, c, best)
        else:
            k, total, _ = stretch(tau, check_per_interval, None, skip, prior)
            better = None if best is None else beats(total, c, best)
        if best is None:
            best = (tau, k, total, c)
        else:
            best = tuple(torch.where(better, new, old) for new, old in zip((tau, k, total, c), best))
    return profile._retimed(best[0], best[1])


def _batched(timed: TimedPath, batch: tuple) -> TimedPath:
    """The result with the path's leading batch dims (``duration``, ``sample``, ``jerk``, ``at_rate``)."""
    timed._batch = batch
    timed.duration = timed.duration.reshape(batch)
    return timed
