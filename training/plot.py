"""Learning curves (mean ± std over seeds) and a results summary from finished runs.

    python -m diffkin.training.plot [RUNS_DIR] [--out runs/results]

For every run group ``RUNS_DIR/<name>/seed*/results.json`` writes ``<out>/<name>.png`` (metric vs env steps
and vs wall-clock), ``<out>/<name>.json`` (per-seed and mean ± std figures) and ``<out>/RESULTS.md``. Seeds
stopped early (``stop_success``) hold their last evaluation for the rest of the common grid.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

__all__ = ["load_groups", "summarize", "plot_group", "main"]


def load_groups(runs_dir: Path) -> dict[str, list[dict]]:
    groups: dict[str, list[dict]] = {}
    for f in sorted(runs_dir.glob("*/seed*/results.json")):
        groups.setdefault(f.parent.parent.name, []).append(json.loads(f.read_text()))
    return groups


def _metric(res: dict) -> str:
    return "success_rate" if "success_rate" in res["final"] else "tracking_error"


def _mean_std(xs) -> dict:
    xs = np.asarray([x for x in xs if x is not None], dtype=float)
    if xs.size == 0:
        return {"mean": None, "std": None, "n": 0}
    return {"mean": float(xs.mean()), "std": float(xs.std(ddof=1)) if xs.size > 1 else 0.0, "n": int(xs.size)}


def summarize(name: str, runs: list[dict]) -> dict:
    key = _metric(runs[0])
    out = {"name": name, "env_id": runs[0]["env_id"], "algo": runs[0]["algo"], "metric": key,
           "seeds": [r["seed"] for r in runs],
           "final": _mean_std(r["final"][key] for r in runs),
           "scripted_ik": _mean_std(r["scripted_ik"][key] for r in runs if r.get("scripted_ik")),
           "timesteps": _mean_std(r["timesteps"] for r in runs),
           "train_wall_s": _mean_std(r["train_wall_s"] for r in runs),
           "per_seed": [{"seed": r["seed"], key: r["final"][key], "timesteps": r["timesteps"],
                         "train_wall_s": r["train_wall_s"], "stop_reason": r["stop_reason"],
                         "steps_to_success_0.95": r.get("steps_to_success_0.95"),
                         "time_to_success_0.95_s": r.get("time_to_success_0.95_s")} for r in runs]}
    if key == "success_rate":
        out["steps_to_success_0.95"] = _mean_std(r.get("steps_to_success_0.95") for r in runs)
        out["time_to_success_0.95_s"] = _mean_std(r.get("time_to_success_0.95_s") for r in runs)
        out["final_distance"] = _mean_std(r["final"].get("final_distance") for r in runs)
    return out


def _on_grid(runs: list[dict], key: str, x: str, grid: np.ndarray) -> np.ndarray:
    ys = []
    for r in runs:
        xs = np.array([p[x] for p in r["curve"]], dtype=float)
        vs = np.array([p[key] for p in r["curve"]], dtype=float)
        ys.append(np.interp(grid, xs, vs, left=np.nan, right=vs[-1]))
    return np.array(ys)


def plot_group(name: str, runs: list[dict], path: Path) -> None:
    from diffkin.errors import require

    Figure = require("matplotlib.figure", "plot", "training.plot").Figure  # file output: no pyplot

    key = _metric(runs[0])
    fig = Figure(figsize=(10, 3.6))
    axes = fig.subplots(1, 2)
    for ax, x, label in zip(axes, ("timesteps", "wall_s"), ("env steps", "wall-clock (s)")):
        hi = max(r["curve"][-1][x] for r in runs)
        lo = min(r["curve"][0][x] for r in runs)
        grid = np.linspace(lo, hi, 100)
        ys = _on_grid(runs, key, x, grid)
        mean, std = np.nanmean(ys, axis=0), np.nanstd(ys, axis=0)
        ax.plot(grid, mean, color="tab:blue", label=f"{runs[0]['algo'].upper()} (mean of {len(runs)} seeds)")
        ax.fill_between(grid, mean - std, mean + std, color="tab:blue", alpha=0.25, label="± std")
        base = [r["scripted_ik"][key] for r in runs if r.get("scripted_ik")]  # none for panda-gym's envs
        if base:
            ax.axhline(np.mean(base), color="tab:green", ls="--", label="scripted IK (upper bound)")
        if key == "success_rate":
            ax.axhline(0.95, color="tab:red", ls=":", lw=1, label="95 %")
            ax.set_ylim(-0.02, 1.02)
        else:
            ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel(key.replace("_", " ") + (" (m)" if key == "tracking_error" else ""))
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="best")
    fig.suptitle(f"{name}: {runs[0]['env_id']}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _fmt(ms: dict, scale: float = 1.0, digits: int = 3) -> str:
    if ms["mean"] is None:
        return "–"
    return f"{ms['mean'] * scale:.{digits}f} ± {ms['std'] * scale:.{digits}f}"


def write_markdown(summaries: list[dict], path: Path) -> None:
    lines = ["# diffkin RL baselines (measured)", "",
             "| run | env | algo | seeds | final metric (mean ± std) | scripted IK | steps to 95 % | "
             "wall to 95 % (s) | train wall (s) |", "|---|---|---|---|---|---|---|---|---|"]
    for s in summaries:
        if s["metric"] == "success_rate":
            fin, ik = f"success {_fmt(s['final'], 100, 1)} %", f"{_fmt(s['scripted_ik'], 100, 1)} %"
            steps, wall = _fmt(s["steps_to_success_0.95"], 1, 0), _fmt(s["time_to_success_0.95_s"], 1, 0)
        else:
            fin = f"tracking error {_fmt(s['final'], 1000, 1)} mm"
            ik, steps, wall = f"{_fmt(s['scripted_ik'], 1000, 2)} mm", "–", "–"
        head = f"| {s['name']} | {s['env_id']} | {s['algo']} | {len(s['seeds'])} |"
        lines.append(f"{head} {fin} | {ik} | {steps} | {wall} | {_fmt(s['train_wall_s'], 1, 0)} |")
    lines += ["", "Per-seed figures: `<run>.json`; learning curves: `<run>.png`."]
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs_dir", nargs="?", default="runs")
    p.add_argument("--out", default="runs/results")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summaries = []
    for name, runs in load_groups(Path(args.runs_dir)).items():
        s = summarize(name, runs)
        summaries.append(s)
        (out / f"{name}.json").write_text(json.dumps(s, indent=2))
        plot_group(name, runs, out / f"{name}.png")
        print(f"{name}: {s['metric']} {_fmt(s['final'])} over seeds {s['seeds']}")
    write_markdown(summaries, out / "RESULTS.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
