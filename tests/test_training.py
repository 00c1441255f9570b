"""Training pipeline: configs load, a short SB3 smoke run of every config, evaluation of the saved run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml

from diffkin.errors import ConventionError
from diffkin.training.algos import EVAL_SEED
from diffkin.training.config import RunConfig, entries, load_config, read_entry

ROOT = Path(__file__).resolve().parents[1]
ALGO_FILES = sorted(ROOT.joinpath("configs").glob("*.yaml"))
#: (file, env ID, variant) of every entry of configs/<algo>.yaml
RUN_CONFIGS = [(p, *(k.split(":", 1) if ":" in k else (k, None))) for p in ALGO_FILES for k in entries(p)]


def _id(case) -> str:
    path, env, variant = case
    return f"{path.stem}-{env.split('/')[-1]}" + (f"-{variant}" if variant else "")


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
    assert [p.name for p in ALGO_FILES] == ["ppo.yaml", "sac.yaml", "tqc.yaml"]
    keys = {f"{p.stem} {e}" + (f":{v}" if v else "") for p, e, v in RUN_CONFIGS}
    assert {"sac diffkin/Reach-v0", "sac diffkin/Reach-v0:cartesian", "ppo diffkin/Reach-v0:cartesian",
            "ppo diffkin/Track-v0", "sac diffkin/Track-v0"} <= keys


@pytest.mark.parametrize("case", RUN_CONFIGS, ids=_id)
def test_config_loads_and_is_frozen(case):
    path, env, variant = case
    cfg = load_config(path, env=env, variant=variant)
    assert cfg.env_id == env and cfg.algo == path.stem and cfg.total_timesteps > 0
    assert cfg.name == f"{path.stem}_{env.split('/')[-1]}" + (f"_{variant}" if variant else "")
    assert load_config(path, env=f"{env}:{variant}" if variant else env) == cfg
    with pytest.raises(AttributeError):
        cfg.seed = 3  # type: ignore[misc]


def test_variants_share_settings_through_anchors():
    """The variants differ from their base entry in what they name, the rest comes from the anchors."""
    sac = ROOT / "configs" / "sac.yaml"
    base, cart = load_config(sac, "diffkin/Reach-v0"), load_config(sac, "diffkin/Reach-v0", "cartesian")
    fast = load_config(sac, "diffkin/Reach-v0", "fast")
    long = load_config(sac, "diffkin/Reach-v0", "fast_long")
    assert cart.env_kwargs["action_mode"] == "cartesian" and base.env_kwargs["action_mode"] == "joint"
    assert cart.algo_kwargs == base.algo_kwargs and cart.her == base.her
    assert fast.env_kwargs["robot_config"] == {"max_joint_speed": 1.0}
    assert fast.algo_kwargs == {**base.algo_kwargs, "train_freq": 1}
    assert long.replace(name="x", total_timesteps=1, stop_success=1.0, max_wall_seconds=1.0) == fast.replace(
        name="x", total_timesteps=1, stop_success=1.0, max_wall_seconds=1.0)
    assert "search_space" in read_entry(sac, "diffkin/Reach-v0", "tune")
    assert load_config(sac, "diffkin/Reach-v0", "tune").replace(name="x") == fast.replace(name="x")
    # each entry is its own copy: changing one does not reach another through a shared anchor
    a, b = read_entry(sac, "diffkin/Reach-v0"), read_entry(sac, "diffkin/Reach-v0", "cartesian")
    a["her"]["n_sampled_goal"] = 99
    assert b["her"]["n_sampled_goal"] == 4


def test_entry_selection_errors(tmp_path):
    sac = ROOT / "configs" / "sac.yaml"
    with pytest.raises(ValueError, match="--env"):
        load_config(sac)
    with pytest.raises(ValueError, match="no entry 'diffkin/Reach-v0:nope'.*diffkin/Reach-v0:cartesian"):
        load_config(sac, "diffkin/Reach-v0", "nope")
    single = tmp_path / "run.yaml"
    single.write_text("env_id: diffkin/Reach-v0\nalgo: sac\ntotal_timesteps: 10\n")
    assert load_config(single).name == "run" and load_config(single, env="diffkin/Reach-v0").algo == "sac"
    with pytest.raises(ValueError, match="single-run"):
        load_config(single, "diffkin/Reach-v0", "fast")
    mine = tmp_path / "mine.yaml"
    mine.write_text("diffkin/Reach-v0:\n  total_timesteps: 10\n")
    with pytest.raises(ValueError, match="sets no algo"):
        load_config(mine, "diffkin/Reach-v0")
    mine.write_text("diffkin/Reach-v0:\n  algo: ppo\n  total_timesteps: 10\n  learning_rat: 1\n")
    with pytest.raises(ValueError, match="learning_rat"):
        load_config(mine, "diffkin/Reach-v0")


def test_readme_maps_every_old_name_to_an_entry():
    """configs/README.md's table of old names (the results in docs/rl/) names existing entries."""
    text = (ROOT / "configs" / "README.md").read_text()
    rows = [ln.split("|")[1:5] for ln in text.splitlines() if ln.startswith("| `") and ln.count("|") == 5]
    results = {p.stem for p in (ROOT / "docs" / "rl").glob("*.json")}
    old = set()
    for old_file, file, env, variant in rows:
        variant = variant.strip().strip("`")
        load_config(ROOT / "configs" / file.strip().strip("`"), env.strip().strip("`"),
                    None if variant == "—" else variant)
        old.add(old_file.strip().split("`")[1].removesuffix(".yaml"))
    # results of the current configs are named by their entries (<algo>_<env name>[_<variant>]); the
    # comparison runner and the robustness check write <algo>_comparison and dr_robustness
    current = {load_config(p, e, v).name for p, e, v in RUN_CONFIGS}
    current |= {"tqc_comparison", "dr_robustness", "dr_robustness_large"}
    assert results <= old | current, results - old - current


