"""trajectories.time_optimal's fast paths against the plain evaluations they replace, to the last bit: the
chained (polyline + jerk) path sampled part by part against every part at every time, the pruned limit check
(coarse samples reused, dense checks on the rows that can still win) against every candidate checked
densely on every row, the per-sample row search against torch.searchsorted, Horner from the top coefficient
against Horner from zero."""

from __future__ import annotations

import pytest
import torch

from diffkin.trajectories import time_optimal
from diffkin.trajectories._common import poly_eval
from diffkin.trajectories.time_optimal import _STRETCH, TimedPath, _cube_root, _peaks, _search_rows

F64 = torch.float64
V = torch.tensor([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61], dtype=F64)
A = torch.tensor([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0], dtype=F64)


def _paths(seed: int, B: int, N: int):
    g = torch.Generator().manual_seed(seed)
    y = torch.cumsum(torch.rand(B, N, 7, generator=g, dtype=F64) - 0.5, 1) * 1.5
    gaps = torch.rand(B, N - 1, generator=g, dtype=F64) + 0.2
    return y, torch.cat((torch.zeros(B, 1, dtype=F64), gaps.cumsum(1)), 1), g


def test_chained_samples_each_part_only():
    y, kn, g = _paths(1, 5, 6)
    res = time_optimal(y, V, A, 100 * A, knots=kn, interpolation="linear")
    B, K = 5, 5
    t = torch.cat((torch.linspace(-0.2, float(res.duration.max()) + 0.2, 400, dtype=F64).expand(B, -1),
                   torch.rand(B, 100, generator=g, dtype=F64) * res.duration[:, None]), 1)
    t = torch.cat((t, res._start), 1)  # exactly at the part boundaries too
    # the plain evaluation: every part at every time (each rests outside its span), then the sample's part
    local = (t[:, None, :] - res._start[:, :, None]).reshape(B * K, -1)
    every = res._parts._joint(local)
    seg = torch.searchsorted(res._start[:, 1:].contiguous(), t.contiguous(), right=True)
    idx = seg[:, None, :, None].expand(B, 1, t.shape[1], 7)
    for x, ref in zip(res._joint(t), every):
        assert torch.equal(x, torch.gather(ref.view(B, K, -1, 7), 1, idx)[:, 0])


# (16, None, 10): a jerk limit 10x the acceleration's (the candidates' durations close): a later dense check
# runs on one of the 8 rows only
@pytest.mark.parametrize("per_interval, grid, jerk", [(16, None, 100), (8, None, 100), (6, None, 100),
                                                      (4, 3, 100), (16, None, 10)])
def test_pruned_limit_check_equals_every_candidate_checked_densely(per_interval, grid, jerk, monkeypatch):
    import sys

    mod = sys.modules["diffkin.trajectories.time_optimal"]
    rows, peaks = [], mod._peaks
    monkeypatch.setattr(mod, "_peaks", lambda timed, t, lim: rows.append(t.shape[0]) or peaks(timed, t, lim))
    y, kn, _ = _paths(2, 8, 5)
    J = jerk * A
    res = time_optimal(y, V, A, J, knots=kn, bc="clamped", check_per_interval=per_interval,
                       grid_per_segment=grid)
    # the coarse check of the 8 rows' 4 candidates in one call, then the dense checks
    assert rows[0] == 32 and rows[1] == 8
    if jerk == 10:  # the pruning's later branch ran: a dense check on some rows only
        assert len(rows) > 2 and all(0 < r < 8 for r in rows[2:])
    # every candidate τ on every row at every dense sample, the shortest (the first of equals) wins
    base = 2 * (A / J).amax()
    best_total, best_k = None, None
    for c in (0.25, 0.5, 1.0, 2.0):
        tau = torch.full((8,), c, dtype=F64) * base
        timed = TimedPath(res._path, res._grid, res._x, tau, torch.ones_like(tau), F64)
        _, qd, qdd, qddd = timed._joint(timed._breakpoints(per_interval))
        k = torch.maximum((qd.abs() / V).amax((1, 2)), (qdd.abs() / A).amax((1, 2)).sqrt())
        k = torch.maximum(k, _cube_root((qddd.abs() / J).amax((1, 2)))).clamp_min(1) * (1 + _STRETCH)
        total = (timed._t[:, -1] + tau) * k
        if best_total is None:
            best_total, best_k = total, k
        else:
            better = total < best_total
            best_total, best_k = torch.where(better, total, best_total), torch.where(better, k, best_k)
    assert torch.equal(res._k, best_k)
    assert torch.equal(res.duration, best_total)


