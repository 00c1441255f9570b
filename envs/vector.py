"""Torch-batched vector env (Gymnasium ``VectorEnv`` semantics); its stable-baselines3 adapter is
:mod:`diffkin.training.sb3` (the environments know no trainer).

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

from diffkin.errors import ConventionError, DTypeError, ShapeError

from ._checks import check_setting
from ._random import key_from_generator, keys_for_seeds
from .core import ResetNeededError, Task, check_action, check_reset_options
from .registry import ENVS

__all__ = ["TorchVectorEnv", "make_task"]

_ROBOT_KEYS = ("robot", "action_mode", "robot_config", "home", "dtype", "device")


def make_task(env_id: str, **kwargs) -> Task:
    """The batched task behind ``env_id``, same keyword arguments as ``gymnasium.make(env_id, ...)``."""
    if env_id not in ENVS:
        raise ConventionError(f"unknown env id {env_id!r}; batched ids: {sorted(ENVS)}")
    spec = ENVS[env_id]
    if "max_episode_steps" in kwargs:  # alias (gym.make consumes this name for its TimeLimit wrapper)
        kwargs["episode_steps"] = kwargs.pop("max_episode_steps")
    robot_kwargs = {k: kwargs.pop(k) for k in (*_ROBOT_KEYS, *spec.task.task_kwargs) if k in kwargs}
    return spec.task(spec.config(**kwargs), **robot_kwargs)


def _is_int(x) -> bool:
    return isinstance(x, int | np.integer) and not isinstance(x, bool | np.bool_)


class TorchVectorEnv(VectorEnv):
    """``num_envs`` envs of one diffkin task stepped as single tensor operations (Gymnasium ``VectorEnv``).

    ## Description
    The batched form of ``diffkin/Reach-v0`` and ``diffkin/Track-v0``: the same task code as the single env
    (:class:`~diffkin.envs.core.Task`) on ``(N, ...)`` tensors, on ``device`` ("cpu" or "cuda"). Env ``i``
    reset with seed ``s + i`` produces the same episodes as ``gymnasium.make(env_id).reset(seed=s + i)``.
    Inputs and outputs are torch tensors; :func:`diffkin.training.sb3.make_sb3_vec_env` wraps it for
    stable-baselines3 (numpy in and out).

    ## Action Space
    ``batch_space(single_action_space, N)``: ``Box(-1.0, 1.0, (N, n), float32)`` (joint mode) or
    ``(N, 3)`` (Cartesian mode). ``step`` takes a tensor or array of that shape (float32 or float64, cast
    to the env's dtype), clipped to [-1, 1].

    ## Observation Space
    ``batch_space(single_observation_space, N)``: for Reach a ``Dict`` of ``(N, d)`` (``d`` = 6 for the
    default observation, end-effector position and velocity), ``(N, 3)``, ``(N, 3)`` tensors; for Track a
    ``(N, n + 3 + 3 (H + 1) + 1)`` tensor (see the single envs).

    ## Rewards
    Those of the single env, a ``(N,)`` tensor. ``compute_reward`` is the task's (vectorised, for HER).

    ## Starting State
    As the single env, per env. ``reset(seed=s)`` seeds env ``i`` with ``s + i`` (or give a list of ``N``
    seeds); later resets draw from a counter-based RNG per env (``envs/_random.py``).

    ## Episode End
    As the single env; ``terminated`` and ``truncated`` are ``(N,)`` bool tensors. Autoreset mode
    **SAME_STEP** (``metadata["autoreset_mode"]``, SB3's convention): the observation returned for an env
    that ended is already the first of its next episode; its last observation is in ``info["final_obs"]``
    (valid where ``info["_final_obs"]``) and its last info values in ``info["final_info"]``. Every other info
    key (``is_success``, ``distance`` / ``tracking_error``) is a ``(N,)`` tensor for every env.

    ## Arguments
    ```python
    TorchVectorEnv(env_id, num_envs, device="cpu", **env_kwargs)
    ```

    * ``env_id``: ``"diffkin/Reach-v0"`` or ``"diffkin/Track-v0"`` (the IDs of
      :data:`diffkin.envs.registry.ENVS`).
    * ``num_envs``: N >= 1.
    * ``device``: where the state and the kinematics live.
    * ``env_kwargs``: the keyword arguments of ``gymnasium.make(env_id, ...)`` except ``render_mode``
      (``robot``, ``action_mode``, ``robot_config``, ``home``, ``dtype``, the task's settings and, for
      Reach, ``collision``);
      ``max_episode_steps`` is an alias of ``episode_steps``.

    ## Version History
    * v0: initial version.
    """

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
            raise ResetNeededError("call reset() before step()")
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
