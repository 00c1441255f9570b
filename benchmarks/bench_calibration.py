"""Calibration speed: one 7-DOF chain from 100 poses (both methods), and K robots in one batched call.

    python -m benchmarks.bench_calibration [--robots 1000] [--poses 100] [--sequential 20] [--device cpu]

Panda (modified DH), true tables ±2 mm / ±0.2° off nominal on every identifiable parameter, full-pose
measurements with 0.05 mm / 0.01° noise, float64. "time to converge" is the wall time of one
``calibrate`` call with the default stopping rules (least squares: |Δζ_j| ≤ 1e-10 (1 + |ζ_j|); L-BFGS:
relative loss change ≤ 1e-13), median of ``--repeats`` after a warm-up call. The batch case calibrates
``--robots`` robots (each its own true table and poses) in one ``calibrate_batch`` call and compares with
``--sequential`` single calls, extrapolated linearly to K calls (they are independent and equal in size).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

from benchmarks.common import sync
from diffkin import models
from diffkin.calibration import CalibrationModel, calibrate, calibrate_batch, identifiability
from diffkin.rotations import rotvec_to_matrix

__all__ = ["run", "main"]

F64 = torch.float64


def _problem(K: int, N: int, seed: int, device: str):
    """Nominal Panda, joints (K, N, 7), noisy measured poses (K, N, 4, 4), noise-free validation data."""
    nominal = models.load("panda", dtype=F64)
    g = torch.Generator().manual_seed(seed)
    q = nominal.random_configuration((K, N), generator=g)
    free = identifiability(nominal, q[0]).identifiable
    model = CalibrationModel.from_chains(nominal)
    mask = torch.tensor([n in free for n in model.names])
    u = 2 * torch.rand(K, model.n_params, generator=g, dtype=F64) - 1
    zeta = model.nominal + torch.where(model.is_length(), 2e-3 * u, math.radians(0.2) * u) * mask
    with torch.no_grad():
        T = model.forward_kinematics(zeta, q).clone()
    T[..., :3, 3] += 5e-5 * torch.randn(K, N, 3, generator=g, dtype=F64)
    T[..., :3, :3] = (
        rotvec_to_matrix(math.radians(0.01) * torch.randn(K, N, 3, generator=g, dtype=F64)) @ T[..., :3, :3]
    )
    return nominal.to(device), q.to(device), T.to(device)


def _timed(fn, repeats: int, device: str):
    fn()  # warm-up
    times, out = [], None
    for _ in range(repeats):
        sync(device)
        t0 = time.perf_counter()
        out = fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def bench_single(N: int, repeats: int, device: str) -> list[dict]:
    nominal, q, T = _problem(1, N, seed=0, device=device)
    rows = []
    for method in ("least_squares", "gradient"):
        sec, res = _timed(
            lambda m=method: calibrate(nominal, q[0], T[0], method=m, progress=False), repeats, device
        )
        rows.append(
            {
                "benchmark": "calibration_single",
                "impl": method,
                "device": device,
                "robots": 1,
                "poses": N,
                "dof": nominal.n_joints,
                "seconds": sec,
                "iterations": res.iterations,
                "converged": res.converged,
                "residual_rms_mm": res.residuals[-1] * 1e3,
            }
        )
    return rows


def bench_batch(K: int, N: int, sequential: int, method: str, device: str) -> list[dict]:
    nominal, q, T = _problem(K, N, seed=1, device=device)
    calibrate_batch(nominal, q[:2], T[:2], method=method, progress=False)  # warm-up
    sync(device)
    t0 = time.perf_counter()
    batch = calibrate_batch(nominal, q, T, method=method, progress=False)
    sync(device)
    t_batch = time.perf_counter() - t0
    S = min(sequential, K)
    t0 = time.perf_counter()
    singles = [calibrate(nominal, q[k], T[k], method=method, progress=False) for k in range(S)]
    sync(device)
    t_seq = (time.perf_counter() - t0) * K / S
    diff = max(float((b.identified - s.identified).abs().max()) for b, s in zip(batch, singles))
    common = {"benchmark": "calibration_batch", "method": method, "device": device, "robots": K, "poses": N}
    return [
        {
            **common,
            "impl": "calibrate_batch (one call)",
            "seconds": t_batch,
            "iterations": batch[0].iterations,
            "residual_rms_mm": statistics.median(r.residuals[-1] for r in batch) * 1e3,
        },
        {
            **common,
            "impl": f"sequential calibrate (est. from {S} calls)",
            "seconds": t_seq,
            "ratio": t_seq / t_batch,
            "max_param_diff_vs_batch": diff,
        },
    ]


def run(args=None) -> list[dict]:
    """Rows ``{benchmark, impl, device, robots, poses, seconds, ...}``; ratio = sequential / batched."""
    args = args if args is not None else parse_args([])
    quick = getattr(args, "quick", False)
    K = getattr(args, "robots", None) or (100 if quick else 1000)
    N = getattr(args, "poses", 100)
    sequential = getattr(args, "sequential", None) or (5 if quick else 20)
    device, threads = getattr(args, "device", "cpu"), getattr(args, "threads", 1)
    repeats = getattr(args, "repeats", 1 if quick else 3)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        rows = bench_single(N, repeats, device)
        for method in ("gradient", "least_squares"):
            rows += bench_batch(K, N, sequential, method, device)
    finally:
        torch.set_num_threads(old)
    for r in rows:
        r["threads"] = threads
    return rows


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", type=int, default=None, help="K for the batch case (default 1000, quick 100)")
    p.add_argument("--poses", type=int, default=100)
    p.add_argument("--sequential", type=int, default=None, help="single calls timed (default 20, quick 5)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads (1 is fastest on a busy box)"
    )
    p.add_argument("--device", default="cpu")
    p.add_argument("--quick", action="store_true")
    return p.parse_args(argv)


def main(argv=None) -> int:
    rows = run(parse_args(argv))
    print(f"{'benchmark':<20}{'method/impl':<58}{'K':>6}{'N':>5}{'seconds':>10}{'iters':>7}{'ratio':>8}")
    for r in rows:
        name = r["impl"] if r["benchmark"] == "calibration_single" else f"{r['method']}: {r['impl']}"
        ratio = f"{r['ratio']:.0f}x" if "ratio" in r else ""
        iters = str(r.get("iterations", ""))
        print(
            f"{r['benchmark']:<20}{name:<58}{r['robots']:>6}{r['poses']:>5}{r['seconds']:>10.3f}{iters:>7}"
            f"{ratio:>8}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
