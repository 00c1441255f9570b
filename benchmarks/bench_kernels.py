"""The kernel performance targets (issue 18), measured in one run against pytorch-kinematics where it has a
counterpart, on an idle machine and with another process holding one core.

    python -m benchmarks.bench_kernels [--quick] [--no-busy] [--parts fk latency env busy] [--json out.json]

Rows (Panda, CPU, medians of timed blocks; see :mod:`benchmarks.common`):

* ``fk`` / ``forward_kinematics_and_jacobian``: configurations per second at batch 100 000, float32 and
  float64, 1 and 2 threads; pytorch-kinematics's FK at the same batch and threads, and the ratio
  (FK + J) / FK;
* ``latency``: one configuration (batch 1): FK, FK + Jacobian, ``ik.solve`` of one reachable full pose
  (median over 50 targets, 0.1 mm / 1 mrad), one ``gymnasium.make("diffkin/Reach-v0")`` step;
* ``env``: ``TorchVectorEnv`` with 4 096 envs, env-steps per second, 1 and 2 threads;
* ``busy``: the same workloads at 2 threads while a second process spins on one core, and the slowdown
  against the idle figure (``--no-busy`` skips them).

Each row carries its target and whether it is met (``target``, ``met``).
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import subprocess
import sys
import time

import gymnasium as gym
import numpy as np
import torch

import diffkin.envs  # noqa: F401  (registers the IDs)
from benchmarks.common import FULL, QUICK, pk_panda, print_table, timeit, torch_threads, write_json
from diffkin import ik, models
from diffkin.envs.vector import TorchVectorEnv

__all__ = ["run", "main", "busy_core"]

_DTYPES = {"float32": torch.float32, "float64": torch.float64}
PARTS = ("fk", "latency", "env", "busy")


@contextlib.contextmanager
def busy_core():
    """Another process spinning on one core for the duration of the block."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    time.sleep(0.5)  # let the scheduler place it
    try:
        yield
    finally:
        proc.kill()
        proc.wait()


def _fk_rows(B: int, threads: int, timing, with_pk: bool) -> list[dict]:
    return [r for name, dtype in _DTYPES.items() for r in _fk_dtype(name, dtype, B, threads, timing, with_pk)]


def _fk_dtype(name: str, dtype, B: int, threads: int, timing, with_pk: bool) -> list[dict]:
    rows = []
    chain = models.load("panda", dtype=dtype)
    q = chain.random_configuration((B,), generator=torch.Generator().manual_seed(0))
    with torch.no_grad(), torch_threads(threads):
        t_fk = timeit(lambda: chain.forward_kinematics(q), *timing)
        t_fkj = timeit(lambda: chain.forward_kinematics_and_jacobian(q), *timing)
        t_pk = None
        if with_pk:
            ref = pk_panda(dtype)
            t_pk = timeit(lambda: ref.forward_kinematics(q).get_matrix(), *timing)
    common = {"batch": B, "dtype": name, "threads": threads}
    rows.append({"benchmark": "fk", "impl": "diffkin FK", **common, "seconds": t_fk, "per_s": B / t_fk,
                 "speedup_vs_pk": (t_pk / t_fk) if t_pk else None,
                 "target": "≥ 20 M/s (float32, 2 threads)" if name == "float32" and threads == 2 else "",
                 "met": (B / t_fk >= 20e6) if name == "float32" and threads == 2 else None})
    if t_pk:
        rows.append({"benchmark": "fk", "impl": "pytorch-kinematics FK", **common, "seconds": t_pk,
                     "per_s": B / t_pk})
    ratio = t_fkj / t_fk
    rows.append({"benchmark": "fk", "impl": "diffkin FK + Jacobian", **common, "seconds": t_fkj,
                 "per_s": B / t_fkj, "ratio_fkj_over_fk": ratio, "target": "(FK + J) / FK ≤ 1.3",
                 "met": ratio <= 1.3})
    return rows


