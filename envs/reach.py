"""``diffkin/Reach-v0``: move the end effector to a goal position (goal-conditioned, HER-ready)."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
from torch import Tensor

from diffkin.errors import ConventionError, DTypeError, ShapeError
from diffkin.validation import shape_str, tensors

from ._checks import check_setting
from .core import Task, TaskEnv
from .robot import robot_collision

__all__ = ["ReachConfig", "ReachTask", "ReachEnv", "reach_reward"]


_GOAL_SAMPLING = ("box", "joints")
_SELF_COLLISION = (None, "terminate", "penalize")
# the parts the "observation" entry can hold (ReachConfig.observation picks and orders them)
OBSERVATION_PARTS = ("ee_position", "ee_velocity", "joint_positions", "joint_velocities")


@dataclass(frozen=True)
class ReachConfig:
    """Task settings.

    ``observation`` (default ``("ee_position", "ee_velocity")``, the layout of panda-gym's PandaReach): the
    parts of the ``observation`` entry, concatenated in the order given, from ``"ee_position"`` (p_ee, 3, m),
    ``"ee_velocity"`` (the end effector's mean velocity over the last control period, (p_ee(t) −
    p_ee(t − 1)) / control_dt, 3, m/s; 0 after a reset), ``"joint_positions"`` (q mapped to [-1, 1] by the
    limits, nq; the quaternion entries of ball and free joints as they are) and ``"joint_velocities"``
    ((q(t) ⊖ q(t − 1)) / control_dt, nv: rad/s, m/s, the angular velocity of a ball joint in its child
    frame; 0 after a reset). ``("joint_positions", "ee_position")`` is the observation before issue 19.

    ``self_collision`` (default None: not checked): ``"terminate"`` ends the episode, ``"penalize"``
    subtracts ``collision_penalty`` from the reward, at every step where the smallest signed distance of the
    robot's checked collision pairs is below ``collision_margin`` (m; 0: touching or penetrating).

    ``goal_sampling="box"`` (default): goals uniform in the axis-aligned cube of edge ``goal_range`` (m)
    centred on ``goal_center`` (base frame, m; None = the end-effector position at ``home``), as panda-gym's
    PandaReach (a 0.3 m cube); a planar arm's cube is flat (z = the centre's). ``goal_sampling="joints"``:
    goals are the end-effector positions of ``home + goal_spread · (U(limits) − home)`` (``goal_spread`` in
    [0, 1]; 1 = uniform over the joint limits, i.e. the whole reachable workspace).
    """

    reward_type: str = "sparse"  # "sparse": -(d > threshold); "dense": -d
    distance_threshold: float = 0.05  # m
    episode_steps: int = 50
    goal_sampling: str = "box"
    goal_center: tuple[float, float, float] | None = None  # m, base frame; None: p_ee(home)
    goal_range: float = 0.3  # m, edge of the goal cube
    goal_spread: float = 1.0  # goal_sampling="joints" only
    init_noise: float = 0.1  # rad, uniform noise on the home pose at reset
    terminate_on_success: bool = False
    observation: tuple[str, ...] = ("ee_position", "ee_velocity")
    # on self-collision (the smallest signed distance of the checked pairs below collision_margin, m):
    # None (default, not checked), "terminate" the episode, or "penalize" the reward by collision_penalty
    self_collision: str | None = None
    collision_penalty: float = 1.0
    collision_margin: float = 0.0

    def __post_init__(self):
        if self.reward_type not in ("sparse", "dense"):
            raise ConventionError(f"reward_type must be 'sparse' or 'dense', got {self.reward_type!r}")
        if self.goal_sampling not in _GOAL_SAMPLING:
            raise ConventionError(f"goal_sampling must be one of {_GOAL_SAMPLING}, "
                                  f"got {self.goal_sampling!r}")
        check_setting(self.distance_threshold, "distance_threshold", low=0.0, strict_low=True)
        check_setting(self.episode_steps, "episode_steps", low=1, integer=True)
        check_setting(self.goal_range, "goal_range", low=0.0)
        check_setting(self.goal_spread, "goal_spread", low=0.0, high=1.0)
        if self.goal_center is not None:
            c = self.goal_center
            if not isinstance(c, tuple | list) or len(c) != 3:
                raise ShapeError(f"expected goal_center as (x, y, z) in metres or None, got {c!r}")
            for i, v in enumerate(c):
                check_setting(v, f"goal_center[{i}]")
        check_setting(self.init_noise, "init_noise", low=0.0)
        if self.self_collision not in _SELF_COLLISION:
            raise ConventionError(f"self_collision must be one of {_SELF_COLLISION}, "
                                  f"got {self.self_collision!r}")
        check_setting(self.collision_penalty, "collision_penalty", low=0.0)
        check_setting(self.collision_margin, "collision_margin")
        if not isinstance(self.terminate_on_success, bool):
            raise DTypeError(f"expected terminate_on_success as a bool, got {self.terminate_on_success!r}")
        parts = self.observation
        if isinstance(parts, list):  # a YAML list
            object.__setattr__(self, "observation", parts := tuple(parts))
        if not isinstance(parts, tuple) or not parts \
                or not all(isinstance(p, str) and p in OBSERVATION_PARTS for p in parts) \
                or len(set(parts)) != len(parts):
            raise ConventionError(f"expected observation as a non-empty sequence of distinct parts from "
                                  f"{OBSERVATION_PARTS}, got {parts!r}")


def reach_reward(achieved_goal, desired_goal, reward_type: str, threshold: float):
    """Vectorised reward over leading dims (broadcast): works on ``(3,)`` and ``(B, 3)``, numpy or torch.

    Inputs by the rule of :mod:`diffkin.validation` (shape ``(..., 3)``, finite; float32/float64 tensors of
    one dtype; numpy arrays and sequences converted). With a tensor among the inputs the reward is a tensor of
    their dtype, else a float32 numpy array (what SB3's HER buffer stores).
    """
    if reward_type not in ("sparse", "dense"):
        raise ConventionError(f"reward_type must be 'sparse' or 'dense', got {reward_type!r}")
    check_setting(threshold, "threshold", low=0.0, strict_low=True)
    a, d = tensors(("achieved_goal", achieved_goal, (3,)), ("desired_goal", desired_goal, (3,)))
    try:
        torch.broadcast_shapes(a.shape, d.shape)
    except RuntimeError:
        raise ShapeError(f"achieved_goal {shape_str(a.shape)} and desired_goal {shape_str(d.shape)} do not "
                         "broadcast") from None
    dist = torch.linalg.vector_norm(a - d, dim=-1)
    r = -dist if reward_type == "dense" else -(dist > threshold).to(dist.dtype)
    if isinstance(achieved_goal, Tensor) or isinstance(desired_goal, Tensor):
        return r
    return np.asarray(r.cpu().numpy(), dtype=np.float32)


class ReachTask(Task):
    """Batched reach logic. Observation: the parts of ``config.observation`` (default ``[p_ee (3),
    ṗ_ee (3)]``); goals ``p_ee``, goal."""

    #: keyword arguments of the task besides its config and the robot's (``make_task`` passes them on)
    task_kwargs = ("collision",)

    def __init__(self, config: ReachConfig | None = None, collision=None, **robot_kwargs):
        super().__init__(**robot_kwargs)
        self.config = config or ReachConfig()
        # the self-collision model: checked (info["min_distance"]) when given or when self_collision is set
        self.collision = None if collision is None and self.config.self_collision is None else \
            robot_collision(self.robot.chain, collision)
        self.tracks_ee_velocity = "ee_velocity" in self.config.observation
        self.tracks_joint_velocity = "joint_velocities" in self.config.observation
        self.max_steps = self.config.episode_steps
        self.n_random = self.robot.nv + max(self.robot.nv, 3)
        c, r = self.config, self.robot
        center = r.ee_position(r.home[None])[0] if c.goal_center is None else \
            torch.tensor(c.goal_center, dtype=self.dtype, device=self.device)
        half = torch.full((3,), c.goal_range / 2, dtype=self.dtype, device=self.device)
        if r.planar:
            half[2] = 0.0
        self.goal_low, self.goal_high = center - half, center + half  # (3,) each, base frame

    def observation_space(self) -> gym.spaces.Dict:
        w, n, cfg = self.workspace, self.robot.n, self.robot.config
        pos = gym.spaces.Box(-w, w, (3,), np.float32)
        # a step moves the end effector less than 2w, so |ṗ_ee| < 2w / control_dt; |normalised q| <= 1 (a
        # quaternion's entries are within ±1); |q̇_i| <= max_joint_speed (twice it: room for rounding)
        bound = {"ee_position": (w, 3), "ee_velocity": (2.0 * w / cfg.control_dt, 3),
                 "joint_positions": (1.0, n), "joint_velocities": (2.0 * cfg.max_joint_speed, self.robot.nv)}
        high = np.concatenate([np.full(bound[p][1], bound[p][0]) for p in self.config.observation])
        obs = gym.spaces.Box(-high.astype(np.float32), high.astype(np.float32), dtype=np.float32)
        return gym.spaces.Dict({"observation": obs, "achieved_goal": pos, "desired_goal": pos})

    def _extra_state(self, n: int) -> dict[str, Tensor]:
        return {"goal": torch.zeros(n, 3, dtype=self.dtype, device=self.device)}

    def _sample(self, state, idx, u) -> None:
        r, n = self.robot, self.robot.nv  # one uniform per velocity coordinate (= per joint for 1-DOF joints)
        state["q"][idx] = r.perturbed_home(u[:, :n], self.config.init_noise)
        if self.config.goal_sampling == "box":
            state["goal"][idx] = self.goal_low + (self.goal_high - self.goal_low) * u[:, n:n + 3]
        else:
            q_goal = r.sample_q(u[:, n:2 * n], self.config.goal_spread)
            state["goal"][idx] = r.ee_position(q_goal, self.geometry(state, idx))

    def _evaluate(self, state, ee):
        c = self.config
        d = torch.linalg.vector_norm(ee - state["goal"], dim=-1)
        success = d < c.distance_threshold
        reward = -d if c.reward_type == "dense" else success.to(self.dtype) - 1.0  # 0 on success, else -1
        terminated = success.clone() if c.terminate_on_success else torch.zeros_like(success)
        info = {"is_success": success, "distance": d}
        if self.collision is not None:
            info["min_distance"] = dmin = self.collision.min_distance(state["q"])
            info["in_collision"] = hit = dmin < c.collision_margin
            if c.self_collision == "terminate":
                terminated = terminated | hit
            elif c.self_collision == "penalize":
                reward = reward - c.collision_penalty * hit.to(reward.dtype)
        return reward, terminated, info

    def _observe(self, state, ee):
        parts = {"ee_position": lambda: ee, "ee_velocity": lambda: state["ee_velocity"],
                 "joint_positions": lambda: self.robot.normalize_q(state["q"]),
                 "joint_velocities": lambda: state["joint_velocity"]}
        obs = torch.cat([parts[p]() for p in self.config.observation], dim=-1)
        return {"observation": obs, "achieved_goal": ee, "desired_goal": state["goal"].clone()}

    def compute_reward(self, achieved_goal, desired_goal, info=None):
        """:func:`reach_reward`; with ``self_collision="penalize"`` minus ``collision_penalty`` where
        ``info`` (a step's info dict, or a sequence of them as HER passes) reports ``in_collision``."""
        c = self.config
        r = reach_reward(achieved_goal, desired_goal, c.reward_type, c.distance_threshold)
        if c.self_collision != "penalize" or info is None:
            return r
        hit = _in_collision(info)
        if isinstance(r, Tensor):
            return r - c.collision_penalty * torch.as_tensor(hit, dtype=r.dtype, device=r.device)
        return (r - np.float32(c.collision_penalty) * hit.astype(np.float32)).astype(np.float32)

    def draw_targets(self, state) -> dict:
        return {"goal": state["goal"][0].cpu().numpy()}


def _in_collision(info) -> np.ndarray:
    """``in_collision`` of an info dict (scalar or batched values) or of a sequence of info dicts."""
    rows = [info] if isinstance(info, dict) else list(np.ravel(np.asarray(info, dtype=object)))
    if not all(isinstance(i, dict) and "in_collision" in i for i in rows):
        raise ConventionError("compute_reward with self_collision='penalize' needs the steps' info (dicts "
                              "with 'in_collision'), got " + type(info).__name__)
    host = lambda v: v.cpu() if isinstance(v, Tensor) else v  # noqa: E731
    vals = [np.asarray(host(i["in_collision"]), dtype=bool) for i in rows]
    return vals[0] if isinstance(info, dict) else np.stack(vals).reshape(np.shape(info))


class ReachEnv(TaskEnv):
    """``diffkin/Reach-v0``: bring the end effector of a kinematic arm to a goal position.

    ## Description
    Kinematic reach with any diffkin chain (default the Franka Panda; no dynamics, no collisions): bring the
    end effector within ``distance_threshold`` of a goal position. By default goals are uniform in a 0.3 m
    cube around the end effector at the start pose (``goal_sampling="box"``, panda-gym's PandaReach
    distribution); ``goal_sampling="joints"`` draws them as the end-effector positions of random joint
    vectors within the limits (the whole workspace, every goal reachable). Goal-conditioned (a ``Dict``
    observation with ``achieved_goal`` / ``desired_goal`` and a vectorised :meth:`compute_reward`), so it
    works with stable-baselines3's ``HerReplayBuffer``; the batched version of the same task is
    ``TorchVectorEnv("diffkin/Reach-v0", N)``.

    ## Action Space
    ``Box(-1.0, 1.0, (nv,), float32)`` with ``action_mode="joint"`` (nv = the chain's velocity count: its
    joint count, 7 for the Panda; a ball joint counts 3): joint velocities ``q̇ = a · max_joint_speed``
    (1.5 rad/s), integrated over ``control_dt`` (0.1 s) on the configuration manifold, ``q ⊕ q̇ Δt``
    (:meth:`~diffkin.chain.KinematicChain.integrate`: ``q + q̇ Δt`` for 1-DOF joints; the quaternion of a
    ball or free joint is turned by ``exp(ω Δt / 2)`` and stays unit) and clamped to the joint limits.
    ``Box(-1.0, 1.0, (3,), float32)`` with ``action_mode="cartesian"``: an end-effector displacement
    ``Δx = a · max_ee_step`` (0.05 m, base frame) turned into ``q ⊕ q̇ · control_dt`` by
    :func:`diffkin.ik.velocity_step`: the damped-least-squares step (damping λ = 0.05²) solved exactly under
    ``|q̇| ≤ max_joint_speed`` and the joint limits (limit-safe: a joint at its limit stops and the others
    take over).
    Actions outside [-1, 1] are clipped; NaN/inf or a wrong shape raise ``ValueError`` subclasses.

    ## Observation Space
    ``Dict`` of float32 ``Box`` es, positions in metres in the chain's base frame:

    | key | shape | content |
    |---|---|---|
    | ``observation`` | ``(6,)`` | ``p_ee``, then ``ṗ_ee`` (m/s): the default ``observation`` parts |
    | ``achieved_goal`` | ``(3,)`` | the end-effector position ``p_ee`` |
    | ``desired_goal`` | ``(3,)`` | the goal position |

    ``observation`` holds the parts named by the ``observation`` argument, in that order: ``"ee_position"``
    (``p_ee``, 3), ``"ee_velocity"`` (``(p_ee(t) − p_ee(t − 1)) / control_dt``, the mean velocity over the
    last control period, 3; 0 after a reset), ``"joint_positions"`` (q mapped to [-1, 1] by the limits, nq)
    and ``"joint_velocities"`` ((q(t) ⊖ q(t − 1)) / control_dt, nv). The default ``("ee_position",
    "ee_velocity")`` is the layout of panda-gym's PandaReach observation (whose velocity is PyBullet's, at the
    grasp point, at the end of a 0.04 s step); with it TQC + HER learns joint-velocity Reach in fewer steps
    than with the joint positions in the observation (``docs/rl/RESULTS.md``). Bounds: ``±w`` for positions,
    with ``w`` a generous bound on the reach (``|p_ee(home)| + 2 m +`` the sum of the DH offsets), ``±2w /
    control_dt`` for the velocity, ±1 for the joints, ``±2 max_joint_speed`` for the joint velocities; SB3
    needs ``MultiInputPolicy`` for this ``Dict``.

    ## Rewards
    ``reward_type="sparse"`` (default): 0 when ``‖p_ee − goal‖ < distance_threshold``, else -1.
    ``reward_type="dense"``: ``-‖p_ee − goal‖`` (m). ``compute_reward(achieved_goal, desired_goal, info)``
    computes the same over any leading batch dimensions (what HER relabelling calls). With
    ``self_collision="penalize"``: minus ``collision_penalty`` at a step in collision (``compute_reward``
    reads ``in_collision`` from the ``info`` it is given: one dict, or the sequence HER passes).

    ## Starting State
    ``q0 = home ⊕ init_noise · U(-1, 1)^nv`` (0.1 rad; ``home + ...`` for 1-DOF joints), clamped to the
    limits; ``home`` is the model's own (its YAML ``home``: the Panda's "ready" pose, the UR5's and the
    planar arm's), else the middle of the limits with identity quaternions.
    The goal (base frame, m): with ``goal_sampling="box"`` uniform in ``goal_center ± goal_range / 2`` per
    axis (``goal_center`` default ``p_ee(home)``, ``goal_range`` 0.3 m; z fixed for the planar arm); with
    ``goal_sampling="joints"`` ``p_ee(home + goal_spread · (U(limits) − home))`` (``goal_spread=1``: the
    whole workspace; on the manifold the geodesic from ``home`` towards a uniform configuration, quaternions
    uniform on the sphere). "Planar" is the model's ``planar`` flag, not its name.

    PandaReach-v3 as here (``configs/tqc.yaml``): ``home=[0, 0.41, 0, -1.85, 0, 2.26, 0.79]`` (panda-gym's
    neutral pose), ``init_noise=0``, ``goal_center=(0.6, 0, 0.255)`` (panda-gym's cube, centre (0, 0, 0.15)
    in its world where the base sits at (-0.6, 0, 0), raised by the 0.105 m from diffkin's flange to
    panda-gym's grasp point), the default observation (panda-gym's), and ``max_joint_speed=0.25`` (0.025 rad
    per step: panda-gym commands 0.05 rad, but its position control carries out only part of it, and at
    0.05 rad the policies, which do not see their joints, do not settle at the goal but drift off it, often
    with a joint at its limit; ``docs/rl/RESULTS.md``).

    Kinematic domain randomisation (``robot_config`` ``geometry_noise_length`` m / ``geometry_noise_angle``
    rad, default 0): every episode of every env draws its own robot, the DH lengths (a, d) and angles
    (alpha, theta) uniformly within that noise of nominal (seeded as the rest of the episode; the goal and
    start pose of a seed are the same with and without it). The end effector (observation, reward, goals
    drawn in joint space) is the FK of that robot; the Cartesian action's DLS step uses the nominal model,
    as a controller that only knows the nominal robot would.

    ## Episode End
    Truncated after ``episode_steps`` steps (50). Terminated on success only with
    ``terminate_on_success=True`` (default False), and on self-collision with
    ``self_collision="terminate"``. ``info`` holds ``is_success`` (bool) and ``distance`` (m) at every step;
    with collision checks also ``min_distance`` (m, the smallest signed distance of the checked pairs) and
    ``in_collision`` (bool). No ``TimeLimit`` wrapper is registered: ``gymnasium.make(id,
    max_episode_steps=k)`` adds an outer one.

    ## Arguments
    ```python
    gymnasium.make("diffkin/Reach-v0", robot="panda", action_mode="joint", render_mode=None,
                   robot_config=None, home=None, dtype=torch.float32, device="cpu",
                   reward_type="sparse", distance_threshold=0.05, episode_steps=50, goal_sampling="box",
                   goal_center=None, goal_range=0.3, goal_spread=1.0, init_noise=0.1,
                   terminate_on_success=False, observation=("ee_position", "ee_velocity"),
                   self_collision=None, collision_penalty=1.0, collision_margin=0.0, collision=None)
    ```

    * ``robot``: a model name of :func:`diffkin.models.load` (``"panda"``, ``"ur5"``, ``"three_link_planar"``,
      ...) or a :class:`~diffkin.chain.KinematicChain` (copied): a DH chain, a URDF chain
      (:func:`diffkin.models.from_urdf`) or a MuJoCo model (:func:`diffkin.models.from_mjcf`), ball and free
      joints included.
    * ``action_mode``: ``"joint"`` or ``"cartesian"`` (above).
    * ``render_mode``: None or ``"rgb_array"`` (a matplotlib drawing of the arm, its trace and the goal).
    * ``robot_config``: :class:`~diffkin.envs.robot.RobotConfig` or a dict of its fields
      (``max_joint_speed`` 1.5 rad/s, ``control_dt`` 0.1 s, ``max_ee_step`` 0.05 m, ``damping`` 0.0025 (λ),
      ``geometry_noise_length`` 0 m, ``geometry_noise_angle`` 0 rad).
    * ``home``: the start pose ``(n,)`` (default above); ``dtype`` (float32 or float64) and ``device`` of
      the kinematics (observations are always float32 numpy).
    * the fields of :class:`ReachConfig`: ``reward_type``, ``distance_threshold`` (m), ``episode_steps``,
      ``goal_sampling`` ("box" | "joints"), ``goal_center`` ((3,) m or None), ``goal_range`` (m),
      ``goal_spread`` in [0, 1] (joints only), ``init_noise`` (rad), ``terminate_on_success``,
      ``observation`` (a sequence of ``"ee_position"``, ``"ee_velocity"``, ``"joint_positions"``,
      ``"joint_velocities"``), ``self_collision`` (None | "terminate" | "penalize"), ``collision_penalty``,
      ``collision_margin`` (m).
    * ``collision``: the :class:`~diffkin.collision.RobotCollision` to check (copied onto the env's chain,
      dtype and device); None: built from the robot's URDF (its ``<collision>`` geoms) or MJCF when
      ``self_collision`` is set (a DH model has no geometry: a ``ModelError`` says to pass one).

    ## Version History
    * v0: initial version. Goals were over the whole joint range; since issue 19 the default is the goal
      cube (``goal_sampling="box"``), the old distribution is ``goal_sampling="joints"``; kinematic domain
      randomisation added (off by default); the observation is panda-gym's ``[p_ee, ṗ_ee]`` by default
      (before: ``[normalised q, p_ee]``, ``observation=("joint_positions", "ee_position")``). The Cartesian
      action is velocity_step (issue 29): the damped-least-squares step solved exactly under
      |q̇| ≤ max_joint_speed and the joint limits over control_dt, instead of the DLS step scaled down
      as a whole and clamped (over joints drawn in the whole range, 1/3 of the steps change and the mean
      end-effector error of a 0.05 m step falls from 9.1 to 7.1 mm); the exact solve costs: 4 096
      Cartesian Reach envs step at 0.18–0.34 M env-steps per CPU second instead of 0.8–1.4 M, 4–5× the
      time (one thread, several runs on a shared machine). Joint mode is unchanged. Issues 26/27: robots
      with ball and free joints (actions of nv components applied on the manifold, episodes of 1-DOF
      robots unchanged to the bit), the ``"joint_velocities"`` observation part, ``self_collision``.
    """

    def __init__(self, robot="panda", action_mode: str = "joint", render_mode: str | None = None,
                 robot_config=None, home=None, dtype=torch.float32, device="cpu", collision=None,
                 **task_kwargs):
        task = ReachTask(ReachConfig(**task_kwargs), collision=collision, robot=robot,
                         action_mode=action_mode, robot_config=robot_config, home=home, dtype=dtype,
                         device=device)
        super().__init__(task, render_mode=render_mode)

    def compute_reward(self, achieved_goal, desired_goal, info=None):
        return self.task.compute_reward(achieved_goal, desired_goal, info)