def test_peaks_in_blocks_equal_one_block():
    y, kn, _ = _paths(3, 3, 4)
    res = time_optimal(y, V, A, 100 * A, knots=kn)
    t = res._breakpoints(16)
    _, qd, qdd, qddd = res._joint(t)
    lims = [V.expand(3, 7), A.expand(3, 7), 100 * A.expand(3, 7)]
    ref = torch.stack([(x.abs() / lim[:, None]).amax((1, 2)) for x, lim in zip((qd, qdd, qddd), lims)], 1)
    assert t.shape[1] > 64  # several blocks of 64 columns at the least
    assert torch.equal(_peaks(res, t, lims), ref)


@pytest.mark.parametrize("interpolation, jerk", [("spline", True), ("spline", False), ("linear", True)])
def test_native_peaks_equal_torch(interpolation, jerk):
    """The dense check in C (kernels/_native_topp.c, topp_peaks) against the torch evaluation, bit for bit: a
    stretched result (k > 1), the breakpoints and times out of order, before 0 and past the end."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("no C compiler: the torch check serves every call")
    y, kn, g = _paths(8, 4, 6)
    J = 100 * A if jerk else None
    res = time_optimal(y, V, A, J, knots=kn, interpolation=interpolation)
    res = res._parts if interpolation == "linear" else res  # the parts are the paths that are checked
    B = res._grid.shape[0]
    assert bool((res._k > 1).all())
    end = float(res._t[:, -1].max() + res._tau.max()) * float(res._k.max())
    t = torch.cat((res._breakpoints(16), torch.rand(B, 300, generator=g, dtype=F64) * (end + 0.4) - 0.2), 1)
    lims = [v.expand(B, 7) for v in (V, A, J) if v is not None]
    got = _peaks(res, t, lims)
    with native.disabled():
        ref = _peaks(res, t, lims)
    assert got.shape == (B, len(lims)) and torch.equal(got, ref)


@pytest.mark.parametrize("interpolation, jerk", [("spline", True), ("spline", False), ("linear", True),
                                                 ("linear", False)])
def test_native_samples_equal_torch(interpolation, jerk):
    """sample() in C (kernels/_native_topp.c, topp_sample) against the torch evaluation, bit for bit: the
    chained parts (polyline + jerk) included, times before 0, past the end and exactly at the knots."""
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("no C compiler: the torch evaluation serves every call")
    y, kn, g = _paths(11, 4, 6)
    res = time_optimal(y, V, A, 100 * A if jerk else None, knots=kn, interpolation=interpolation)
    end = float(res.duration.max())
    t = torch.cat((torch.rand(4, 300, generator=g, dtype=F64) * (end + 0.4) - 0.2,
                   torch.linspace(0, end, 200, dtype=F64).expand(4, -1)), 1)
    got = res.sample(t)
    with native.disabled():
        ref = res.sample(t)
    for a, b in zip(got, ref):
        assert torch.equal(a, b)
    assert bool((got.velocity.abs() > 0.1).any())


def test_search_rows_equals_searchsorted():
    g = torch.Generator().manual_seed(4)
    for L in (0, 1, 2, 7, 64):
        seq = torch.rand(5, L, generator=g, dtype=F64).sort(1).values
        if L > 2:
            seq[:, 2] = seq[:, 1]  # repeated values
        x = torch.cat((torch.rand(5, 50, generator=g, dtype=F64) * 1.2 - 0.1, seq), 1)
        rows = torch.randint(0, 5, x.shape, generator=g)
        for right in (True, False):
            ref = torch.searchsorted(seq[rows], x[..., None], right=right)[..., 0]
            assert torch.equal(_search_rows(seq, rows, x, right), ref)


def test_poly_eval_equals_horner_from_zero():
    g = torch.Generator().manual_seed(5)
    for n in (2, 3, 4, 6):
        coeffs = [torch.randn(4, 1, 3, generator=g, dtype=F64) for _ in range(n)]
        tau = torch.randn(4, 9, 1, generator=g, dtype=F64)
        p = torch.zeros_like(tau * coeffs[-1])
        v, a = torch.zeros_like(p), torch.zeros_like(p)
        for c in reversed(coeffs):
            a, v, p = a * tau + 2 * v, v * tau + p, p * tau + c
        for x, ref in zip(poly_eval(coeffs, tau), (p, v, a)):
            assert x.shape == ref.shape and torch.equal(x, ref)


@pytest.mark.parametrize("interpolation", ["spline", "linear"])
def test_native_topp_passes_equal_torch(interpolation):
    from diffkin.kernels import native

    if not native.available():
        pytest.skip("no C compiler: the torch passes serve every call")
    y, kn, _ = _paths(6, 7, 5)
    res = time_optimal(y, V, A, knots=kn, interpolation=interpolation, grid_per_segment=40)
    with native.disabled():
        ref = time_optimal(y, V, A, knots=kn, interpolation=interpolation, grid_per_segment=40)
    assert torch.equal(res._x, ref._x) and torch.equal(res.duration, ref.duration)
    assert bool((res._x[:, 1:-1] > 0).any())  # a motion, not a path at rest


def test_native_topp_grid_equals_torch():
    """TOPP-RA from the path's derivatives in C (topp_grid: the rows, their fixed bound, the moving row, the
    passes) against _topp's torch code, bit for bit, on random derivatives with zero entries (rows without u,
    joints without a speed bound) and stops."""
    from diffkin.kernels import native
    from diffkin.trajectories.time_optimal import _X_BIG, _topp

    if not native.available():
        pytest.skip("no C compiler: the torch code serves every call")
    g = torch.Generator().manual_seed(9)
    B, M, n = 3, 120, 7
    P1, P2 = (torch.randn(B, M, n, generator=g, dtype=F64) for _ in range(2))
    Q1, Q2 = (torch.randn(B, M - 1, n, generator=g, dtype=F64) for _ in range(2))
    P1[:, ::5, :3] = 0
    Q1[:, ::9] = 0
    Q2[:, ::7] = 0
    grid = torch.cat((torch.zeros(B, 1, dtype=F64), (torch.rand(B, M - 1, generator=g, dtype=F64) + 0.1)
                      .cumsum(1)), 1)
    grid = grid / grid[:, -1:]
    stops = torch.zeros(B, M, dtype=torch.bool)
    stops[:, 40:-1:40] = True
    amax, vmax = A.expand(B, n), V.expand(B, n)

    class Derivatives:  # the path's derivatives at the grid points (P) and at the interval ends (Q)
        s, c = None, ()  # no knots or coefficients: the C slopes are not asked for (native disabled below)

        def eval(self, s, k):
            return (None, P1, P2, None) if s.shape[1] == M else (None, Q1, Q2, None)

    got = native.topp_grid(P1, P2, Q1, Q2, amax, vmax, grid[:, 1:] - grid[:, :-1], stops, _X_BIG)
    with native.disabled():
        ref = _topp(Derivatives(), grid, torch.zeros(B, M, dtype=torch.long), vmax, amax, stops)
    assert torch.equal(got, ref) and bool((ref[:, 1:-1] > 0).any()) and bool((ref[stops] == 0).all())


def test_spline_check_marks_equal_padded_marks():
    """motion._spline_clear checks each row's own marks in blocks: the same decisions as all fine samples at
    once and every row padded to the longest row's mark count (the former code), here with a stand-in
    checker whose decision is a plane in joint space."""
    from diffkin.motion._spline import _knots, _spline_clear
    from diffkin.trajectories.time_optimal import _Path

    class Plane:
        reach = torch.full((7,), 0.3, dtype=F64)

        def eta_of(self, problem):
            return 0.004 + 0.002 * (problem % 2).to(F64)

        def clear(self, q, problem):
            return q[..., 0] + 0.01 * problem.to(F64) < 1.2

    y, _, _ = _paths(7, 9, 6)
    y[::3] *= 0.1  # short and long paths in one batch
    kn, lo, hi = _knots(y), torch.full((7,), -3.0, dtype=F64), torch.full((7,), 3.0, dtype=F64)
    problem = torch.arange(9)
    fine = 512
    got = _spline_clear(Plane(), y, kn, lo, hi, problem, fine=fine)
    # the former code
    s = (kn - kn[:, :1]) / (kn[:, -1:] - kn[:, :1])
    p = _Path(s.contiguous(), y, "spline", "clamped")
    u = torch.linspace(0, 1, fine + 1, dtype=F64).expand(9, -1).contiguous()
    q = p.eval(u)[0]
    inside = ((q >= lo) & (q <= hi)).all(-1).all(-1)
    cum = torch.cat((torch.zeros(9, 1, dtype=F64), ((q[:, 1:] - q[:, :-1]).abs() * Plane.reach).sum(-1)
                     .cumsum(1)), 1)
    c = 0.8 * Plane().eta_of(problem)
    n = torch.ceil(cum[:, -1] / c).long().clamp(min=1)
    K = int(n.max()) + 1
    marks = (torch.arange(K, dtype=F64)[None] * c[:, None]).contiguous()
    idx = torch.searchsorted(cum, marks).clamp(max=fine)
    idx = torch.where(torch.arange(K)[None] <= n[:, None], idx, fine)
    qc = torch.gather(q, 1, idx[..., None].expand(9, K, 7))
    ref = Plane().clear(qc, problem[:, None]).all(1) & inside
    assert torch.equal(got, ref) and bool(got.any()) and not bool(got.all())


def test_native_spline_check_points_equal_torch():
    """motion._spline_clear's fine samples and check points in C (kernels/_native_spline.c) against its torch
    code, bit for bit: the points handed to the checker, their paths, and the decisions (limits included)."""
    from diffkin.kernels import native
    from diffkin.motion._spline import _knots, _spline_clear

    if not native.available():
        pytest.skip("no C compiler: the torch code serves every call")
    seen = []

    class Plane:
        reach = torch.tensor([0.9, 0.8, 0.7, 0.5, 0.4, 0.3, 0.2], dtype=F64)

        def eta_of(self, problem):
            return 0.004 + 0.002 * (problem % 2).to(F64)

        def clear(self, q, problem):
            seen.append((q, problem))
            return q[..., 0] + 0.01 * problem.to(F64) < 1.2

    y, _, _ = _paths(10, 9, 7)
    y[::3] *= 0.1
    kn, problem = _knots(y), torch.arange(9)
    lo, hi = torch.full((7,), -2.5, dtype=F64), torch.full((7,), 2.5, dtype=F64)
    got = _spline_clear(Plane(), y, kn, lo, hi, problem, fine=1000)
    with native.disabled():
        ref = _spline_clear(Plane(), y, kn, lo, hi, problem, fine=1000)
    half = len(seen) // 2  # each call's decisions (rows too long for fine = 1000 are checked again finer)
    assert len(seen) == 2 * half and half >= 1 and torch.equal(got, ref)
    for (q1, p1), (q2, p2) in zip(seen[:half], seen[half:]):
        assert torch.equal(q1, q2) and torch.equal(p1, p2)
    inside = ((y >= -2.5) & (y <= 2.5)).all(-1).all(-1)
    assert bool(got.any()) and not bool(got.all()) and not bool(inside.all())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_grid_slopes_in_c_equal_the_path_evaluation(dtype):
    """_topp's q', q'' at the grid (right-hand at the grid points, left-hand at each interval's end) from
    the C kernel (native.topp_slopes) against _Path.eval's torch Horner, to the bit: splines and polylines,
    one path and batches, float64 and float32."""
    import sys

    from diffkin.kernels import native

    if not native.available():
        pytest.skip("the C library is not available")
    T = sys.modules["diffkin.trajectories.time_optimal"]
    g = torch.Generator().manual_seed(0)
    for B, N, n, m in ((1, 6, 7, 85), (3, 2, 7, 512), (4, 9, 3, 5)):
        y = torch.cumsum(torch.rand(B, N, n, generator=g, dtype=F64) - 0.5, 1)
        gaps = torch.rand(B, N - 1, generator=g, dtype=F64) + 0.2
        s = T.unit_knots(torch.cat((torch.zeros(B, 1, dtype=F64), gaps.cumsum(1)), 1))
        f = torch.arange(m, dtype=F64) / m
        grid = torch.cat(((s[:, :-1, None] + f * (s[:, 1:] - s[:, :-1])[..., None]).flatten(1), s[:, -1:]), 1)
        seg = torch.arange(N - 1).repeat_interleave(m)
        kseg = torch.cat((seg, seg[-1:])).expand(B, -1).contiguous()
        for how in ("spline", "linear"):
            p = T._Path(s.contiguous(), y, how, "clamped")
            p.s, p.c = p.s.to(dtype), tuple(c.to(dtype) for c in p.c)
            got = native.topp_slopes(p.s, p.c, grid.to(dtype), kseg)
            _, P1, P2, _ = p.eval(grid.to(dtype), kseg)
            _, Q1, Q2, _ = p.eval(grid.to(dtype)[:, 1:], kseg[:, :-1])
            assert got is not None and all(torch.equal(a, b) for a, b in zip(got, (P1, P2, Q1, Q2)))


def test_polyline_with_jerk_in_float32_times_its_parts_in_float64():
    """A float32 polyline with a jerk limit is timed part by part in float64, as a float64 one (the parts'
    durations are added up in float64): the same part starts and the float64 durations rounded once."""
    y, kn, _ = _paths(4, 3, 5)
    y, kn, v, a = (x.float() for x in (y, kn, V, A))  # the float32 values, given in both dtypes below
    r32 = time_optimal(y, v, a, 100 * a, knots=kn, interpolation="linear")
    r64 = time_optimal(y.double(), v.double(), a.double(), 100 * a.double(), knots=kn.double(),
                       interpolation="linear")
    assert r32._parts._dtype == F64 and torch.equal(r32._start, r64._start)
    assert r32.duration.dtype == torch.float32 and torch.equal(r32.duration, r64.duration.float())


def test_a_path_alone_is_timed_as_its_row_in_a_batch():
    """Each row's duration and stretch k, timed with seven other paths or alone, to the bit (the cube root of
    the jerk peak one entry at a time: torch's pow can differ in the last bit by the tensor's size/layout)."""
    y, kn, _ = _paths(2, 8, 5)
    J = 10 * A
    batch = time_optimal(y, V, A, J, knots=kn, bc="clamped")
    for b in range(8):
        alone = time_optimal(y[b:b + 1], V, A, J, knots=kn[b:b + 1], bc="clamped")
        assert torch.equal(alone.duration, batch.duration[b:b + 1])
        assert torch.equal(alone._k, batch._k[b:b + 1])
    x = torch.rand(37, dtype=F64) * 10
    assert torch.equal(_cube_root(x), torch.tensor([v ** (1 / 3) for v in x.tolist()], dtype=F64))
    assert torch.equal(_cube_root(x[5:6]), _cube_root(x)[5:6])
