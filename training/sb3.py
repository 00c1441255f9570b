"""stable-baselines3 adapter of the torch-batched diffkin envs (the environments themselves know no trainer).

:class:`SB3VecEnv` wraps a :class:`~diffkin.envs.vector.TorchVectorEnv` as an SB3 ``VecEnv`` (numpy in and
out, ``Dict`` observations supported); :func:`make_sb3_vec_env` builds both in one call. The name differs
from SB3's own ``stable_baselines3.common.env_util.make_vec_env`` (N copies of a single env in a
``DummyVecEnv``), which works on the registered IDs too but steps the envs one by one.
"""

from __future__ import annotations

import numpy as np
import torch
from stable_baselines3.common.vec_env import VecEnv

from diffkin.envs.vector import TorchVectorEnv

__all__ = ["SB3VecEnv", "make_sb3_vec_env"]


def _to_numpy(x):
    if isinstance(x, dict):
        return {k: _to_numpy(v) for k, v in x.items()}
    return x.detach().cpu().numpy()


class SB3VecEnv(VecEnv):
    """stable-baselines3 ``VecEnv`` over a :class:`~diffkin.envs.vector.TorchVectorEnv`.

    Observations, rewards (float32) and dones come back as numpy arrays; actions go in as numpy arrays.
    Done envs carry ``infos[i]["terminal_observation"]`` and ``"TimeLimit.truncated"`` (SB3's conventions);
    the scalar info values (``is_success``, ``distance``, ``tracking_error``) are in every ``infos[i]``.
    ``seed(s)`` before ``reset()`` seeds env ``i`` with ``s + i``; ``env_method("compute_reward", ...)``
    serves ``HerReplayBuffer``.
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


def make_sb3_vec_env(
    env_id: str,
    num_envs: int,
    *,
    device: str = "cpu",
    seed: int | None = None,
    robot="panda",
    action_mode: str = "joint",
    robot_config=None,
    home=None,
    dtype: torch.dtype = torch.float32,
    **task_kwargs,
) -> SB3VecEnv:
    """``num_envs`` envs of ``env_id``, stepped as one batch, as a stable-baselines3 ``VecEnv``.

    Args:
        env_id: ``"diffkin/Reach-v0"`` or ``"diffkin/Track-v0"``.
        num_envs: how many envs the batch holds (SB3's ``n_envs``). With on-policy algorithms a rollout is
            ``n_steps × num_envs`` transitions: pass PPO an ``n_steps`` near the episode length (e.g. 50),
            not SB3's default 2048.
        device: ``"cpu"`` or ``"cuda"``: where the env state and kinematics live (the policy's device is
            the algorithm's own).
        seed: when given, the first ``reset()`` seeds env ``i`` with ``seed + i`` (SB3's ``VecEnv.seed``).
        robot: a model name of :func:`diffkin.models.load` (``"panda"``, ``"ur5"``,
            ``"three_link_planar"``, ...) or a :class:`~diffkin.chain.KinematicChain`.
        action_mode: ``"joint"`` (joint velocities) or ``"cartesian"`` (end-effector displacements through
            a damped-least-squares step).
        robot_config: a :class:`~diffkin.envs.robot.RobotConfig` or a dict of its fields (``max_joint_speed``
            rad/s, ``control_dt`` s, ``max_ee_step`` m, ``damping``, ``geometry_noise_length`` m and
            ``geometry_noise_angle`` rad: each env's own robot per episode).
        home: the start pose ``(n,)``; default the model's own (the Panda's "ready" pose).
        dtype: ``torch.float32`` or ``torch.float64`` for the kinematics (observations are float32).
        **task_kwargs: the task's settings, the fields of :class:`~diffkin.envs.reach.ReachConfig`
            (``reward_type`` "sparse" | "dense", ``distance_threshold`` m, ``episode_steps``,
            ``goal_sampling`` "box" | "joints", ``goal_center`` m, ``goal_range`` m, ``goal_spread``,
            ``init_noise`` rad, ``terminate_on_success``) or :class:`~diffkin.envs.track.TrackConfig`
            (``episode_steps``, ``lookahead``, ``line_fraction``, ``line_spread``, ``max_line_length``,
            ``radius_range``, ``init_noise``). Unknown names raise ``TypeError``.

    Returns:
        An :class:`SB3VecEnv`. Reach's ``Dict`` observation needs ``MultiInputPolicy``; wrap it in
        ``VecMonitor`` for episode statistics and ``VecNormalize`` for observation / reward normalisation.
    """
    venv = SB3VecEnv(TorchVectorEnv(env_id, num_envs, device=device, robot=robot, action_mode=action_mode,
                                    robot_config=robot_config, home=home, dtype=dtype, **task_kwargs))
    if seed is not None:
        venv.seed(seed)
    return venv
