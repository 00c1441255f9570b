"""Evaluate a trained run (batched, on the torch vector env) against a scripted IK baseline.

    python -m diffkin.training.evaluate RUN_DIR [--episodes N] [--seed S]

The scripted baseline is closed-loop inverse kinematics with diffkin's damped-least-squares step
(the env's own Cartesian mapping): each step it commands Δx = target − p_ee (goal for Reach, next path
point for Track), converted to the env's action space and clipped. It knows the goal/path exactly, so it is
an upper bound for a policy rather than a competitor.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from diffkin.envs.vector import TorchVectorEnv

__all__ = ["run_episodes", "run_vec_episodes", "scripted_policy", "model_policy", "load_run", "evaluate_run",
           "evaluate_and_save",
           "main"]

Policy = Callable[[object, TorchVectorEnv], object]


def run_episodes(venv: TorchVectorEnv, policy: Policy, seed: int = 10_000) -> dict:
    """One episode in each of the ``venv.num_envs`` envs. Success and final distance are taken at each
    env's first episode end; tracking error is the mean over that episode's steps (and envs)."""
    obs, _ = venv.reset(seed=seed)
    n = venv.num_envs
    finished = torch.zeros(n, dtype=torch.bool, device=venv.device)
    success = torch.zeros(n, dtype=torch.bool, device=venv.device)
    dist = torch.zeros(n, device=venv.device)
    err_sum = torch.zeros(n, device=venv.device)
    steps = torch.zeros(n, device=venv.device)
    while not bool(finished.all()):
        obs, _, term, trunc, info = venv.step(policy(obs, venv))
        live = ~finished
        if "tracking_error" in info:
            err_sum += torch.where(live, info["tracking_error"].float(), 0.0)
        steps += live.float()
        done = (term | trunc) & live
        if "is_success" in info:
            success |= done & info["is_success"]
            dist = torch.where(done, info["distance"].float(), dist)
        finished |= done
    out = {"episodes": n}
    if "is_success" in info:
        out.update(success_rate=float(success.float().mean()), final_distance=float(dist.mean()))
    if "tracking_error" in info:
        per_ep = err_sum / steps
        out.update(tracking_error=float(per_ep.mean()), tracking_error_std=float(per_ep.std()))
    return out


def run_vec_episodes(venv, model, obs_normalizer=None, episodes: int = 100, seed: int = 10_000) -> dict:
    """``episodes`` episodes of a deterministic SB3 ``model`` on an SB3 ``VecEnv`` of any Gymnasium env
    (e.g. panda-gym's, which has no batched form): the first ``episodes`` episode ends count. Success is
    ``info["is_success"]`` at the end; the final distance ``‖achieved_goal − desired_goal‖`` (m) of the
    terminal observation where the env is goal-conditioned. ``venv`` is seeded with ``seed`` first."""
    venv.seed(seed)
    obs = venv.reset()
    success: list[bool] = []
    dist: list[float] = []
    while len(success) < episodes:
        inp = obs_normalizer.normalize_obs(obs) if obs_normalizer is not None else obs
        action, _ = model.predict(inp, deterministic=True)
        obs, _, done, infos = venv.step(action)
        for i in np.flatnonzero(done):
            info = infos[i]
            success.append(bool(info.get("is_success", False)))
            term = info.get("terminal_observation")
            if isinstance(term, dict) and "achieved_goal" in term:
                dist.append(float(np.linalg.norm(term["achieved_goal"] - term["desired_goal"])))
    out = {"episodes": episodes, "success_rate": float(np.mean(success[:episodes]))}
    if dist:
        out["final_distance"] = float(np.mean(dist[:episodes]))
    return out


def scripted_policy(obs, venv: TorchVectorEnv) -> torch.Tensor:
    """Closed-loop IK with diffkin's damped-least-squares step, in the env's action space; for a task that
    knows its reference motion (``reference_action``: ``diffkin/Imitate-v0``), the step onto the next
    reference frame."""
    task, state = venv.task, venv.state
    if hasattr(task, "reference_action"):
        return task.reference_action(state)
    robot = task.robot
    ee = task.ee(state)  # the episode's robot (domain randomisation); its DLS step uses the nominal model
    target = state["goal"] if "goal" in state else task.targets(state, offset=1)[:, 0]
    dx = target - ee
    if robot.action_mode == "cartesian":
        a = dx / robot.config.max_ee_step
        return a / a.abs().amax(dim=-1, keepdim=True).clamp(min=1.0)
    return (robot.cartesian_delta(state["q"], dx) / robot.step_limit).clamp(-1.0, 1.0)


def model_policy(model, obs_normalizer=None) -> Policy:
    """Deterministic SB3 policy on batched torch observations."""

    def act(obs, venv):
        obs_np = {k: v.cpu().numpy() for k, v in obs.items()} if isinstance(obs, dict) else obs.cpu().numpy()
        if obs_normalizer is not None:
            obs_np = obs_normalizer.normalize_obs(obs_np)
        action, _ = model.predict(obs_np, deterministic=True)
        return torch.as_tensor(action, dtype=torch.float32)

    return act


def load_run(run_dir: str | Path):
    """(config, model, VecNormalize or None) of a finished run directory."""
    from diffkin.training.algos import algo_class
    from diffkin.training.config import load_config

    run_dir = Path(run_dir)
    cfg = load_config(run_dir / "config.yaml")
    _check_observation_space(run_dir, cfg)
    env = None
    if cfg.her is not None:  # SB3 rebuilds the HerReplayBuffer on load and needs an env for it
        from diffkin.training.sb3 import make_sb3_vec_env

        env = make_sb3_vec_env(cfg.env_id, 1, **cfg.env_kwargs)
    model = algo_class(cfg.algo).load(run_dir / "model.zip", env=env, device="cpu")
    norm = None
    if (run_dir / "vecnormalize.pkl").exists():
        import pickle

        norm = pickle.loads((run_dir / "vecnormalize.pkl").read_bytes())
        norm.training = False
    return cfg, model, norm


def _shapes(space) -> dict:
    return {k: tuple(v.shape) for k, v in space.spaces.items()} if hasattr(space, "spaces") else \
        {"": tuple(space.shape)}


def _check_observation_space(run_dir: Path, cfg) -> None:
    """The run's policy was trained on the observations its config gives today: a run of ``diffkin/Reach-v0``
    from before issue 19 observed ``(joint_positions, ee_position)``, the env's default until then."""
    from stable_baselines3.common.save_util import load_from_zip_file

    from diffkin.errors import ConventionError
    from diffkin.training.algos import is_diffkin_env

    if not is_diffkin_env(cfg.env_id):  # no torch env to compare with (panda-gym)
        return
    data, _, _ = load_from_zip_file(run_dir / "model.zip", load_data=True, print_system_info=False)
    saved = data.get("observation_space") if data else None
    if saved is None:
        return
    now = TorchVectorEnv(cfg.env_id, 1, **cfg.env_kwargs).single_observation_space
    if _shapes(saved) != _shapes(now):
        raise ConventionError(
            f"{run_dir}: the policy was trained on observations of shapes {_shapes(saved)}, the env of its "
            f"config.yaml gives {_shapes(now)}; a diffkin/Reach-v0 run from before issue 19 observed "
            "(joint_positions, ee_position): add `observation: [joint_positions, ee_position]` to its "
            "env_kwargs")


def evaluate_run(run_dir: str | Path, episodes: int = 200, seed: int = 20_000,
                 robot_config: dict | None = None) -> dict:
    """Policy vs scripted baseline on ``episodes`` identical episodes (same seeds). ``robot_config``
    overrides fields of the run's :class:`~diffkin.envs.robot.RobotConfig`, e.g.
    ``{"geometry_noise_length": 0.02, "geometry_noise_angle": 0.04}``: every episode on its own perturbed
    robot (the goals and start poses of a seed are the same with and without the perturbation)."""
    cfg, model, norm = load_run(run_dir)
    kwargs = {**cfg.env_kwargs, **cfg.eval_env_kwargs}
    if robot_config:
        kwargs["robot_config"] = {**(kwargs.get("robot_config") or {}), **robot_config}
    venv = TorchVectorEnv(cfg.env_id, episodes, **kwargs)
    return {
        "run": str(run_dir),
        "env_id": cfg.env_id,
        "robot_config": kwargs.get("robot_config"),
        "policy": run_episodes(venv, model_policy(model, norm), seed),
        "scripted_ik": run_episodes(venv, scripted_policy, seed),
    }


def evaluate_and_save(run_dir: str | Path, episodes: int = 200, seed: int = 20_000) -> dict:
    """:func:`evaluate_run`, also written to ``run_dir/evaluation.json``."""
    res = evaluate_run(run_dir, episodes, seed)
    (Path(run_dir) / "evaluation.json").write_text(json.dumps(res, indent=2))
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir")
    p.add_argument("--episodes", type=int, default=200)
    p.add_argument("--seed", type=int, default=20_000)
    args = p.parse_args(argv)
    torch.set_num_threads(1)  # the command line's choice (small batched kernels); the functions set nothing
    print(json.dumps(evaluate_and_save(args.run_dir, args.episodes, args.seed), indent=2))
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    raise SystemExit(main())