def _ik_targets(chain, count: int):
    q = chain.random_configuration((count,), generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        return chain.forward_kinematics(q)


def _latency_rows(timing, quick: bool) -> list[dict]:
    rows = [row for name, dtype in _DTYPES.items() for row in _latency_dtype(name, dtype, timing, quick)]
    rows.append(_single_env_row(timing))
    return rows


def _latency_dtype(name: str, dtype, timing, quick: bool) -> list[dict]:
    rows = []
    chain = models.load("panda", dtype=dtype)
    q = chain.random_configuration((1,), generator=torch.Generator().manual_seed(1))
    with torch.no_grad(), torch_threads(1):
        t_fk = timeit(lambda: chain.forward_kinematics(q), *timing)
        t_fkj = timeit(lambda: chain.forward_kinematics_and_jacobian(q), *timing)
        targets = _ik_targets(chain, 10 if quick else 50)
        ik.solve(chain, targets[:1])  # warm-up (sample library)
        per_target, success = [], 0
        for T in targets:
            t0 = time.perf_counter()
            res = ik.solve(chain, T[None])
            per_target.append(time.perf_counter() - t0)
            success += int(res.success.sum())
    t_ik = statistics.median(per_target)
    common = {"benchmark": "latency", "batch": 1, "dtype": name, "threads": 1}
    rows += [
        {**common, "impl": "FK", "seconds": t_fk, "microseconds": t_fk * 1e6, "target": "≤ 30 µs",
         "met": t_fk <= 30e-6},
        {**common, "impl": "FK + Jacobian", "seconds": t_fkj, "microseconds": t_fkj * 1e6},
        {**common, "impl": f"ik.solve (median of {len(per_target)} targets, {success} solved)",
         "seconds": t_ik, "microseconds": t_ik * 1e6, "target": "≤ 1 ms", "met": t_ik <= 1e-3},
    ]
    return rows


def _single_env_row(timing) -> dict:
    env = gym.make("diffkin/Reach-v0")
    env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (64, 7)).astype(np.float32)
    i = [0]

    def step():
        _, _, term, trunc, _ = env.step(actions[i[0] % 64])
        i[0] += 1
        if term or trunc:
            env.reset()

    with torch_threads(1):
        t_env = timeit(step, *timing)
    return {"benchmark": "latency", "impl": "gymnasium.make('diffkin/Reach-v0').step", "batch": 1,
            "dtype": "float32", "threads": 1, "seconds": t_env, "microseconds": t_env * 1e6,
            "per_s": 1 / t_env, "target": "≥ 10 000 steps/s", "met": 1 / t_env >= 1e4}


def _vector_env_step(n: int):
    venv = TorchVectorEnv("diffkin/Reach-v0", n)
    venv.reset(seed=0)
    gen = torch.Generator().manual_seed(0)
    actions = [torch.rand(n, 7, generator=gen) * 2 - 1 for _ in range(8)]
    i = [0]

    def step():
        venv.step(actions[i[0] % 8])
        i[0] += 1

    for _ in range(60):  # crosses an auto-reset
        step()
    return step


def _env_rows(n: int, threads: int, timing) -> list[dict]:
    step = _vector_env_step(n)
    with torch_threads(threads):
        t = timeit(step, max(timing[0], 1.0), timing[1])  # blocks of ≥ 1 s: they cross auto-resets
    met = n / t >= 10e6 if n == 4096 else None
    return [{"benchmark": "env", "impl": "TorchVectorEnv diffkin/Reach-v0", "batch": n, "dtype": "float32",
             "threads": threads, "seconds": t, "per_s": n / t, "target": "≥ 10 M env-steps/s (4 096 envs)",
             "met": met}]


def _busy_rows(timing, quick: bool) -> list[dict]:
    """The 2-thread workloads again beside a spinning process; slowdown = busy time / idle time."""
    B = 20_000 if quick else 100_000
    chain = models.load("panda", dtype=torch.float32)
    q = chain.random_configuration((B,), generator=torch.Generator().manual_seed(0))
    targets = _ik_targets(chain, 200 if quick else 1000)
    step = _vector_env_step(4096)
    work = {
        f"FK, batch {B:,}": lambda: chain.forward_kinematics(q),
        f"FK + Jacobian, batch {B:,}": lambda: chain.forward_kinematics_and_jacobian(q),
        f"ik.solve, {targets.shape[0]} targets": lambda: ik.solve(chain, targets),
        "TorchVectorEnv step, 4 096 envs": step,
    }
    rows = []
    with torch.no_grad(), torch_threads(2):
        t_idle = {k: timeit(fn, *timing) for k, fn in work.items()}
        with busy_core():
            t_busy = {k: timeit(fn, *timing) for k, fn in work.items()}
    for k in work:
        slow = t_busy[k] / t_idle[k]
        rows.append({"benchmark": "busy", "impl": k, "dtype": "float32", "threads": 2,
                     "seconds_idle": t_idle[k], "seconds_busy": t_busy[k], "slowdown": slow,
                     "target": "≤ 2×", "met": slow <= 2.0})
    return rows


def run(args=None) -> list[dict]:
    args = args if args is not None else parse_args([])
    quick = getattr(args, "quick", False)
    timing = QUICK if quick else FULL
    B = 20_000 if quick else 100_000
    parts = set(getattr(args, "parts", None) or PARTS)
    if getattr(args, "no_busy", False):
        parts.discard("busy")
    rows = []
    if "fk" in parts:
        for threads in (1, 2):
            rows += _fk_rows(B, threads, timing, with_pk=True)
    if "latency" in parts:
        rows += _latency_rows(timing, quick)
    if "env" in parts:
        for threads in (1, 2):
            rows += _env_rows(4096, threads, timing)
    if "busy" in parts:
        rows += _busy_rows(timing, quick)
    return rows


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="smaller batches, short timing blocks")
    p.add_argument("--no-busy", action="store_true", help="skip the runs beside a busy core")
    p.add_argument("--parts", nargs="+", choices=PARTS, default=None, help="run only these (default all)")
    p.add_argument("--json", default=None, help="write the rows to this JSON file")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    rows = run(args)
    for name in ("fk", "latency", "env", "busy"):
        print_table([r for r in rows if r["benchmark"] == name], title=name)
    if args.json:
        write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
