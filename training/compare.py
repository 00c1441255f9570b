"""Same-run comparison of env IDs under one algorithm config (diffkin's Reach against panda-gym's PandaReach).

    python -m diffkin.training.compare --config configs/tqc.yaml [--entries ID[:VARIANT] ...] [--seeds 0 1 2]
        [--runs runs] [--out docs/rl] [--name tqc_reach_comparison] [--resume]

Trains every entry of the config (default: all of them) for every seed with :func:`training.train.train`
(one after the other, in this process, on ``torch_threads``), into ``RUNS/<name>/seed<S>`` (``--resume``
reuses a run directory that already holds ``results.json``), measures each env's own speed (random actions on
one ``gymnasium.make`` env) and writes ``OUT/<name>.json`` (per entry: final success, steps and wall-clock to
95 %, training and env steps/s, mean ± std over the seeds, and the per-seed figures), ``OUT/<name>.md`` (the
table) and ``OUT/<name>.png`` (success vs env steps and vs wall-clock, mean ± std over the seeds).
panda-gym's IDs need the ``panda`` extra and TQC the ``contrib`` extra.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from diffkin.training.algos import import_env_package
from diffkin.training.config import RunConfig, entries, load_config
from diffkin.training.plot import _mean_std, _on_grid, summarize
from diffkin.validation import check_count

__all__ = ["env_speed", "run_entry", "compare", "comparison_table", "plot_comparison", "main"]

_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink",
           "tab:olive", "tab:cyan", "tab:gray")  # ten entries before a colour repeats


def env_speed(cfg: RunConfig, steps: int = 2000, seed: int = 0) -> float:
    """Env steps per second (wall-clock) of one ``gymnasium.make(cfg.env_id, **cfg.env_kwargs)`` env under
    uniformly random actions, resets included; ``steps`` >= 1."""
    steps = check_count(steps, "steps")
    import_env_package(cfg.env_id)
    env = gym.make(cfg.env_id, **cfg.env_kwargs)
    env.action_space.seed(seed)
    env.reset(seed=seed)
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - start)
    env.close()
    return rate


def run_entry(cfg: RunConfig, seeds, runs_dir: Path, resume: bool = False, log=print) -> list[dict]:
    """The results of ``cfg`` for every seed: trained into ``runs_dir/<name>/seed<S>`` (or read from there
    with ``resume`` when the run finished before)."""
    from diffkin.training.train import train

    out = []
    for seed in seeds:
        run_dir = runs_dir / cfg.name / f"seed{seed}"
        done = run_dir / "results.json"
        if resume and done.exists():
            out.append(json.loads(done.read_text()))
            log(f"{cfg.name} seed {seed}: reused {done}")
            continue
        out.append(train(cfg.replace(seed=seed), run_dir, progress_bar=False, log=lambda _: None))
        log(f"{cfg.name} seed {seed}: {json.dumps(out[-1]['final'])} in {out[-1]['train_wall_s']} s")
    return out


def _entry_summary(key: str, cfg: RunConfig, runs: list[dict], speed: float) -> dict:
    s = summarize(cfg.name, runs)
    reached = [r for r in runs if r.get("steps_to_success_0.95") is not None]
    s.update({"entry": key, "env_kwargs": cfg.env_kwargs, "env_steps_per_s": speed,
              "seeds_reaching_0.95": len(reached),
              "train_steps_per_s": _mean_std(r.get("train_steps_per_s") for r in runs),
              "eval_wall_s": _mean_std(r.get("eval_wall_s") for r in runs)})
    return s


def compare(config: str | Path, keys: list[str] | None = None, seeds=(0, 1, 2), runs_dir: str | Path = "runs",
            resume: bool = False, speed_steps: int = 2000, log=print) -> dict:
    """Train (or reuse) every entry ``keys`` (default: all of the file's) for every seed and summarise;
    returns ``{"config", "seeds", "entries": [summary per entry], "curves": {entry: per-seed curves}}``."""
    keys = list(keys) if keys else entries(config)
    if not keys:
        raise ValueError(f"{config}: a single-run file; compare needs an algorithm file keyed by env ID")
    cfgs = {k: load_config(config, k) for k in keys}  # every entry checked before any training starts
    summaries, curves = [], {}
    for key, cfg in cfgs.items():
        runs = run_entry(cfg, seeds, Path(runs_dir), resume, log)
        speed = env_speed(cfg, speed_steps)
        summaries.append(_entry_summary(key, cfg, runs, speed))
        curves[key] = [{"seed": r["seed"], "curve": r["curve"]} for r in runs]
    return {"config": str(config), "algo": summaries[0]["algo"], "seeds": list(seeds), "entries": summaries,
            "curves": curves}


def _pm(ms: dict, scale: float = 1.0, digits: int = 0) -> str:
    if ms["mean"] is None:
        return "–"
    return f"{ms['mean'] * scale:,.{digits}f} ± {ms['std'] * scale:,.{digits}f}"


def comparison_table(result: dict) -> str:
    """The markdown table of a :func:`compare` result."""
    lines = ["| env (config entry) | final success | steps to 95 % (seeds reaching it) | wall to 95 % (s) | "
             "train wall (s) | train steps/s | env steps/s |", "|---|---|---|---|---|---|---|"]
    for s in result["entries"]:
        n = len(s["seeds"])
        lines.append(f"| `{s['entry']}` | {_pm(s['final'], 100, 1)} % | {_pm(s['steps_to_success_0.95'])} "
                     f"({s['seeds_reaching_0.95']}/{n}) | {_pm(s['time_to_success_0.95_s'])} | "
                     f"{_pm(s['train_wall_s'])} | {_pm(s['train_steps_per_s'])} | "
                     f"{s['env_steps_per_s']:,.0f} |")
    return "\n".join(lines) + "\n"


def plot_comparison(result: dict, path: Path) -> None:
    """Success rate vs env steps and vs wall-clock, mean ± std over the seeds, one colour per entry."""
    from diffkin.errors import require

    Figure = require("matplotlib.figure", "plot", "training.compare").Figure
    fig = Figure(figsize=(11, 4))
    axes = fig.subplots(1, 2)
    for i, s in enumerate(result["entries"]):
        runs = result["curves"][s["entry"]]
        color = _COLORS[i % len(_COLORS)]
        for ax, x in zip(axes, ("timesteps", "wall_s")):
            hi = max(r["curve"][-1][x] for r in runs)
            grid = np.linspace(min(r["curve"][0][x] for r in runs), hi, 100)
            ys = _on_grid(runs, "success_rate", x, grid)
            mean, std = np.nanmean(ys, axis=0), np.nanstd(ys, axis=0)
            ax.plot(grid, mean, color=color, label=f"{s['entry']} ({len(runs)} seeds)")
            ax.fill_between(grid, mean - std, mean + std, color=color, alpha=0.2)
    for ax, label in zip(axes, ("env steps", "wall-clock (s, training + evaluations)")):
        ax.axhline(0.95, color="k", ls=":", lw=1)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel(label)
        ax.set_ylabel("success rate (deterministic policy)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle(f"{result['algo'].upper()} + HER, one config ({result['config']}); band: ± std over seeds",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", required=True, help="an algorithm file keyed by env ID, e.g. configs/tqc.yaml")
    p.add_argument("--entries", nargs="*", help="ENV_ID or ENV_ID:VARIANT keys (default: all)")
    p.add_argument("--seeds", nargs="*", type=int, default=[0, 1, 2])
    p.add_argument("--runs", default="runs", help="where the run directories go")
    p.add_argument("--out", default="docs/rl", help="where the table, JSON and figure go")
    p.add_argument("--name", default=None, help="file name of the outputs (default <algo>_comparison)")
    p.add_argument("--resume", action="store_true", help="reuse finished run directories")
    p.add_argument("--speed-steps", type=int, default=2000, help="random steps of the env-speed measurement")
    args = p.parse_args(argv)
    torch.set_num_threads(1)  # the command line's choice, as diffkin train's default torch_threads
    result = compare(args.config, args.entries, args.seeds, args.runs, args.resume, args.speed_steps)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = args.name or f"{result['algo']}_comparison"
    (out / f"{name}.json").write_text(json.dumps(result, indent=1))
    table = comparison_table(result)
    (out / f"{name}.md").write_text(table)
    plot_comparison(result, out / f"{name}.png")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
