"""Torch-batched vector env (Gymnasium ``VectorEnv`` semantics) and its stable-baselines3 ``VecEnv`` adapter.

``TorchVectorEnv`` steps N envs of one task as single tensor operations on ``device`` ("cpu" or "cuda");
observations, rewards, terminations, truncations and info values are ``(N, ...)`` torch tensors.

Autoreset: **SAME_STEP** (``metadata["autoreset_mode"]``, the SB3 convention). When env i ends, the obs
returned for it is already the first obs of its next episode; its terminal obs is in ``info["final_obs"]``
(a batched obs, valid where the mask ``info["_final_obs"]`` is True) and its terminal info values in
``info["final_info"]``. Every other info key is present for every env (no ``_key`` masks needed).

Seeding: ``reset(seed=s)`` seeds env i like a single env reset with ``seed=s + i`` (or pass a list of
seeds); resets then draw from a counter-based RNG per env (``envs/_random.py``), so env i of the batch
produces the same episodes as ``gymnasium.make(id).reset(seed=s + i)`` followed by plain resets.
"""

from __future__ import annotations

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from stable_baselines3.common.vec_env import VecEnv

from diffkin.errors import ConventionError, DTypeError, ShapeError

from ._checks import check_setting
from ._random import key_from_generator, keys_for_seeds
from .core import Task, check_action, check_reset_options
from .reach import ReachConfig, ReachTask
from .track import TrackConfig, TrackTask

__all__ = ["TorchVectorEnv", "SB3VecEnv", "make_task", "make_vec_env"]

_TASKS = {"diffkin/Reach-v0": (ReachTask, ReachConfig), "diffkin/Track-v0": (TrackTask, TrackConfig)}
_ROBOT_KEYS = ("robot", "action_mode", "robot_config", "home", "dtype", "device")


def make_task(env_id: str, **kwargs) -> Task:
    """The batched task behind ``env_id``, same keyword arguments as ``gymnasium.make(env_id, ...)``."""
    if env_id not in _TASKS:
        raise ConventionError(f"unknown env id {env_id!r}; batched ids: {sorted(_TASKS)}")
    task_cls, cfg_cls = _TASKS[env_id]
    if "max_episode_steps" in kwargs:  # alias (gym.make consumes this name for its TimeLimit wrapper)
        kwargs["episode_steps"] = kwargs.pop("max_episode_steps")
    robot_kwargs = {k: kwargs.pop(k) for k in _ROBOT_KEYS if k in kwargs}
    return task_cls(cfg_cls(**kwargs), **robot_kwargs)


def _is_int(x) -> bool:
    return isinstance(x, int | np.integer) and not isinstance(x, bool | np.bool_)


def _to_numpy(x):
    if isinstance(x, dict):
        return {k: _to_numpy(v) for k, v in x.items()}
    return x.detach().cpu().numpy()


class TorchVectorEnv(VectorEnv):
    """N envs of ``env_id`` stepped as one tensor op (see module docstring for autoreset and seeding)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, env_id: str, num_envs: int, device: str = "cpu", **env_kwargs):
        check_setting(num_envs, "num_envs", low=1, integer=True)
        self.env_id = env_id
        self.task = make_task(env_id, device=device, **env_kwargs)
        self.num_envs = int(num_envs)
        self.device = self.task.device
        self.single_observation_space = self.task.observation_space()
        self.single_action_space = self.task.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.state = self.task.new_state(self.num_envs)
        self._action_shape = (self.num_envs, *self.single_action_space.shape)
        self._seeded = False

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        """Reset every env. ``seed``: int (env i gets seed + i), a list of N ints, or None. ``options``:
        None or ``{}`` (the envs take no reset options)."""
        check_reset_options(options, type(self).__name__)
        if seed is not None:
            seeds = [seed + i for i in range(self.num_envs)] if _is_int(seed) else list(seed)
            if len(seeds) != self.num_envs:
                raise ShapeError(f"expected {self.num_envs} seeds, got {len(seeds)}")
            if not all(_is_int(s) and s >= 0 for s in seeds):
                raise DTypeError(f"expected seeds as non-negative integers, got {seeds}")
            self._set_keys(keys_for_seeds(seeds))
        elif not self._seeded:
            self._set_keys([key_from_generator(self.np_random) for _ in range(self.num_envs)])
        self.task.reset_rows(self.state)
        return self.task.observe(self.state), {}

    def _set_keys(self, keys: list[int]) -> None:
        self.state["key"] = torch.tensor(keys, dtype=torch.int64, device=self.device)
        self.state["episode"].zero_()
        self._seeded = True

    def step(self, actions):
        if not self._seeded:
            raise RuntimeError("call reset() before step()")
        actions = check_action(actions, self._action_shape, "actions", self.task.dtype, self.device)
        obs, reward, terminated, truncated, info = self.task.step(self.state, actions)
        done = terminated | truncated
        if bool(done.any()):
            idx = done.nonzero().squeeze(-1)
            info = dict(info, final_obs=obs, _final_obs=done, final_info=dict(info))
            self.task.reset_rows(self.state, idx)
            obs = self.task.observe(self.state)
        return obs, reward, terminated, truncated, info

    def compute_reward(self, achieved_goal, desired_goal, info=None):
        return self.task.compute_reward(achieved_goal, desired_goal, info)


class SB3VecEnv(VecEnv):
    """stable-baselines3 ``VecEnv`` over a :class:`TorchVectorEnv` (numpy in/out, Dict obs supported).

    Done envs carry ``infos[i]["terminal_observation"]`` and ``"TimeLimit.truncated"`` (SB3's conventions);
    ``env_method("compute_reward", ...)`` serves ``HerReplayBuffer``.
    """

    def __init__(self, venv: TorchVectorEnv):
        self.venv = venv
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
        self._actions = None

    def reset(self):
        seeds = self._seeds
        if seeds and seeds[0] is not None:
            obs, _ = self.venv.reset(seed=[int(s) for s in seeds])
        else:
            obs, _ = self.venv.reset()
        self._reset_seeds()
        return _to_numpy(obs)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.venv.step(self._actions)
        done = (terminated | truncated).cpu().numpy()
        scalars = {k: v.cpu().numpy() for k, v in info.items()
                   if isinstance(v, torch.Tensor) and v.ndim == 1 and not k.startswith(("_", "final"))}
        infos = [{k: v[i].item() for k, v in scalars.items()} for i in range(self.num_envs)]
        if done.any():
            final = _to_numpy(info["final_obs"])
            trunc = (truncated & ~terminated).cpu().numpy()
            for i in np.flatnonzero(done):
                infos[i]["terminal_observation"] = (
                    {k: v[i] for k, v in final.items()} if isinstance(final, dict) else final[i]
                )
                infos[i]["TimeLimit.truncated"] = bool(trunc[i])
        return _to_numpy(obs), reward.cpu().numpy().astype(np.float32), done, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name, indices=None):
        return [getattr(self.venv.task, attr_name, getattr(self.venv, attr_name, None))] * len(
            self._get_indices(indices))

    def set_attr(self, attr_name, value, indices=None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name, *method_args, indices=None, **method_kwargs):
        fn = getattr(self.venv, method_name)
        return [fn(*method_args, **method_kwargs) for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * len(self._get_indices(indices))

    def get_images(self):
        return [None] * self.num_envs


def make_vec_env(env_id: str, num_envs: int, device: str = "cpu", **env_kwargs) -> SB3VecEnv:
    """A batched env of ``env_id`` wrapped for stable-baselines3."""
    return SB3VecEnv(TorchVectorEnv(env_id, num_envs, device=device, **env_kwargs))
