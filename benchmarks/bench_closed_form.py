"""Closed-form IK (all 8 branches) vs ik.solve (one solution) on random reachable UR10 targets.

    python -m benchmarks.bench_closed_form [--targets 100000] [--solve-targets 10000] [--threads 1] [--quick]

UR10 from the vendored URDF (tests/data/urdf/ur10.urdf, float64), targets = FK of joints drawn within the
limits (fixed seed). ``closed_form`` = every branch, its validity by FK and the limit mask; ``solve`` =
Levenberg–Marquardt (tolerances 1e-6 m / rad) on the first ``--solve-targets`` targets
(all by default); ``solve_seeded`` = ik.solve seeded by the closed form. Per-target times.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from diffkin import ik
from diffkin.models import from_urdf

__all__ = ["run", "main"]
URDF = Path(__file__).resolve().parents[1] / "tests" / "data" / "urdf" / "ur10.urdf"


def _time(fn, repeats=3):
    best = float("inf")
    out = None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def run(args) -> list[dict]:
    torch.set_num_threads(getattr(args, "threads", 1))
    quick = getattr(args, "quick", False)
    n = 2000 if quick else getattr(args, "targets", 100_000)
    ns = min(n, 500 if quick else getattr(args, "solve_targets", 100_000))
    chain = from_urdf(URDF, "tool0", dtype=torch.float64)
    q = chain.random_configuration((n,), generator=torch.Generator().manual_seed(0))
    rows = []
    with torch.no_grad():
        T = chain.forward_kinematics(q)
        ik.closed_form(chain, T[:10])
        sec, sol = _time(lambda: ik.closed_form(chain, T))
        rows.append(dict(benchmark="closed_form_ur10", impl="closed_form (8 branches)", batch=n, seconds=sec,
                         us_per_target=1e6 * sec / n, found=float(sol.success.any(-1).float().mean()),
                         branches_valid=float(sol.success.float().mean())))
        Ts = T[:ns]
        sec, res = _time(lambda: ik.solve(chain, Ts, seed=0, position_tolerance=1e-6,
                                          orientation_tolerance=1e-6), repeats=1)
        rows.append(dict(benchmark="closed_form_ur10", impl="ik.solve (1 solution)", batch=ns, seconds=sec,
                         us_per_target=1e6 * sec / ns, found=float(res.success.float().mean())))
        sec, res = _time(lambda: ik.solve(chain, Ts, seeds_from_closed_form=True, seed=0,
                                          position_tolerance=1e-6, orientation_tolerance=1e-6), repeats=1)
        rows.append(dict(benchmark="closed_form_ur10", impl="ik.solve seeded by closed form", batch=ns,
                         seconds=sec, us_per_target=1e6 * sec / ns, found=float(res.success.float().mean())))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--targets", type=int, default=100_000)
    p.add_argument("--solve-targets", type=int, default=100_000)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--quick", action="store_true")
    for r in run(p.parse_args(argv)):
        print(r)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

# Measured once (1 thread, shared 2-core CPU, float64, 100 000 targets): closed_form 12.7 µs/target for all
# 8 branches incl. FK validity (at least one valid branch for 100 %); ik.solve 49 µs/target for one solution
# (99.3 % success); ik.solve seeded by the closed form 64 µs/target (100 %).
