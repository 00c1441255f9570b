"""Task base class (batched torch logic shared by single and vector envs) and the single-env wrapper.

A task owns no env state: it works on a ``state`` dict of ``(N, ...)`` tensors, so the very same code steps
one env (``TaskEnv``, N = 1) and a batch (``envs.vector.TorchVectorEnv``). That is what makes env ``i`` of a
batch equal a single env with the same seed.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from torch import Tensor

from diffkin.errors import ConventionError, DTypeError, ShapeError
from diffkin.validation import check_finite, check_given, shape_str, tensors

from ._random import key_from_generator, uniform
from .robot import Robot, RobotConfig

__all__ = ["Task", "TaskEnv", "check_action", "to_numpy"]  # check_reset_options: the envs' own


_FLOAT_ARRAYS = (np.dtype(np.float32), np.dtype(np.float64))


class ResetNeededError(gym.error.ResetNeeded, RuntimeError):
    """``step()`` before ``reset()``: Gymnasium's typed ``ResetNeeded`` (still a ``RuntimeError``)."""


def check_action(action, shape: tuple[int, ...], name: str = "action", dtype=torch.float32,
                 device="cpu") -> Tensor:
    """An action by the rule of :mod:`diffkin.validation`, as a tensor of the env's ``dtype`` and ``device``.

    Numpy arrays (the Gymnasium case), sequences and numbers of float or integer dtype are converted; tensors
    must be float32 or float64 (either is cast to the env's dtype: an action is a command, not a computation
    the caller shares). Integer, bool, complex and half-precision tensors raise ``DTypeError``; a shape
    other than ``shape`` ``ShapeError``; NaN or inf ``NonFiniteError`` (all ``ValueError`` subclasses).
    Values out of the action space's bounds are the task's to clip.
    """
    if type(action) is np.ndarray and action.dtype in _FLOAT_ARRAYS and action.shape == tuple(shape) \
            and np.isfinite(action).all():  # the Gymnasium case, validated in numpy: no tensor round trip
        return torch.from_numpy(action).to(dtype=dtype, device=device, copy=True)
    check_given(action, name, f"numbers of shape {tuple(shape)}")  # tensors() passes None through
    (a,) = tensors((name, action, None), finite=False)
    if tuple(a.shape) != tuple(shape):
        raise ShapeError(f"expected {name} of shape {tuple(shape)}, got {shape_str(a.shape)}")
    check_finite(a, name)
    return a.to(dtype=dtype, device=device)


def check_reset_options(options, env: str) -> None:
    """``reset(options=...)``: these envs take none; ``None`` or ``{}`` pass, anything else is refused
    (a misspelt or unsupported option would otherwise be silently ignored)."""
    if options is None or (isinstance(options, dict) and not options):
        return
    got = sorted(map(str, options)) if isinstance(options, dict) else type(options).__name__
    raise ConventionError(f"{env}.reset takes no options (expected None or {{}}), got {got}")


def to_numpy(obs):
    """Row 0 of a (dict of) ``(1, ...)`` tensor(s) as float32 numpy."""
    if isinstance(obs, dict):
        return {k: to_numpy(v) for k, v in obs.items()}
    return obs[0].detach().to("cpu", torch.float32).numpy().copy()