def test_unknown_config_key_is_an_error(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("env_id: diffkin/Reach-v0\nalgo: sac\ntotal_timesteps: 10\nlearning_rat: 0.1\n")
    with pytest.raises(ValueError, match="learning_rat"):
        load_config(p)
    with pytest.raises(ValueError, match="HER"):
        RunConfig(name="x", env_id="diffkin/Reach-v0", algo="ppo", total_timesteps=1, her={})


@pytest.mark.parametrize("case", RUN_CONFIGS, ids=_id)
def test_smoke_run_and_evaluate(case, tmp_path):
    from diffkin.training.algos import is_diffkin_env
    from diffkin.training.evaluate import evaluate_run
    from diffkin.training.train import train

    threads = torch.get_num_threads()
    path, env, variant = case
    cfg = _small(load_config(path, env=env, variant=variant))
    if cfg.algo == "tqc":
        pytest.importorskip("sb3_contrib", reason="TQC needs the contrib extra")
    if not is_diffkin_env(cfg.env_id):
        pytest.importorskip("panda_gym", reason="panda-gym's IDs need the panda extra")
    res = train(cfg, tmp_path, progress_bar=False, log=lambda s: None)
    torch.set_num_threads(threads)
    for name in ("config.yaml", "meta.json", "model.zip", "results.json"):
        assert (tmp_path / name).is_file(), name
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["timesteps"] == res["timesteps"] >= cfg.total_timesteps
    assert load_config(tmp_path / "config.yaml") == cfg
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["seed"] == cfg.seed and "torch" in meta["versions"]
    if not is_diffkin_env(cfg.env_id):  # panda-gym: evaluated on its own envs, no scripted baseline
        assert res["scripted_ik"] is None and res["final"]["episodes"] == cfg.eval_episodes
        assert 0.0 <= res["final"]["success_rate"] <= 1.0 and res["final"]["final_distance"] > 0.0
        return
    key = "success_rate" if cfg.env_id == "diffkin/Reach-v0" else "tracking_error"
    # the saved run, evaluated again on the training's evaluation episodes, reproduces the recorded figures
    # (deterministic policy, same seeds): what results.json reports is what the saved model does
    ev = evaluate_run(tmp_path, episodes=cfg.eval_episodes, seed=EVAL_SEED)
    final = {k: v for k, v in res["final"].items() if k != "timesteps"}
    assert set(final) == set(ev["policy"]) and final["episodes"] == cfg.eval_episodes
    for k, v in ev["policy"].items():
        assert final[k] == pytest.approx(v, rel=1e-6, abs=1e-9), k
    for k, v in ev["scripted_ik"].items():
        assert res["scripted_ik"][k] == pytest.approx(v, rel=1e-6, abs=1e-9), k
    if key == "success_rate":
        assert final[key] * cfg.eval_episodes == pytest.approx(round(final[key] * cfg.eval_episodes))
        assert ev["scripted_ik"]["success_rate"] >= 0.75  # the IK baseline is an upper bound
        # a config whose env no longer gives the policy's observations (a run from before the observation
        # option, whose default changed) is refused with the fix, not evaluated on the wrong inputs
        other = ["ee_velocity"] if cfg.env_kwargs.get("observation") == ["ee_position"] else ["ee_position"]
        stale = {**cfg.to_dict(), "env_kwargs": {**cfg.env_kwargs, "observation": other}}
        (tmp_path / "config.yaml").write_text(yaml.safe_dump(stale, sort_keys=False))
        with pytest.raises(ConventionError, match="joint_positions, ee_position"):
            evaluate_run(tmp_path, episodes=2)
    else:
        assert ev["scripted_ik"]["tracking_error"] < 0.01


@pytest.mark.parametrize("env_id", ["diffkin/Reach-v0", "diffkin/Track-v0"])
def test_run_episodes_rates_are_those_of_the_episodes(env_id):
    """run_episodes' figures, recomputed from each env's own first episode (stepped here one by one)."""
    import numpy as np

    from diffkin.envs.vector import TorchVectorEnv
    from diffkin.training.evaluate import run_episodes, scripted_policy

    kw = dict(robot="three_link_planar", episode_steps=12)
    if env_id == "diffkin/Reach-v0":
        kw.update(distance_threshold=0.02, init_noise=0.5, goal_sampling="joints")  # some fail in 12 steps
    n, seed = 6, 123
    out = run_episodes(TorchVectorEnv(env_id, n, **kw), scripted_policy, seed=seed)
    venv = TorchVectorEnv(env_id, n, **kw)
    obs, _ = venv.reset(seed=seed)
    success, dist, err = [None] * n, [None] * n, [[] for _ in range(n)]
    while any(s is None for s in (success if "Reach" in env_id else dist)):
        obs, _, term, trunc, info = venv.step(scripted_policy(obs, venv))
        for i in range(n):
            if (success if "Reach" in env_id else dist)[i] is not None:
                continue
            if "tracking_error" in info:
                err[i].append(float(info["tracking_error"][i]))
            if bool(term[i] | trunc[i]):
                if "is_success" in info:
                    success[i], dist[i] = bool(info["is_success"][i]), float(info["distance"][i])
                else:
                    dist[i] = 0.0  # episode over
    assert out["episodes"] == n
    if "Reach" in env_id:
        assert 0 < sum(success) < n, "pick settings where the rate is informative"
        assert out["success_rate"] == pytest.approx(sum(success) / n)
        assert out["final_distance"] == pytest.approx(np.mean(dist), rel=1e-5)
    else:
        per_ep = [np.mean(e) for e in err]
        assert out["tracking_error"] == pytest.approx(np.mean(per_ep), rel=1e-5)
        assert out["tracking_error_std"] == pytest.approx(np.std(per_ep, ddof=1), rel=1e-4)
