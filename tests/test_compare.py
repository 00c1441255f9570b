"""The comparison runner (training.compare) and the robustness check (training.robustness).

The diffkin-only tests run without the optional extras; the panda-gym one skips cleanly without them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml

from diffkin.training.compare import compare, comparison_table, env_speed, main, plot_comparison
from diffkin.training.config import entries as config_entries
from diffkin.training.config import load_config

ROOT = Path(__file__).resolve().parents[1]
_TINY = dict(total_timesteps=300, n_envs=1, eval_freq=100, eval_episodes=4,
             algo_kwargs=dict(learning_starts=100, batch_size=32, buffer_size=2000,
                              policy_kwargs=dict(net_arch=[16, 16])),
             her=dict(n_sampled_goal=2, goal_selection_strategy="future"))


def _config(tmp_path, entries: dict) -> Path:
    path = tmp_path / "sac.yaml"
    path.write_text(yaml.safe_dump(entries, sort_keys=False))
    return path


def _keep_threads(fn, *args, **kwargs):
    threads = torch.get_num_threads()
    try:
        return fn(*args, **kwargs)
    finally:
        torch.set_num_threads(threads)


def test_compare_diffkin_entries(tmp_path):
    env = dict(robot="three_link_planar", episode_steps=10, distance_threshold=0.2)
    cart = {**env, "action_mode": "cartesian"}
    cfg = _config(tmp_path, {"diffkin/Reach-v0": {**_TINY, "env_kwargs": env},
                             "diffkin/Reach-v0:cartesian": {**_TINY, "env_kwargs": cart}})
    runs = tmp_path / "runs"
    res = compare(cfg, seeds=(0, 1), runs_dir=runs, speed_steps=50, log=lambda s: None)
    assert [s["entry"] for s in res["entries"]] == ["diffkin/Reach-v0", "diffkin/Reach-v0:cartesian"]
    for s in res["entries"]:
        assert s["seeds"] == [0, 1] and s["env_steps_per_s"] > 0 and s["final"]["n"] == 2
        assert 0.0 <= s["final"]["mean"] <= 1.0 and s["train_steps_per_s"]["mean"] > 0
        assert 0 <= s["seeds_reaching_0.95"] <= 2
        for seed in (0, 1):
            saved = json.loads((runs / s["name"] / f"seed{seed}" / "results.json").read_text())
            assert saved["timesteps"] >= 300 and saved["curve"][-1]["timesteps"] == saved["timesteps"]
        assert [c["seed"] for c in res["curves"][s["entry"]]] == [0, 1]
    table = comparison_table(res)
    assert table.count("\n") == 4 and "`diffkin/Reach-v0:cartesian`" in table
    plot_comparison(res, tmp_path / "c.png")
    assert (tmp_path / "c.png").stat().st_size > 10_000
    # --resume reuses the finished runs: the same figures, nothing trained again
    mtime = (runs / "sac_Reach-v0" / "seed0" / "results.json").stat().st_mtime
    again = compare(cfg, ["diffkin/Reach-v0"], seeds=(0, 1), runs_dir=runs, resume=True, speed_steps=50,
                    log=lambda s: None)
    assert again["entries"][0]["final"] == res["entries"][0]["final"]
    assert (runs / "sac_Reach-v0" / "seed0" / "results.json").stat().st_mtime == mtime


def test_compare_command_writes_table_json_figure(tmp_path):
    env = dict(robot="three_link_planar", episode_steps=10)
    cfg = _config(tmp_path, {"diffkin/Reach-v0": {**_TINY, "env_kwargs": env}})
    out = tmp_path / "out"
    assert _keep_threads(main, ["--config", str(cfg), "--seeds", "3", "--runs", str(tmp_path / "runs"),
                                "--out", str(out), "--speed-steps", "20"]) == 0
    data = json.loads((out / "sac_comparison.json").read_text())
    assert data["seeds"] == [3] and data["entries"][0]["entry"] == "diffkin/Reach-v0"
    assert (out / "sac_comparison.png").is_file()
    assert "| `diffkin/Reach-v0` |" in (out / "sac_comparison.md").read_text()


def test_compare_refuses_bad_input(tmp_path):
    single = tmp_path / "run.yaml"
    single.write_text("env_id: diffkin/Reach-v0\nalgo: sac\ntotal_timesteps: 10\n")
    with pytest.raises(ValueError, match="single-run"):
        compare(single)
    cfg = _config(tmp_path, {"diffkin/Reach-v0": {**_TINY, "learning_rat": 1}})
    with pytest.raises(ValueError, match="learning_rat"):  # every entry checked before any training
        compare(cfg, runs_dir=tmp_path / "runs")
    assert not (tmp_path / "runs").exists()
    with pytest.raises(ValueError, match="steps"):
        env_speed(load_config(ROOT / "configs" / "tqc.yaml", "diffkin/Reach-v0"), steps=0)


def test_tqc_config_is_one_algorithm_config_for_every_env():
    """configs/tqc.yaml: rl-zoo's PandaReach settings for every entry; the diffkin entries set up as
    PandaReach (goal cube, threshold, episode length, neutral start, panda-gym's observation; 0.025 rad or
    0.05 m per step)."""
    path = ROOT / "configs" / "tqc.yaml"
    keys = ["PandaReach-v3", "PandaReach-v3:joints", "diffkin/Reach-v0", "diffkin/Reach-v0:joint_obs",
            "diffkin/Reach-v0:step_0.05", "diffkin/Reach-v0:cartesian", "diffkin/Reach-v0:dr",
            "diffkin/Reach-v0:joint_obs_dr"]
    assert config_entries(path) == keys
    cfgs = {k: load_config(path, k) for k in keys}
    zoo = cfgs["PandaReach-v3"]
    assert zoo.algo == "tqc" and zoo.total_timesteps == 20000 and zoo.normalize
    assert zoo.algo_kwargs["policy_kwargs"] == {"net_arch": [64, 64], "n_critics": 1}
    for c in cfgs.values():
        assert (c.algo_kwargs, c.her, c.total_timesteps, c.normalize_kwargs) == (
            zoo.algo_kwargs, zoo.her, zoo.total_timesteps, zoo.normalize_kwargs)
    reach = cfgs["diffkin/Reach-v0"].env_kwargs
    assert reach["goal_center"] == [0.6, 0.0, 0.255] and reach["goal_range"] == 0.3
    assert reach["distance_threshold"] == 0.05 and reach["episode_steps"] == 50
    assert reach["robot_config"]["max_joint_speed"] * 0.1 == pytest.approx(0.025)
    assert reach["observation"] == ["ee_position", "ee_velocity"]
    ablation = {**reach, "observation": ["joint_positions", "ee_position"]}
    assert cfgs["diffkin/Reach-v0:joint_obs"].env_kwargs == ablation
    coarse = {**reach, "robot_config": {"max_joint_speed": 0.5}}
    assert cfgs["diffkin/Reach-v0:step_0.05"].env_kwargs == coarse
    assert cfgs["diffkin/Reach-v0:cartesian"].env_kwargs["robot_config"] == {"max_ee_step": 0.05}
    dr = cfgs["diffkin/Reach-v0:dr"].env_kwargs
    assert dr == {**reach, "robot_config": {**reach["robot_config"], "geometry_noise_length": 0.04,
                                            "geometry_noise_angle": 0.08}}
    assert cfgs["diffkin/Reach-v0:joint_obs_dr"].env_kwargs == {**dr, "observation": ablation["observation"]}


def test_compare_panda_gym(tmp_path):
    pytest.importorskip("panda_gym", reason="panda-gym's IDs need the panda extra")
    pytest.importorskip("sb3_contrib", reason="TQC needs the contrib extra")
    zoo = load_config(ROOT / "configs" / "tqc.yaml", "PandaReach-v3")
    entry = {**_TINY, "algo": "tqc", "normalize": True, "env_kwargs": zoo.env_kwargs,
             "algo_kwargs": {**_TINY["algo_kwargs"], "policy_kwargs": {"net_arch": [16, 16], "n_critics": 1}}}
    cfg = _config(tmp_path, {"PandaReach-v3": entry})
    res = _keep_threads(compare, cfg, seeds=(0,), runs_dir=tmp_path / "runs", speed_steps=20,
                        log=lambda s: None)
    s = res["entries"][0]
    assert s["algo"] == "tqc" and s["env_steps_per_s"] > 0 and 0.0 <= s["final"]["mean"] <= 1.0
    assert s["scripted_ik"]["n"] == 0  # no scripted baseline for panda-gym's envs
