"""Run configuration: a YAML file keyed by env ID → a frozen dataclass."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import yaml

__all__ = ["RunConfig", "load_config"]

_ALGOS = ("sac", "td3", "ppo")
_SWEEP_SECTIONS = ("search_space", "tune")


@dataclass(frozen=True)
class RunConfig:
    """One training run.

    ``vectorized``: train on the torch-batched env (``envs.vector``) with ``n_envs`` envs; else
    ``n_envs`` single envs in an SB3 ``DummyVecEnv``. ``her``: ``HerReplayBuffer`` kwargs
    (goal-conditioned envs, off-policy algorithms only). ``eval_env_kwargs`` override ``env_kwargs`` for
    evaluation (e.g. the sparse success metric while training on a dense reward). ``max_wall_seconds``
    stops training after that much wall-clock; ``stop_success`` once an evaluation reaches that success.
    """

    name: str
    env_id: str
    algo: str
    total_timesteps: int
    seed: int = 0
    n_envs: int = 1
    vectorized: bool = False
    device: str = "cpu"
    torch_threads: int = 1
    env_kwargs: dict = field(default_factory=dict)
    eval_env_kwargs: dict = field(default_factory=dict)
    algo_kwargs: dict = field(default_factory=dict)
    her: dict | None = None
    normalize: bool = False
    eval_freq: int = 2000  # env steps between evaluations
    eval_episodes: int = 100
    max_wall_seconds: float | None = None
    stop_success: float | None = None

    def __post_init__(self):
        if self.algo not in _ALGOS:
            raise ValueError(f"algo must be one of {_ALGOS}, got {self.algo!r}")
        if self.her is not None and self.algo == "ppo":
            raise ValueError("HER needs an off-policy algorithm (sac or td3), got ppo")

    def replace(self, **changes) -> RunConfig:
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def load_config(path: str | Path) -> RunConfig:
    """Read a YAML run config; unknown keys raise ``ValueError`` naming them. A sweep's ``search_space``
    and ``tune`` sections (:mod:`training.tune`) are left to the sweep."""
    data = yaml.safe_load(Path(path).read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping at the top level")
    data.setdefault("name", Path(path).stem)
    for section in _SWEEP_SECTIONS:  # read by training.tune; a sweep config trains as its base config
        data.pop(section, None)
    known = {f.name for f in dataclasses.fields(RunConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{path}: unknown keys {unknown}; known: {sorted(known)}")
    return RunConfig(**data)
