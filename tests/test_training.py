"""Training pipeline: configs load, a short SB3 smoke run of every config, evaluation of the saved run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from training.config import RunConfig, load_config

CONFIGS = sorted(Path(__file__).resolve().parents[1].joinpath("configs").glob("*.yaml"))
RUN_CONFIGS = [p for p in CONFIGS if "algo" in p.read_text()]


def _small(cfg: RunConfig) -> RunConfig:
    """The same run, a few hundred env steps long, with tiny batches."""
    kw = dict(cfg.algo_kwargs)
    if cfg.algo == "ppo":
        kw.update(n_steps=16, batch_size=64, n_epochs=1)
    else:
        kw.update(learning_starts=100, batch_size=32, buffer_size=2000)
    n_envs = min(cfg.n_envs, 8)
    return cfg.replace(total_timesteps=300 if cfg.algo != "ppo" else 16 * n_envs * 2, n_envs=n_envs,
                       algo_kwargs=kw, eval_freq=10**9, eval_episodes=4, max_wall_seconds=120)


def test_there_are_run_configs():
    names = {p.stem for p in RUN_CONFIGS}
    assert {"sac_her_reach_panda", "sac_her_reach_panda_cartesian", "ppo_batched_reach_panda"} <= names
    assert any("track" in n for n in names)


@pytest.mark.parametrize("path", RUN_CONFIGS, ids=lambda p: p.stem)
def test_config_loads_and_is_frozen(path):
    cfg = load_config(path)
    assert cfg.env_id.startswith("diffkin/") and cfg.total_timesteps > 0
    with pytest.raises(AttributeError):
        cfg.seed = 3  # type: ignore[misc]


def test_unknown_config_key_is_an_error(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("env_id: diffkin/Reach-v0\nalgo: sac\ntotal_timesteps: 10\nlearning_rat: 0.1\n")
    with pytest.raises(ValueError, match="learning_rat"):
        load_config(p)
    with pytest.raises(ValueError, match="HER"):
        RunConfig(name="x", env_id="diffkin/Reach-v0", algo="ppo", total_timesteps=1, her={})


@pytest.mark.parametrize("path", RUN_CONFIGS, ids=lambda p: p.stem)
def test_smoke_run_and_evaluate(path, tmp_path):
    from training.evaluate import evaluate_run
    from training.train import train

    threads = torch.get_num_threads()
    cfg = _small(load_config(path))
    res = train(cfg, tmp_path, progress_bar=False, log=lambda s: None)
    torch.set_num_threads(threads)
    for name in ("config.yaml", "meta.json", "model.zip", "results.json"):
        assert (tmp_path / name).is_file(), name
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["timesteps"] == res["timesteps"] >= cfg.total_timesteps
    assert load_config(tmp_path / "config.yaml") == cfg
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["seed"] == cfg.seed and "torch" in meta["versions"]
    key = "success_rate" if cfg.env_id == "diffkin/Reach-v0" else "tracking_error"
    assert 0.0 <= res["final"][key] and key in res["scripted_ik"]
    ev = evaluate_run(tmp_path, episodes=4)
    assert key in ev["policy"] and key in ev["scripted_ik"]
    if key == "success_rate":
        assert ev["scripted_ik"]["success_rate"] >= 0.75  # the IK baseline is an upper bound
    else:
        assert ev["scripted_ik"]["tracking_error"] < 0.01
