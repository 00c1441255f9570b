"""``diffkin demo`` sections: a short PPO run on the batched Reach environment."""

from __future__ import annotations

import json
import traceback

from ._common import REPO_ROOT, Report, _figure, _md_table

__all__ = ["section_rl"]


def section_rl(report: Report, seconds: int) -> None:
    import yaml

    cfg_path = REPO_ROOT / "configs" / "ppo.yaml"
    if not cfg_path.exists():
        report.add("RL (PPO on batched Reach)", "Skipped: run from a clone of the diffkin repository.")
        return
    try:
        from diffkin.training.config import load_config, read_entry
        from diffkin.training.train import train
    except ImportError as exc:
        report.add(
            "RL (PPO on batched Reach)",
            f"Skipped: the training code is not importable ({exc}); install the `rl` extra "
            "(`pip install -e '.[rl]'`) and run from a clone of the diffkin repository.",
        )
        return
    cfg = read_entry(cfg_path, env="diffkin/Reach-v0", variant="cartesian")  # PPO, Cartesian actions
    cfg["max_wall_seconds"] = seconds
    cfg["eval_freq"] = min(int(cfg.get("eval_freq", 100_000)), 50_000)
    run_dir = report.out / "rl"
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "demo_config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    try:
        train(load_config(run_dir / "demo_config.yaml"), run_dir, progress_bar=False, log=lambda line: None)
    except Exception:  # the report records the failure and the tour goes on
        report.failures.append("RL training failed: " + traceback.format_exc()[-2000:])
        report.add("RL (PPO on batched Reach)", "Training failed; see the console output.")
        return
    res = json.loads((run_dir / "results.json").read_text())
    final = res["final"]
    fig = _figure(figsize=(6, 3.4))
    ax = fig.subplots()
    xs = [p["wall_s"] for p in res["curve"]]
    ys = [p.get("success_rate", 0) * 100 for p in res["curve"]]
    ax.plot(xs, ys, marker="o")
    ax.set_xlabel("wall-clock [s]")
    ax.set_ylabel("success rate [%]")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(report.out / "rl_curve.png", dpi=110)
    body = (
        f"PPO on `diffkin/Reach-v0` (Panda, {cfg['n_envs']} torch-batched envs, Cartesian actions), "
        f"{seconds} s wall-clock budget on this machine.\n\n"
        + _md_table(
            ["timesteps", "train time [s]", "success rate (sparse, 0.05 m)", "scripted IK baseline"],
            [
                [
                    res["timesteps"],
                    res["train_wall_s"],
                    f"{final.get('success_rate', 0) * 100:.1f} %",
                    f"{res['scripted_ik'].get('success_rate', 0) * 100:.1f} %",
                ]
            ],
        )
        + "\n\n![learning curve](rl_curve.png)\n"
    )
    report.add("RL (PPO on batched Reach)", body)