class Task:
    """Batched task logic. Subclasses set ``n_random``; implement ``_sample``, ``_evaluate``, ``_observe``."""

    n_random: int = 0
    max_steps: int = 50
    # keep state["ee"] (p_ee at the last step) and state["ee_velocity"] ((p_ee(t) − p_ee(t − 1)) / Δt, 0 after
    # a reset): a task that observes the end effector's velocity sets it
    tracks_ee_velocity: bool = False
    # keep state["joint_velocity"] ((q(t) ⊖ q(t − 1)) / Δt, (N, nv), 0 after a reset): a task that observes it
    tracks_joint_velocity: bool = False
    #: keyword arguments of the task besides its config and the robot's (``make_task`` passes them on)
    task_kwargs: tuple[str, ...] = ()

    def __init__(self, robot: str = "panda", action_mode: str = "joint",
                 robot_config: RobotConfig | dict | None = None,
                 home=None, dtype=torch.float32, device="cpu"):
        if dtype not in (torch.float32, torch.float64):
            raise DTypeError(f"expected the env dtype torch.float32 or torch.float64, got {dtype!r}")
        if isinstance(robot_config, dict):
            robot_config = RobotConfig(**robot_config)
        self.robot = Robot(robot, robot_config, action_mode=action_mode, home=home, dtype=dtype,
                           device=device)
        self.dtype, self.device = dtype, self.robot.device
        self.action_space = gym.spaces.Box(-1.0, 1.0, (self.robot.action_dim,), np.float32)
        home_ee = float(self.robot.ee_position(self.robot.home).norm())
        self.workspace = home_ee + 2.0 + _reach_bound(self.robot)

    # ------------------------------------------------------------------------------------------ state
    def new_state(self, n: int) -> dict[str, Tensor]:
        z = torch.zeros(n, dtype=torch.int64, device=self.device)
        q = self.robot.home.expand(n, -1).clone()
        state = {"q": q, "t": z.clone(), "key": z.clone(), "episode": z.clone()}
        if self.robot.geometry_dim:  # domain randomisation: each row's own DH parameters
            state["geometry"] = self.robot.nominal_geometry(n)
        if self.tracks_ee_velocity:
            state["ee"] = torch.zeros(n, 3, dtype=self.dtype, device=self.device)
            state["ee_velocity"] = torch.zeros(n, 3, dtype=self.dtype, device=self.device)
        if self.tracks_joint_velocity:
            state["joint_velocity"] = torch.zeros(n, self.robot.nv, dtype=self.dtype, device=self.device)
        state.update(self._extra_state(n))
        return state

    def _extra_state(self, n: int) -> dict[str, Tensor]:
        return {}

    def reset_rows(self, state: dict[str, Tensor], idx: Tensor | None = None) -> None:
        """Start a new episode in rows ``idx`` (all rows if None), from the counter-based RNG of each row."""
        idx = torch.arange(state["q"].shape[0], device=self.device) if idx is None else idx
        g = self.robot.geometry_dim
        u = uniform(state["key"][idx], state["episode"][idx], self.n_random + g, dtype=self.dtype)
        state["episode"][idx] += 1
        state["t"][idx] = 0
        if g:  # the episode's robot first (the task's draws are the same numbers with or without it)
            state["geometry"][idx] = self.robot.sample_geometry(u[:, self.n_random:])
        self._sample(state, idx, u[:, :self.n_random])
        if self.tracks_ee_velocity:  # at rest at the episode's start; out of place: the last step's p_ee and
            # velocity are also that step's (final) observation
            ee = self.robot.ee_position(state["q"][idx], self.geometry(state, idx))
            state["ee"] = state["ee"].index_copy(0, idx, ee)
            state["ee_velocity"] = state["ee_velocity"].index_fill(0, idx, 0.0)
        if self.tracks_joint_velocity:
            state["joint_velocity"] = state["joint_velocity"].index_fill(0, idx, 0.0)

    def geometry(self, state: dict[str, Tensor], idx: Tensor | None = None) -> Tensor | None:
        """The rows' DH parameters ``(M, geometry_dim)`` under domain randomisation, else None (nominal)."""
        if "geometry" not in state:
            return None
        return state["geometry"] if idx is None else state["geometry"][idx]

    def ee(self, state: dict[str, Tensor]) -> Tensor:
        """End-effector positions ``(N, 3)`` of the state's rows, each on its episode's robot."""
        return self.robot.ee_position(state["q"], self.geometry(state))

    def observe(self, state: dict[str, Tensor]):
        # p_ee is in the state when the velocity is tracked (copied: the observation must not alias it)
        return self._observe(state, state["ee"].clone() if self.tracks_ee_velocity else self.ee(state))

    def step(self, state: dict[str, Tensor], action: Tensor):
        """Advance all rows one control period; ``(obs, reward, terminated, truncated, info)`` tensors."""
        action = action.to(self.dtype).clamp(-1.0, 1.0)
        q0, state["q"] = state["q"], self.robot.apply_action(state["q"], action)
        if self.tracks_joint_velocity:
            state["joint_velocity"] = self.robot.velocity(q0, state["q"])
        state["t"] += 1
        ee = self.ee(state)
        if self.tracks_ee_velocity:  # the mean velocity over this control period
            state["ee_velocity"] = (ee - state["ee"]) / self.robot.config.control_dt
            state["ee"] = ee
        reward, terminated, info = self._evaluate(state, ee)
        truncated = state["t"] >= self.max_steps
        return self._observe(state, ee), reward, terminated, truncated, info

    # --------------------------------------------------------------------------------- to implement
    def observation_space(self) -> gym.spaces.Space:
        raise NotImplementedError

    def _sample(self, state, idx, u) -> None:
        raise NotImplementedError

    def _evaluate(self, state, ee):
        raise NotImplementedError

    def _observe(self, state, ee):
        raise NotImplementedError

    def draw_targets(self, state) -> dict:
        """Points to draw for row 0: ``{"goal": (3,)}`` or ``{"path": (M, 3), "target": (3,)}``."""
        return {}


