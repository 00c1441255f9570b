"""The geometric path of a plan: chord-length knots through waypoints and the continuous check of the
clamped cubic spline through them (the path :func:`~diffkin.trajectories.time_optimal` times), shared by
:func:`~diffkin.motion.plan` and its optimisation stage (:mod:`diffkin.motion.optimize`)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..kernels import native
from ..trajectories.time_optimal import _BLOCK, _Path, _search_rows, unit_knots
from ._edges import SPACING, EdgeChecker

#: the most fine samples per row of the spline check (a row needing more, a very fine resolution on a
#: long path, is not proven: its polyline is timed instead)
_FINE_MAX = 1 << 20

__all__ = ["_knots", "_spline", "_spline_clear", "_spline_failures"]


def _knots(path: Tensor) -> Tensor:
    """Chord-length knots (B, L), float64, strictly increasing (in float32, 1e-9 added to a zero chord would
    vanish in the sum: two equal knots)."""
    path = path.to(torch.float64)
    seg = (path[:, 1:] - path[:, :-1]).norm(dim=-1) + 1e-9
    return torch.cat((torch.zeros_like(seg[:, :1]), seg.cumsum(1)), 1)


def _spline(path: Tensor, knots: Tensor) -> _Path:
    """The clamped cubic spline through ``path (B, L, nq)`` at ``knots (B, L)`` (normalised to [0, 1]),
    float64: the geometric path :func:`~diffkin.trajectories.time_optimal` times."""
    return _Path(unit_knots(knots).contiguous(), path.to(torch.float64), "spline", "clamped")


def _spline_clear(checker: EdgeChecker, path: Tensor, knots: Tensor, lo: Tensor, hi: Tensor, problem: Tensor,
                  fine: int = 4096) -> Tensor:
    """(B,) bool: the clamped cubic spline through ``path`` is proven clear and within the limits
    (:func:`_spline_failures`, which says where it is not)."""
    return ~_spline_failures(checker, path, knots, lo, hi, problem, fine).any(1)


def _spline_failures(checker: EdgeChecker, path: Tensor, knots: Tensor, lo: Tensor, hi: Tensor,
                     problem: Tensor, fine: int = 4096, spline: _Path | None = None) -> Tensor:
    """(B, L − 1) bool: the knot intervals where the clamped cubic spline through ``path`` (B, L, nq) at
    ``knots`` (B, L) — the geometric path :func:`~diffkin.trajectories.time_optimal` times — is *not* proven
    clear or within the joint limits ``lo``, ``hi`` (nq,) (all False: the whole spline is; a cubic
    overshoots its waypoints: the limits checked on the ``fine`` samples, whose spacing leaves at most the
    spline's curvature times (1/fine)² between them). Its bound-length
    Σ_j R_j ∫|q'_j| ds is measured on ``fine`` chords per row and the spline checked wherever that length
    crosses a multiple of min(0.8 · 2 η_b, 0.95 · 2 η_b − the row's longest fine chord) (η_b each
    problem's resolution, 2 the subdivision's :data:`~diffkin.motion._edges.SPACING`; each check point is
    the first fine sample past its mark, so two are at most that plus one chord apart; 5 % is left for
    chords against arcs; a row where that leaves less than 0.2 · 2 η_b is checked again with finer
    samples, up to :data:`_FINE_MAX`, else not proven). The samples and check points in C on
    the CPU (``kernels/_native_spline.c``, the same floats), else in torch. ``spline``: :func:`_spline` of
    ``path`` and ``knots`` where the caller has it already."""
    B = path.shape[0]
    p = _spline(path, knots) if spline is None else spline
    s = p.s
    u = torch.linspace(0, 1, fine + 1, dtype=torch.float64, device=path.device).expand(B, -1).contiguous()
    lo, hi, reach = lo.to(torch.float64), hi.to(torch.float64), checker.reach.to(torch.float64)
    fine_c = native.spline_fine(u[0], p.s, p.c, p.end, lo, hi, reach)  # in C on the CPU: the same floats
    if fine_c is not None:
        cum, inside = fine_c
    else:
        # the fine samples in column blocks (each overlapping the next by one sample for its chord): the
        # (B, ·, nq) positions of all of them at once would be hundreds of MB for a large batch
        w = max(64, _BLOCK // max(B, 1))
        inside, chords = torch.ones(B, dtype=torch.bool, device=path.device), []
        for c in range(0, fine, w):
            q = p.eval(u[:, c:c + w + 1], position_only=True)[0]
            inside &= ((q >= lo) & (q <= hi)).all(-1).all(-1)
            d = (q[:, 1:] - q[:, :-1]).abs() * reach
            chords.append(sum(d.unbind(-1)))  # the joints in order, first to last (as the C code)
        chord = torch.cat(chords, 1)
        cum = torch.cat((torch.zeros_like(chord[:, :1]), chord.cumsum(1)), 1)  # (B, fine + 1)
    # the marks' spacing per problem: each check point is the first fine sample at or past its mark, so two
    # of them can be a mark's spacing plus one fine chord apart; rows whose longest chord leaves less than a
    # fifth of the step (a very fine resolution on a long path) are checked again with finer samples
    step = SPACING * checker.eta_of(problem).to(torch.float64)  # (B,): the bound-length between samples
    longest = (cum[:, 1:] - cum[:, :-1]).amax(1) if fine else torch.zeros_like(step)
    c = torch.minimum(0.8 * step, 0.95 * step - longest)  # 5 % left for chords against arcs
    coarse = c < 0.2 * step
    c = torch.where(coarse, 0.8 * step, c)
    n = torch.where(coarse, 1, torch.ceil(cum[:, -1] / c).long().clamp(min=1))  # (coarse: failed below)
    # each row's own n + 1 marks only, flat (padding every row to the longest row's count multiplied the
    # evaluations and collision checks: a row's marks past n would all be its end point, its mark n)
    rows = torch.repeat_interleave(torch.arange(B, device=path.device), n + 1)
    first = torch.cumsum(n + 1, 0) - (n + 1)
    qc = native.spline_marks(u[0], cum, c, n, first, p.s, p.c, p.end)  # in C on the CPU: the same floats
    if qc is None:
        marks = (torch.arange(rows.shape[0], device=path.device) - first[rows]).to(torch.float64) * c[rows]
        idx = _search_rows(cum, rows, marks, right=False).clamp(max=fine)
        qc = p.eval(u[0, idx], rows=rows, position_only=True)[0]  # the same floats as above
    ok = checker.clear(qc.to(path.dtype), problem[rows])
    # each failing mark blames the knot interval holding it (a mark on a knot: the interval it starts); its
    # fine sample found again for the failing marks only
    L = path.shape[1]
    bad = torch.zeros(B, L - 1, dtype=torch.bool, device=path.device)
    fail = (~ok).nonzero().flatten()
    if fail.numel():
        fr = rows[fail]
        fm = (fail - first[fr]).to(torch.float64) * c[fr]
        fidx = _search_rows(cum, fr, fm, right=False).clamp(max=fine)
        bad[fr, (_search_rows(s, fr, u[0, fidx]) - 1).clamp(0, L - 2)] = True
    if bool(coarse.any()):  # those rows again with finer samples (where that stays within _FINE_MAX)
        need = fine * torch.exp2(torch.ceil(torch.log2(longest / (0.15 * step))).clamp(min=1))  # (B,)
        bad[coarse & (need > _FINE_MAX)] = True
        r = (coarse & (need <= _FINE_MAX)).nonzero().flatten()
        if r.numel():
            finer = int(need[r].max())
            bad[r] = _spline_failures(checker, path[r], knots[r], lo, hi, problem[r], finer)
    out = (~inside).nonzero().flatten()  # rows beyond a limit somewhere: their samples evaluated again
    if out.numel():
        sub = _Path(s[out].contiguous(), path[out].to(torch.float64), "spline", "clamped")
        q = sub.eval(u[out], position_only=True)[0]
        ob, oi = (~((q >= lo) & (q <= hi))).any(-1).nonzero(as_tuple=True)  # NaN: outside, as for inside
        bad[out[ob], (_search_rows(s, out[ob], u[0, oi]) - 1).clamp(0, L - 2)] = True
        bad[out] |= ~bad[out].any(1, keepdim=True)  # never a row not inside without a failing interval
    return bad
