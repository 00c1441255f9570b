"""Train an SB3 agent on a diffkin env from a YAML config; the run records itself.

    python -m diffkin.training.train --config configs/<algo>.yaml --env ENV_ID [--variant V] [--seed S]
        [--total-timesteps N] [--out DIR]

(``--config`` may also be a single-run file, without ``--env``: a run directory's ``config.yaml``.)

Writes to ``DIR`` (default ``runs/<name>/seed<S>``): ``config.yaml`` (resolved), ``meta.json`` (seed,
versions, command line, timings), TensorBoard logs (``tb/``), ``model.zip`` (+ ``vecnormalize.pkl``) and
``results.json`` (final evaluation, scripted-IK baseline, evaluation curve).
"""

from __future__ import annotations

import argparse
import copy
import json
import pickle
import platform
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
import yaml
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env as sb3_make_vec_env
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

import diffkin.envs  # noqa: F401  (registers the IDs)
from diffkin.envs.vector import TorchVectorEnv
from diffkin.training.algos import ALGOS, EVAL_SEED, algo_class, import_env_package, is_diffkin_env
from diffkin.training.config import RunConfig, load_config
from diffkin.training.evaluate import model_policy, run_episodes, run_vec_episodes, scripted_policy
from diffkin.training.sb3 import make_sb3_vec_env

__all__ = ["ALGOS", "EVAL_SEED", "build_env", "make_eval_env", "build_model", "EvalCallback", "versions",
           "train",
           "resolve_run", "summary_json", "main"]


def build_env(cfg: RunConfig):
    import_env_package(cfg.env_id)
    if cfg.vectorized:
        venv = VecMonitor(make_sb3_vec_env(cfg.env_id, cfg.n_envs, device=cfg.device, **cfg.env_kwargs))
    else:
        venv = sb3_make_vec_env(cfg.env_id, n_envs=cfg.n_envs, seed=cfg.seed, env_kwargs=cfg.env_kwargs)
    venv.seed(cfg.seed)
    if cfg.normalize:
        venv = VecNormalize(venv, **{"norm_obs": True, "norm_reward": True, **cfg.normalize_kwargs})
    return venv


def build_model(cfg: RunConfig, venv, tb_dir: str | None):
    kwargs = copy.deepcopy(cfg.algo_kwargs)  # SB3 mutates policy_kwargs
    if cfg.her is not None:
        kwargs.update(replay_buffer_class=HerReplayBuffer, replay_buffer_kwargs=dict(cfg.her))
    if "action_noise_std" in kwargs:
        dim = venv.action_space.shape[0]
        std = kwargs.pop("action_noise_std")
        kwargs["action_noise"] = NormalActionNoise(np.zeros(dim), std * np.ones(dim))
    policy = "MultiInputPolicy" if isinstance(venv.observation_space, gym.spaces.Dict) else "MlpPolicy"
    return algo_class(cfg.algo)(policy, venv, seed=cfg.seed, device=cfg.device, tensorboard_log=tb_dir,
                                verbose=0, **kwargs)


class EvalCallback(BaseCallback):
    """Batched evaluation every ``eval_freq`` env steps; wall-clock and success-based stopping."""

    def __init__(self, cfg: RunConfig, eval_env, start: float, log=print,
                 out: Path | None = None, on_evaluate=None):
        super().__init__()
        self.cfg, self.eval_env, self.start, self.log, self.out = cfg, eval_env, start, log, out
        self.on_evaluate = on_evaluate
        self.curve: list[dict] = []
        self.next_eval = cfg.eval_freq
        self.stop_reason = "total_timesteps"
        self.eval_s = 0.0  # wall-clock spent in evaluations (part of the run's wall-clock)

    def evaluate(self) -> dict:
        t0 = time.time()
        norm = self.model.get_vec_normalize_env()
        if isinstance(self.eval_env, TorchVectorEnv):
            res = run_episodes(self.eval_env, model_policy(self.model, norm), seed=EVAL_SEED)
        else:  # an env without a batched form (panda-gym): SB3 VecEnv of single envs
            res = run_vec_episodes(self.eval_env, self.model, norm, self.cfg.eval_episodes, EVAL_SEED)
        self.eval_s += time.time() - t0
        point = {"timesteps": int(self.num_timesteps), "wall_s": round(time.time() - self.start, 2), **res}
        self.curve.append(point)
        if self.out is not None:  # partial curve, readable while the run is going
            (self.out / "progress.json").write_text(json.dumps(self.curve, indent=1))
        for k in ("success_rate", "final_distance", "tracking_error"):
            if k in res:
                self.logger.record(f"eval/{k}", res[k])
        self.log(json.dumps(point))
        if self.on_evaluate is not None:  # e.g. a sweep's pruning hook; it may raise to end the run
            self.on_evaluate(point)
        return res

    def _on_step(self) -> bool:
        cfg = self.cfg
        if cfg.max_wall_seconds is not None and time.time() - self.start > cfg.max_wall_seconds:
            self.stop_reason = "max_wall_seconds"
            return False
        if self.num_timesteps < self.next_eval:
            return True
        self.next_eval += cfg.eval_freq
        res = self.evaluate()
        if cfg.stop_success is not None and res.get("success_rate", 0.0) >= cfg.stop_success:
            self.stop_reason = "stop_success"
            return False
        return True


def versions() -> dict:
    import stable_baselines3

    return {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
            "gymnasium": gym.__version__, "stable_baselines3": stable_baselines3.__version__,
            "platform": platform.platform()}


