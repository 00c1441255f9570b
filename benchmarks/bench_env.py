"""Env steps/s: ``gymnasium.make`` + ``SyncVectorEnv`` vs the torch-batched ``TorchVectorEnv``.

    python -m benchmarks.bench_env [--envs 1 64 1024 4096] [--env-id diffkin/Reach-v0] [--threads 1]

Random actions in [-1, 1], Panda, joint-velocity mode, auto-reset included (episodes of 50 steps).
Each figure is the median of ``--repeats`` timed blocks of at least ``--min-time`` seconds. The Sync figure
for many envs is taken over fewer steps (it is thousands of times slower); speed is steps × envs / s.
"""

from __future__ import annotations

import argparse
import statistics
import time

import gymnasium as gym
import numpy as np
import torch

import diffkin.envs  # noqa: F401
from diffkin.envs.vector import TorchVectorEnv

__all__ = ["run", "main"]


def _timed(step, batch: int, min_time: float, repeats: int) -> tuple[float, float]:
    """Median env-steps per wall-clock second and per process-CPU second over ``repeats`` blocks.

    The CPU-time figure is robust to other processes sharing the cores (with one torch thread it is what
    the env would sustain on an idle core).
    """
    rates, cpu_rates = [], []
    for _ in range(repeats):
        n, t0, c0 = 0, time.perf_counter(), time.process_time()
        while True:
            step()
            n += 1
            dt = time.perf_counter() - t0
            if dt >= min_time:
                break
        rates.append(n * batch / dt)
        cpu_rates.append(n * batch / max(time.process_time() - c0, 1e-9))
    return statistics.median(rates), statistics.median(cpu_rates)


def bench_batched(env_id: str, n: int, device: str, min_time: float, repeats: int) -> tuple[float, float]:
    venv = TorchVectorEnv(env_id, n, device=device)
    venv.reset(seed=0)
    gen = torch.Generator(device=device).manual_seed(0)
    actions = [torch.rand(n, *venv.single_action_space.shape, generator=gen, device=device) * 2 - 1
               for _ in range(8)]
    i = [0]

    def step():
        venv.step(actions[i[0] % 8])
        i[0] += 1

    for _ in range(60):  # warm-up, crosses an auto-reset
        step()
    if device == "cuda":
        torch.cuda.synchronize()
    return _timed(step, n, min_time, repeats)


def bench_sync(env_id: str, n: int, min_time: float, repeats: int) -> tuple[float, float]:
    venv = gym.vector.SyncVectorEnv([lambda: gym.make(env_id) for _ in range(n)])
    venv.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(8, n, *venv.single_action_space.shape)).astype(np.float32)
    i = [0]

    def step():
        venv.step(actions[i[0] % 8])
        i[0] += 1

    for _ in range(2):
        step()
    rate = _timed(step, n, min_time, repeats)
    venv.close()
    return rate


def run(args=None) -> list[dict]:
    """Rows ``{benchmark, impl, num_envs, steps_per_s, steps_per_cpu_s, ratio_vs_sync}`` (batched / Sync)."""
    args = args if args is not None else parse_args([])
    env_id = getattr(args, "env_id", "diffkin/Reach-v0")
    quick = getattr(args, "quick", False)
    counts = getattr(args, "envs", [1, 64, 1024] if quick else [1, 64, 1024, 4096])
    threads, device = getattr(args, "threads", 1), getattr(args, "device", "cpu")
    min_time = getattr(args, "min_time", 0.3 if quick else 1.0)
    repeats = getattr(args, "repeats", 1 if quick else 3)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    rows = []
    try:
        for n in counts:
            batched, batched_cpu = bench_batched(env_id, n, device, min_time, repeats)
            sync, sync_cpu = bench_sync(env_id, n, min_time, repeats)
            common = {"benchmark": "env_step", "env_id": env_id, "num_envs": n, "batch": n,
                      "threads": threads}
            rows.append({**common, "impl": "gym.make+SyncVectorEnv", "device": "cpu", "steps_per_s": sync,
                         "steps_per_cpu_s": sync_cpu})
            rows.append({**common, "impl": "TorchVectorEnv", "device": device, "steps_per_s": batched,
                         "steps_per_cpu_s": batched_cpu, "ratio_vs_sync": batched / sync,
                         "cpu_ratio_vs_sync": batched_cpu / sync_cpu})
    finally:
        torch.set_num_threads(old)
    return rows


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env-id", default="diffkin/Reach-v0")
    p.add_argument("--envs", type=int, nargs="+", default=[1, 64, 1024, 4096])
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--device", default="cpu")
    p.add_argument("--min-time", type=float, default=1.0)
    p.add_argument("--repeats", type=int, default=3)
    return p.parse_args(argv)


def main(argv=None) -> int:
    rows = run(parse_args(argv))
    print(f"{'impl':<24}{'envs':>6}{'steps/s (wall)':>16}{'ratio':>8}{'steps/CPU-s':>14}{'ratio':>8}")
    for r in rows:
        ratio = f"{r['ratio_vs_sync']:.0f}x" if "ratio_vs_sync" in r else ""
        cpu_ratio = f"{r['cpu_ratio_vs_sync']:.0f}x" if "cpu_ratio_vs_sync" in r else ""
        print(f"{r['impl']:<24}{r['num_envs']:>6}{r['steps_per_s']:>16,.0f}{ratio:>8}"
              f"{r['steps_per_cpu_s']:>14,.0f}{cpu_ratio:>8}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
