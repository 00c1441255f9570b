"""trajectories.time_optimal beside toppra (TOPP-RA, PyPI) on the same geometric path and grid, in the same
run: durations within 1 %, limits on dense samples, rest at both ends, the path itself (scipy's CubicSpline),
the jerk-limited variant against finite differences of its own acceleration."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch
from scipy.interpolate import CubicSpline

from diffkin.errors import OptionError, ShapeError
from diffkin.trajectories import InfeasibleTrajectoryError, time_optimal

ta = pytest.importorskip("toppra")
import toppra.algorithm as talgo  # noqa: E402
import toppra.constraint as tcon  # noqa: E402

ta.setup_logging("WARNING")


def _problem(seed: int, B: int = 4, N: int = 6, n: int = 7):
    rng = np.random.default_rng(seed)
    path = rng.uniform(-1.5, 1.5, (B, N, n))
    v = rng.uniform(1.0, 2.5, (B, n))
    a = rng.uniform(5.0, 15.0, (B, n))
    return path, v, a, rng


def _toppra_duration(path, v, a, grid, knots, bc="not-a-knot") -> float:
    p = ta.SplineInterpolator(knots, path, bc_type=bc)
    cons = [tcon.JointVelocityConstraint(np.stack([-v, v], 1)),
            tcon.JointAccelerationConstraint(np.stack([-a, a], 1))]  # toppra's default (interpolation) scheme
    inst = talgo.TOPPRA(cons, p, gridpoints=grid, parametrizer="ParametrizeConstAccel")
    return inst.compute_trajectory(0, 0).duration


@pytest.mark.parametrize("bc", ["not-a-knot", "clamped"])
def test_durations_match_toppra_and_limits_hold(bc):
    path, v, a, rng = _problem(0)
    B, N, _ = path.shape
    knots = np.cumsum(rng.uniform(0.5, 1.5, (B, N)), 1)  # uneven knots: the same path as toppra's
    res = time_optimal(torch.tensor(path), torch.tensor(v), torch.tensor(a), knots=torch.tensor(knots), bc=bc)
    grid = res._grid.numpy() * (knots[:, -1:] - knots[:, :1]) + knots[:, :1]
    grid[:, 0], grid[:, -1] = knots[:, 0], knots[:, -1]
    for b in range(B):
        ref = _toppra_duration(path[b], v[b], a[b], grid[b], knots[b], bc)
        assert abs(float(res.duration[b]) / ref - 1) < 0.01, (b, float(res.duration[b]), ref)
    t = torch.linspace(0, float(res.duration.max()) + 0.1, 4001, dtype=torch.float64)
    tr = res.sample(t)
    assert (tr.velocity.abs() <= torch.tensor(v)[:, None] * (1 + 1e-9)).all()
    assert (tr.acceleration.abs() <= torch.tensor(a)[:, None] * (1 + 1e-9)).all()
    # the geometric path is scipy's spline: positions lie on it (the path parameter recovered by time)
    prof = res._profile(t.expand(B, -1) / res._k[:, None])[0].clamp(0, 1).numpy()
    for b in range(B):
        s = knots[b, 0] + prof[b] * (knots[b, -1] - knots[b, 0])
        ref = CubicSpline(knots[b], path[b], bc_type=bc)(s)
        np.testing.assert_allclose(tr.position[b].numpy(), ref, atol=1e-10)
    # starts exactly, holds the end at rest
    end = res.sample(res.duration[:, None] + 0.5)
    np.testing.assert_array_equal(tr.position[:, 0].numpy(), path[:, 0])
    np.testing.assert_allclose(end.position[:, 0].numpy(), path[:, -1], atol=1e-12)
    assert (end.velocity == 0).all() and (end.acceleration == 0).all()


def test_linear_path_stops_at_waypoints_and_stays_on_segments():
    path, v, a, _ = _problem(1, B=3, N=4, n=3)
    res = time_optimal(torch.tensor(path), torch.tensor(v[0]), torch.tensor(a[0]), interpolation="linear")
    t = torch.linspace(0, float(res.duration.max()), 3001, dtype=torch.float64)
    tr = res.sample(t)
    assert (tr.velocity.abs() <= torch.tensor(v[0]) * (1 + 1e-9)).all()
    assert (tr.acceleration.abs() <= torch.tensor(a[0]) * (1 + 1e-9)).all()
    # every sample on one of the straight segments
    q, P = tr.position.numpy(), path
    for b in range(3):
        d = []
        for k in range(3):
            e = P[b, k + 1] - P[b, k]
            lam = np.clip((q[b] - P[b, k]) @ e / (e @ e), 0, 1)
            d.append(np.linalg.norm(q[b] - (P[b, k] + lam[:, None] * e), axis=1))
        assert np.min(d, 0).max() < 1e-12
    # at rest at every interior waypoint (the velocity is zero at its time)
    for b in range(3):
        for k in (1, 2):
            hit = np.linalg.norm(q[b] - P[b, k], axis=1).argmin()
            assert np.linalg.norm(tr.velocity[b, hit].numpy()) < 0.05 * np.linalg.norm(v[0])


def test_jerk_limited_variant():
    path, v, a, rng = _problem(2, B=3)
    j = rng.uniform(50.0, 500.0, 7)
    free = time_optimal(torch.tensor(path), torch.tensor(v), torch.tensor(a))
    res = time_optimal(torch.tensor(path), torch.tensor(v), torch.tensor(a), torch.tensor(j))
    assert (res.duration >= free.duration).all()  # the smoothing can only cost time
    t = torch.linspace(0, float(res.duration.max()) + 0.1, 6001, dtype=torch.float64)
    tr, jerk = res.sample(t), res.jerk(t)
    assert (tr.velocity.abs() <= torch.tensor(v)[:, None] * (1 + 1e-9)).all()
    assert (tr.acceleration.abs() <= torch.tensor(a)[:, None] * (1 + 1e-9)).all()
    assert (jerk.abs() <= torch.tensor(j) * (1 + 1e-9)).all()
    # rest at both ends with zero acceleration (the moving average starts and ends at rest)
    assert tr.acceleration[:, 0].abs().max() == 0 and tr.velocity[:, 0].abs().max() == 0
    end = res.sample(res.duration[:, None])
    assert end.velocity.abs().max() < 1e-9 and end.acceleration.abs().max() < 1e-9
    # velocity, acceleration and jerk are the derivatives of the samples (central differences)
    tq, h = torch.tensor([0.31, 0.77, 1.9], dtype=torch.float64), 1e-6
    up, dn = res.sample(tq + h), res.sample(tq - h)
    np.testing.assert_allclose((up.position - dn.position) / (2 * h), res.sample(tq).velocity, atol=1e-6)
    np.testing.assert_allclose((up.velocity - dn.velocity) / (2 * h), res.sample(tq).acceleration, atol=1e-5)
    np.testing.assert_allclose((up.acceleration - dn.acceleration) / (2 * h), res.jerk(tq), atol=1e-3)


def test_at_rate_float32_and_errors():
    path, v, a, _ = _problem(3, B=2, N=3, n=2)
    res = time_optimal(torch.tensor(path, dtype=torch.float32), 2.0, 10.0)
    t, tr = res.at_rate(0.01)
    assert t.dtype == tr.position.dtype == torch.float32 and tr.position.shape == (2, t.shape[1], 2)
    assert t.shape[1] == int(np.ceil(float(res.duration.max()) / 0.01)) + 1
    np.testing.assert_allclose(tr.position[:, -1].numpy(), path[:, -1], atol=1e-5)
    for dt in (0.0, -0.01, float("nan")):
        with pytest.raises(OptionError, match="dt"):
            res.at_rate(dt)
    with pytest.raises(InfeasibleTrajectoryError):
        time_optimal(torch.tensor(path), torch.tensor([1.0, 0.0], dtype=torch.float64), 10.0)
    with pytest.raises(ShapeError):
        time_optimal(torch.tensor(path), torch.ones(3, dtype=torch.float64), 10.0)


def test_linear_path_with_jerk_limit_rests_at_every_corner():
    path, v, a, rng = _problem(4, B=2, N=4, n=3)
    j = rng.uniform(50.0, 300.0, 3)
    res = time_optimal(torch.tensor(path), torch.tensor(v[0]), torch.tensor(a[0]), torch.tensor(j),
                       interpolation="linear")
    h = 1e-4
    t = torch.arange(0, float(res.duration.max()) + 0.05, h, dtype=torch.float64)
    tr, jerk = res.sample(t), res.jerk(t)
    assert (tr.velocity.abs() <= torch.tensor(v[0]) * (1 + 1e-9)).all()
    assert (tr.acceleration.abs() <= torch.tensor(a[0]) * (1 + 1e-9)).all()
    assert (jerk.abs() <= torch.tensor(j) * (1 + 1e-9)).all()
    # no velocity jump anywhere (a corner passed at speed would show here): positions differentiate to qd
    fd = (tr.position[:, 2:] - tr.position[:, :-2]) / (2 * h)
    assert (fd - tr.velocity[:, 1:-1]).abs().max() < 1e-4
    fa = (tr.velocity[:, 2:] - tr.velocity[:, :-2]) / (2 * h)
    assert (fa - tr.acceleration[:, 1:-1]).abs().max() < 0.05
    end = res.sample(res.duration[:, None] + 1e-9).position[:, 0]
    np.testing.assert_array_equal(end.numpy(), path[:, -1])


def _close_waypoints_path() -> tuple[torch.Tensor, torch.Tensor]:
    """A MotionBenchMaker plan's path (bookshelf_thin/0013 as motion.plan timed it among the 700): two of its
    waypoints 0.1 mrad apart, so the clamped spline crosses one very short knot interval with a large third
    derivative; its segments split at their midpoints, as motion.plan pads a batch."""
    w = torch.tensor([
        [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785],
        [2.1027e-03, -7.8948e-01, -8.6624e-02, -2.3193e+00, 2.9395e-02, 1.5971e+00, 7.9258e-01],
        [2.1745e-03, -7.8950e-01, -8.6780e-02, -2.3193e+00, 2.9478e-02, 1.5971e+00, 7.9258e-01],
        [2.6274e-01, -8.7883e-01, -4.1812e-01, -2.1920e+00, 2.5302e-01, 1.7369e+00, 7.6852e-01],
        [1.1848e+00, -1.1937e+00, -1.5621e+00, -1.7536e+00, 1.0347e+00, 2.2228e+00, 6.8074e-01],
        [1.1859e+00, -1.1940e+00, -1.5635e+00, -1.7531e+00, 1.0356e+00, 2.2234e+00, 6.8063e-01],
        [1.5882e+00, -1.3309e+00, -2.0520e+00, -1.5663e+00, 1.3732e+00, 2.4323e+00, 6.4135e-01],
        [1.7471e+00, -1.3846e+00, -2.2347e+00, -1.4969e+00, 1.5032e+00, 2.5118e+00, 6.2488e-01],
        [1.7603e+00, -1.3883e+00, -2.2345e+00, -1.4977e+00, 1.5089e+00, 2.5138e+00, 6.2207e-01],
        [2.1831e+00, -1.3719e+00, -2.4224e+00, -1.2178e+00, 2.0152e+00, 2.4672e+00, 8.9695e-01]],
        dtype=torch.float64)
    pieces = [torch.lerp(w[i], w[i + 1], torch.linspace(0, 1, 4, dtype=torch.float64)[:-1, None])
              for i in range(len(w) - 1)]
    path = torch.cat((*pieces, w[-1:]))[None]  # (1, 28, 7)
    chord = (path[:, 1:] - path[:, :-1]).norm(dim=-1)
    return path, torch.cat((chord.new_zeros(1, 1), chord.cumsum(1)), 1)


@pytest.mark.parametrize("short", [0, None])
def test_jerk_held_across_a_short_knot_interval(monkeypatch, short):
    """The jerk limit holds on 10 µs samples where the spline turns sharply between two close waypoints:
    the check samples the time the smoothed profile takes to cross the shortest knot intervals (without
    them, ``short=0``, the limit is exceeded several times over there)."""
    topp = importlib.import_module("diffkin.trajectories.time_optimal")  # the module, not the function
    if short is not None:
        monkeypatch.setattr(topp, "_SHORT_INTERVALS", short)
    path, knots = _close_waypoints_path()
    v = torch.tensor([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61], dtype=torch.float64)
    a = torch.tensor([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0], dtype=torch.float64)
    j = torch.tensor([7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0], dtype=torch.float64)
    res = time_optimal(path, v, a, j, knots=knots, bc="clamped")
    dt = 1e-5
    t = torch.arange(0, float(res.duration[0]) + dt, dt, dtype=torch.float64)
    ratio = float((res.sample(t).acceleration[0].diff(dim=0).abs() / dt / j).max())
    if short == 0:
        assert ratio > 2
    else:
        assert ratio <= 1.005


def test_coarse_checks_in_one_call_equal_one_call_per_candidate(monkeypatch):
    """The coarse checks of the τ candidates run as one call for small batches (rows × candidates
    up to _ONE_CHECK) and one call per candidate for large ones: the same durations, stretches and samples to
    the bit, spline and linear, with and without a jerk limit, batches of 1 and 5."""
    tom = importlib.import_module("diffkin.trajectories.time_optimal")
    g = torch.Generator().manual_seed(11)
    v, a, j = torch.full((7,), 2.0, dtype=torch.float64), torch.full((7,), 10.0, dtype=torch.float64), \
        torch.full((7,), 5000.0, dtype=torch.float64)
    for B, N in ((1, 6), (5, 4)):
        path = torch.cumsum(torch.rand(B, N, 7, generator=g, dtype=torch.float64) - 0.5, 1)
        for interpolation in ("spline", "linear"):
            for jerk in (j, None):
                got = []
                for one in (256, 0):
                    monkeypatch.setattr(tom, "_ONE_CHECK", one)
                    r = time_optimal(path, v, a, jerk, interpolation=interpolation)
                    t = torch.linspace(0, float(r.duration.max()), 40, dtype=torch.float64)
                    got.append((r.duration, r.sample(t).position, r.sample(t).acceleration))
                assert all(torch.equal(x, y) for x, y in zip(*got))


def test_search_rows_gathered_equals_its_binary_search(monkeypatch):
    """_search_rows' ways (one row, or a few samples with their rows gathered: one torch.searchsorted;
    many: the binary search by gathers) give the same index for every sample: ties, both sides, values
    outside the rows, a NaN sample (0), rows broadcast against the samples, and against torch.searchsorted
    row by row."""
    mod = importlib.import_module("diffkin.trajectories.time_optimal")
    g = torch.Generator().manual_seed(0)
    for trial in range(200):
        P, L = int(torch.randint(1, 5, (1,), generator=g)), int(torch.randint(1, 300, (1,), generator=g))
        P = 1 if trial % 4 == 0 else P  # one row: its own searchsorted
        seq = torch.rand(P, L, generator=g, dtype=torch.float64).sort(1).values
        N = int(torch.randint(1, 40, (1,), generator=g))
        rows = torch.randint(0, P, (N,), generator=g)
        x = torch.rand(N, generator=g, dtype=torch.float64) * 1.2 - 0.1
        if trial % 3 == 0:  # ties between samples and entries
            seq, x = (seq * 4).round() / 4, (x * 4).round() / 4
        if trial % 5 == 0:
            x[0] = float("nan")
        for right in (True, False):
            monkeypatch.setattr(mod, "_GATHERED", 1 << 16)
            gathered = mod._search_rows(seq, rows, x, right)
            monkeypatch.setattr(mod, "_GATHERED", 0)
            searched = mod._search_rows(seq, rows, x, right) if P > 1 else \
                mod._search_rows(seq.expand(2, L), rows, x, right)  # two equal rows: the binary search
            assert torch.equal(gathered, searched)
            finite = x == x
            ref = torch.stack([torch.searchsorted(seq[r], v, right=right) for r, v in zip(rows, x)])
            assert torch.equal(gathered[finite], ref[finite]) and (gathered[~finite] == 0).all()
    monkeypatch.setattr(mod, "_GATHERED", 1 << 16)
    seq = torch.tensor([[0.0, 1.0, 2.0], [0.5, 1.5, 2.5]], dtype=torch.float64)
    x = torch.tensor([[0.7, 1.7, 3.0]], dtype=torch.float64)
    out = mod._search_rows(seq, torch.tensor([[0], [1]]), x)
    assert out.tolist() == [[1, 2, 3], [1, 2, 3]]
