"""Sweeps with Optuna (training.tune): search spaces, configs, and two workers sharing one SQLite study."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

optuna = pytest.importorskip("optuna")
pytest.importorskip("stable_baselines3")

from diffkin.training.config import load_config  # noqa: E402
from diffkin.training.tune import apply_params, read_sweep, sample_params, show, state_counts  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tune_tiny.yaml"


def test_dotted_paths_set_nested_and_top_level_fields():
    cfg = load_config(TINY)
    new = apply_params(cfg, {"algo_kwargs.learning_rate": 0.01, "total_timesteps": 5,
                             "algo_kwargs.policy_kwargs.net_arch": [8]})
    assert new.algo_kwargs["learning_rate"] == 0.01 and new.total_timesteps == 5
    assert new.algo_kwargs["policy_kwargs"]["net_arch"] == [8]
    assert cfg.algo_kwargs.get("learning_rate") is None  # the base config is untouched
    with pytest.raises(ValueError, match="no such config field"):
        apply_params(cfg, {"learning_rat": 0.1})


def test_sampled_values_follow_the_space():
    space = {"a": {"type": "float", "low": 1e-4, "high": 1e-2, "log": True},
             "b": {"type": "int", "low": 1, "high": 4}, "c": {"type": "categorical", "choices": [8, 16]}}
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(20):
        p = sample_params(study.ask(), space)
        assert 1e-4 <= p["a"] <= 1e-2 and p["b"] in {1, 2, 3, 4} and p["c"] in {8, 16}


def test_bad_search_spaces_are_refused(tmp_path):
    base = yaml.safe_load(TINY.read_text())
    cases = [({"x": {"type": "uniform"}}, "type must be"), ({"x": {"type": "float", "low": 1}}, "needs"),
             ({"x": {"type": "int", "low": 3, "high": 1}}, "low < high"), (None, "mapping")]
    for space, match in cases:
        path = tmp_path / "s.yaml"
        path.write_text(yaml.safe_dump({**base, "search_space": space}))
        with pytest.raises(ValueError, match=match):
            read_sweep(path)


@pytest.mark.slow
def test_two_workers_share_one_sqlite_study(tmp_path):
    """Two processes, 2 trials each, on one SQLite file: 4 distinct trials of the 4-point grid, the 300-step
    ones pruned, the 100-step ones complete, and --show writes the best config."""
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    cmd = [sys.executable, "-m", "diffkin.training.tune", "--config", str(TINY), "--trials", "2",
           "--storage", storage, "--study", "tiny"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    workers = [subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True) for _ in range(2)]
    outs = [w.communicate()[0] for w in workers]
    assert all(w.returncode == 0 for w in workers), outs
    study = optuna.load_study(study_name="tiny", storage=storage)
    numbers = [t.number for t in study.trials]
    assert sorted(numbers) == [0, 1, 2, 3]  # no collision: each trial run once, by one worker
    counts = state_counts(storage, "tiny")
    assert counts.get("complete", 0) >= 1 and counts.get("pruned", 0) >= 1, counts
    for t in study.trials:  # the pruner's rule: only 300-step trials reach a report after the warm-up
        assert (t.state.name == "PRUNED") == (t.params["total_timesteps"] == 300), (t.number, t.params)
    rows, path = show(storage, "tiny", output=tmp_path / "best.yaml")
    assert rows[0]["trial"] == study.best_trial.number
    best = load_config(path)
    assert best.total_timesteps == study.best_trial.params["total_timesteps"]
    assert best.algo_kwargs["learning_rate"] == study.best_trial.params["algo_kwargs.learning_rate"]


def test_the_sweep_is_an_entry_of_the_algorithm_file():
    """configs/sac.yaml's diffkin/Reach-v0:tune: the fast variant's run with a search space and settings."""
    sac = ROOT / "configs" / "sac.yaml"
    cfg, space, settings = read_sweep(sac, "diffkin/Reach-v0", "tune")
    assert cfg.replace(name="x") == load_config(sac, "diffkin/Reach-v0", "fast").replace(name="x")
    assert "algo_kwargs.learning_rate" in space and settings["metric"] == "success_rate"
    for path in space:  # every searched path exists in the run config
        apply_params(cfg, {path: space[path].get("low", (space[path].get("choices") or [None])[0])})
    with pytest.raises(ValueError, match="search_space"):
        read_sweep(sac, "diffkin/Reach-v0", "fast")


@pytest.mark.parametrize(("spec", "match"), [
    ({"type": "float", "low": 0.0, "high": 1.0, "log": True}, "log scale needs low > 0"),
    ({"type": "int", "low": 0.5, "high": 3.5}, "must be an integer"),
    ({"type": "float", "low": 1.0, "high": 2.0, "bogus": 3}, "unknown keys"),
    ({"type": "categorical", "choices": []}, "non-empty list"),
    ({"type": "float", "low": 1.0, "high": 2.0, "step": 0}, "step must be > 0"),
])
def test_distributions_are_checked_before_any_trial(tmp_path, spec, match):
    base = yaml.safe_load(TINY.read_text())
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump({**base, "search_space": {"algo_kwargs.learning_rate": spec}}))
    with pytest.raises(ValueError, match=match):
        read_sweep(path)


def test_a_config_that_does_not_build_fails_before_the_study_is_touched(tmp_path):
    """An option SAC does not take, an unknown metric, a mapping replaced by a number: one error, no trial,
    no storage file."""
    from diffkin.training.tune import tune

    base = yaml.safe_load(TINY.read_text())
    for change, match in [({"search_space": {"algo_kwargs.learning_rat": {"type": "categorical",
                                                                          "choices": [1]}}}, "learning_rat"),
                          ({"tune": {**base["tune"], "metric": "succes"}}, "choose one of"),
                          ({"search_space": {"algo_kwargs": {"type": "int", "low": 1, "high": 2}}},
                           "mapping")]:
        path = tmp_path / "s.yaml"
        path.write_text(yaml.safe_dump({**base, **change}))
        db = tmp_path / "s.db"
        with pytest.raises(ValueError, match=match):
            tune(path, 1, storage=f"sqlite:///{db}", study="s", out=tmp_path / "runs", log=lambda _m: None)
        assert not db.exists()


def test_reading_a_missing_study_creates_nothing(tmp_path):
    with pytest.raises(ValueError, match="no such storage file"):
        show(f"sqlite:///{tmp_path / 'none.db'}", "x")
    assert not (tmp_path / "none.db").exists()