def _reach_bound(robot: Robot) -> float:
    """A generous bound on |p_ee|: sum of link offsets of the DH table (plus base/tool)."""
    chain = robot.chain
    if hasattr(chain, "dh_table"):
        tab = chain.dh_table()
        total = float(tab[:, 0].abs().sum() + tab[:, 2].abs().sum())
        lo, hi = robot.lower, robot.upper
        total += float(torch.where(robot.revolute, 0.0, torch.maximum(lo.abs(), hi.abs())).sum())
    else:
        total = 5.0
    for T in (getattr(chain, "base", None), getattr(chain, "tool", None)):
        if T is not None:
            total += float(T[:3, 3].norm())
    return total


class TaskEnv(gym.Env):
    """A single Gymnasium env over a batched :class:`Task` with N = 1.

    Seeding goes only through ``super().reset(seed=seed)``: after it a 32-bit key is drawn from
    ``self.np_random`` and episode ``e`` is a pure function of ``(key, e)`` (see ``envs/_random.py``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, task: Task, render_mode: str | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ConventionError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.task = task
        self.render_mode = render_mode
        self.action_space = task.action_space
        self.observation_space = task.observation_space()
        self._state: dict[str, Tensor] | None = None
        self._trace: list[np.ndarray] = []
        self._renderer = None

    @property
    def robot(self) -> Robot:
        return self.task.robot

    @property
    def q(self) -> np.ndarray:
        """The joint configuration ``(nq,)`` now (rad or m; unit quaternions (w, x, y, z) for ball and free
        joints), a float64 copy: reading it never changes the env. Through ``gym.make``'s wrappers:
        ``env.unwrapped.q`` or ``env.get_wrapper_attr("q")``. Gymnasium's ``ResetNeeded`` before the first
        ``reset()``."""
        if self._state is None:
            raise ResetNeededError("call reset() before reading q")
        return self._state["q"][0].detach().cpu().numpy().astype(np.float64)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        check_reset_options(options, type(self).__name__)
        super().reset(seed=seed)
        if seed is not None or self._state is None:
            self._state = self.task.new_state(1)
            self._state["key"][0] = key_from_generator(self.np_random)
        self.task.reset_rows(self._state)
        obs = self.task.observe(self._state)
        self._trace = [self._ee()] if self.render_mode else []  # the drawn trace: only when rendering
        return to_numpy(obs), {}

    def step(self, action):
        if self._state is None:
            raise ResetNeededError("call reset() before step()")
        task = self.task
        a = check_action(action, self.action_space.shape, dtype=task.dtype, device=task.device)[None]
        obs, reward, terminated, truncated, info = self.task.step(self._state, a)
        if self.render_mode:
            self._trace.append(self._ee())
        info = {k: v[0].item() for k, v in info.items()}
        return to_numpy(obs), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def _ee(self) -> np.ndarray:
        return self.task.ee(self._state)[0].detach().cpu().numpy().astype(np.float64)

    def render(self):
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        from .render import ArmRenderer

        if self._renderer is None:
            self._renderer = ArmRenderer(planar=self.robot.planar, extent=_reach_bound(self.robot))
        frames = self.robot.frames(self._state["q"])[0].cpu().numpy()
        return self._renderer.draw(frames, np.array(self._trace), self.task.draw_targets(self._state))

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