def train(cfg: RunConfig, out: Path, progress_bar: bool = True, log=print, on_evaluate=None) -> dict:
    """Train, evaluate and save; returns the results dict (also written to ``out/results.json``).

    ``on_evaluate(point)`` is called after each evaluation with its curve point (timesteps, wall_s and the
    evaluation's metrics); an exception it raises ends training and propagates (Optuna's pruning).

    Leaves torch's thread count alone: ``cfg.torch_threads`` is applied by the command-line entry points
    (:func:`main`, ``diffkin train``), not here."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    meta = {"seed": cfg.seed, "command": " ".join(sys.argv), "versions": versions(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S")}
    (out / "meta.json").write_text(json.dumps(meta, indent=2))
    try:
        import tensorboard  # noqa: F401

        tb_dir = str(out / "tb")
    except ImportError:
        tb_dir = None
    venv = build_env(cfg)
    eval_env = make_eval_env(cfg)
    model = build_model(cfg, venv, tb_dir)
    start = time.time()
    cb = EvalCallback(cfg, eval_env, start, log, out, on_evaluate)
    try:
        model.learn(cfg.total_timesteps, callback=cb, progress_bar=progress_bar)
    except BaseException as exc:
        venv.close()  # a pruned or interrupted run leaves no env behind, and says why it stopped
        eval_env.close()
        meta["stopped"] = f"{time.strftime('%Y-%m-%dT%H:%M:%S')} {type(exc).__name__}: {exc}"
        (out / "meta.json").write_text(json.dumps(meta, indent=2))
        raise
    train_s = time.time() - start
    if not cb.curve or cb.curve[-1]["timesteps"] != model.num_timesteps:
        cb.evaluate()
    final = {k: v for k, v in cb.curve[-1].items() if k != "wall_s"}
    baseline = run_episodes(eval_env, scripted_policy, seed=EVAL_SEED) if is_diffkin_env(cfg.env_id) else None
    model.save(out / "model.zip")
    if isinstance(venv, VecNormalize):
        (out / "vecnormalize.pkl").write_bytes(pickle.dumps(venv))
    first = next((p for p in cb.curve if p.get("success_rate", 0.0) >= 0.95), {})
    results = {"name": cfg.name, "env_id": cfg.env_id, "algo": cfg.algo, "seed": cfg.seed,
               "timesteps": int(model.num_timesteps), "train_wall_s": round(train_s, 1),
               "eval_wall_s": round(cb.eval_s, 1),
               "train_steps_per_s": round(model.num_timesteps / max(train_s - cb.eval_s, 1e-9), 1),
               "stop_reason": cb.stop_reason, "final": final, "scripted_ik": baseline, "curve": cb.curve,
               "time_to_success_0.95_s": first.get("wall_s"), "steps_to_success_0.95": first.get("timesteps")}
    (out / "results.json").write_text(json.dumps(results, indent=2))
    meta["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    (out / "meta.json").write_text(json.dumps(meta, indent=2))
    venv.close()
    eval_env.close()
    return results


def make_eval_env(cfg: RunConfig):
    """The evaluation env of a run: ``eval_episodes`` diffkin envs as one ``TorchVectorEnv``, or for other
    IDs (panda-gym) an SB3 ``DummyVecEnv`` of ``min(eval_episodes, 10)`` single envs."""
    kwargs = {**cfg.env_kwargs, **cfg.eval_env_kwargs}
    if is_diffkin_env(cfg.env_id):
        return TorchVectorEnv(cfg.env_id, cfg.eval_episodes, **kwargs)
    import_env_package(cfg.env_id)
    return sb3_make_vec_env(cfg.env_id, n_envs=min(cfg.eval_episodes, 10), seed=EVAL_SEED, env_kwargs=kwargs)


def resolve_run(config: str | Path, seed: int | None = None, total_timesteps: int | None = None,
                out: str | Path | None = None, env: str | None = None,
                variant: str | None = None) -> tuple[RunConfig, Path]:
    """The config's entry ``env`` / ``variant`` (see :func:`~diffkin.training.config.load_config`) with the
    command line's overrides, and the run directory (default ``runs/<name>/seed<seed>``)."""
    cfg = load_config(config, env, variant).replace(seed=seed, total_timesteps=total_timesteps)
    return cfg, Path(out) if out else Path("runs") / cfg.name / f"seed{cfg.seed}"


def summary_json(results: dict) -> str:
    """The results without the evaluation curve, as printed at the end of a run."""
    return json.dumps({k: v for k, v in results.items() if k != "curve"}, indent=2)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="Train an SB3 agent on a diffkin env from a YAML config.")
    p.add_argument("--config", required=True, help="configs/<algo>.yaml (with --env) or a single-run file")
    p.add_argument("--env", help="env ID of the config's entry, e.g. diffkin/Reach-v0")
    p.add_argument("--variant", help="variant of the entry, e.g. cartesian (key diffkin/Reach-v0:cartesian)")
    p.add_argument("--seed", type=int)
    p.add_argument("--total-timesteps", type=int)
    p.add_argument("--out")
    p.add_argument("--no-progress", action="store_true", help="disable the progress bar (for log files)")
    args = p.parse_args(argv)
    cfg, out = resolve_run(args.config, seed=args.seed, total_timesteps=args.total_timesteps, out=args.out,
                           env=args.env, variant=args.variant)
    torch.set_num_threads(cfg.torch_threads)  # the command line applies the config's thread count
    res = train(cfg, out, progress_bar=not args.no_progress)
    print(summary_json(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
