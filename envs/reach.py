"""``diffkin/Reach-v0``: move the end effector to a goal position (goal-conditioned, HER-ready)."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
from torch import Tensor

from .core import Task, TaskEnv

__all__ = ["ReachConfig", "ReachTask", "ReachEnv", "reach_reward"]


@dataclass(frozen=True)
class ReachConfig:
    """Task settings. ``goal_spread`` in [0, 1]: goal joints are ``home + goal_spread · (U(limits) − home)``
    (1 = uniform over the joint limits, i.e. the whole reachable workspace)."""

    reward_type: str = "sparse"  # "sparse": -(d > threshold); "dense": -d
    distance_threshold: float = 0.05  # m
    episode_steps: int = 50
    goal_spread: float = 1.0
    init_noise: float = 0.1  # rad, uniform noise on the home pose at reset
    terminate_on_success: bool = False


def reach_reward(achieved_goal, desired_goal, reward_type: str, threshold: float):
    """Vectorised reward over leading dims: works on ``(3,)`` and ``(B, 3)``, numpy or torch."""
    if isinstance(achieved_goal, Tensor):
        d = torch.linalg.vector_norm(achieved_goal - desired_goal, dim=-1)
        return -d if reward_type == "dense" else -(d > threshold).to(d.dtype)
    d = np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal), axis=-1)
    r = -d if reward_type == "dense" else -(d > threshold).astype(np.float32)
    return np.asarray(r, dtype=np.float32)


class ReachTask(Task):
    """Batched reach logic. Observation ``[q normalised to [-1, 1] (n), p_ee (3)]``; goals ``p_ee``, goal."""

    def __init__(self, config: ReachConfig | None = None, **robot_kwargs):
        super().__init__(**robot_kwargs)
        self.config = config or ReachConfig()
        if self.config.reward_type not in ("sparse", "dense"):
            raise ValueError(f"reward_type must be 'sparse' or 'dense', got {self.config.reward_type!r}")
        self.max_steps = self.config.episode_steps
        self.n_random = 2 * self.robot.n

    def observation_space(self) -> gym.spaces.Dict:
        w, n = self.workspace, self.robot.n
        pos = gym.spaces.Box(-w, w, (3,), np.float32)
        obs = gym.spaces.Box(-w, w, (n + 3,), np.float32)
        return gym.spaces.Dict({"observation": obs, "achieved_goal": pos, "desired_goal": pos})

    def _extra_state(self, n: int) -> dict[str, Tensor]:
        return {"goal": torch.zeros(n, 3, dtype=self.dtype, device=self.device)}

    def _sample(self, state, idx, u) -> None:
        r, n = self.robot, self.robot.n
        q0 = r.home + self.config.init_noise * (2.0 * u[:, :n] - 1.0)
        state["q"][idx] = r.chain.clamp_to_limits(q0)
        state["goal"][idx] = r.ee_position(r.sample_q(u[:, n:], self.config.goal_spread))

    def _evaluate(self, state, ee):
        c = self.config
        d = torch.linalg.vector_norm(ee - state["goal"], dim=-1)
        success = d < c.distance_threshold
        reward = -d if c.reward_type == "dense" else -(~success).to(self.dtype)
        terminated = success & c.terminate_on_success
        return reward, terminated, {"is_success": success, "distance": d}

    def _observe(self, state, ee):
        obs = torch.cat((self.robot.normalize_q(state["q"]), ee), dim=-1)
        return {"observation": obs, "achieved_goal": ee, "desired_goal": state["goal"].clone()}

    def compute_reward(self, achieved_goal, desired_goal, info=None):
        c = self.config
        return reach_reward(achieved_goal, desired_goal, c.reward_type, c.distance_threshold)

    def draw_targets(self, state) -> dict:
        return {"goal": state["goal"][0].cpu().numpy()}


class ReachEnv(TaskEnv):
    """## Description
    Kinematic reach with any diffkin chain (default Franka Panda): bring the end effector within
    ``distance_threshold`` of a goal sampled by forward kinematics of random joints within limits.

    ## Action space
    ``Box(-1, 1, (n,))`` joint-velocity command scaled by ``max_joint_speed``, integrated over
    ``control_dt`` and clamped to the joint limits; or with ``action_mode="cartesian"`` ``Box(-1, 1, (3,))``,
    an end-effector displacement (× ``max_ee_step``) mapped through a damped-least-squares step.

    ## Observation space
    ``Dict(observation=[q normalised (n), p_ee (3)], achieved_goal=p_ee (3), desired_goal=goal (3))``,
    float32.

    ## Rewards
    sparse: 0 on success, -1 otherwise; dense: minus the distance. ``compute_reward`` is vectorised.

    ## Episode end
    Truncated after ``episode_steps`` (50); terminated on success only if ``terminate_on_success``.
    ``info["is_success"]``, ``info["distance"]``.
    """

    def __init__(self, robot="panda", action_mode: str = "joint", render_mode: str | None = None,
                 robot_config=None, home=None, dtype=torch.float32, device="cpu", **task_kwargs):
        task = ReachTask(ReachConfig(**task_kwargs), robot=robot, action_mode=action_mode,
                         robot_config=robot_config, home=home, dtype=dtype, device=device)
        super().__init__(task, render_mode=render_mode)

    def compute_reward(self, achieved_goal, desired_goal, info=None):
        return self.task.compute_reward(achieved_goal, desired_goal, info)
