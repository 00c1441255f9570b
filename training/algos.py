"""The stable-baselines3 algorithms a run config may name (shared by :mod:`training.train` and
:mod:`training.evaluate`, which must not import each other)."""

from __future__ import annotations

from stable_baselines3 import PPO, SAC, TD3

__all__ = ["ALGOS", "EVAL_SEED"]

ALGOS = {"sac": SAC, "td3": TD3, "ppo": PPO}
EVAL_SEED = 10_000  # seed of the evaluation episodes during training
