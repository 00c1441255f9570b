"""The envs on the configuration manifold (issue 26 item 1): a MuJoCo model with ball joints as the robot.

References: MuJoCo's own ``mj_integratePos`` / ``mj_differentiatePos`` for the steps and velocities, scipy's
uniform rotations for the start-configuration sampler; the model-data facts (``home``, ``planar``) of
issue 30 item 13 against the numbers of the YAML files.
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import diffkin.envs  # noqa: F401
from diffkin import models
from diffkin.chain import DHChain
from diffkin.envs.robot import Robot
from diffkin.envs.vector import TorchVectorEnv
from diffkin.errors import ModelError
from diffkin.kernels.configuration import ConfigurationSpace

mujoco = pytest.importorskip("mujoco")

KINDS = Path(__file__).parent / "data" / "mjcf_extra" / "joint_kinds.xml"
F64 = torch.float64
OBS = ("ee_position", "joint_positions", "joint_velocities")


def _ball_arm(dtype=F64):
    """torso → palm of the joint-kinds model: a ball shoulder, two hinges, a slide, a hinge (nq 8, nv 7)."""
    return models.from_mjcf(KINDS, "palm", root_link="torso", dtype=dtype)


def _mujoco_integrate(m, chain, q, v):
    """q ⊕ v by ``mj_integratePos`` on the whole model (the chain's joints' dofs set, dt = 1)."""
    qpos = chain.to_qpos(torch.as_tensor(q, dtype=F64)).numpy().copy()
    qvel = np.zeros(m.nv)
    i = 0
    for name in chain.joint_names:
        j = m.joint(name)
        k = {0: 6, 1: 3}.get(int(j.type[0]), 1)  # free, ball, else one dof
        qvel[j.dofadr[0]:j.dofadr[0] + k] = np.asarray(v)[i:i + k]
        i += k
    mujoco.mj_integratePos(m, qpos, qvel, 1.0)
    return chain.from_qpos(torch.tensor(qpos)).numpy()


@pytest.mark.parametrize("action_mode", ["joint", "cartesian"])
def test_check_env_and_spaces_with_ball_joints(action_mode):
    chain = _ball_arm(torch.float32)
    env = gym.make("diffkin/Reach-v0", robot=chain, action_mode=action_mode, observation=OBS)
    check_env(env.unwrapped, skip_render_check=True)
    assert env.action_space.shape == ((chain.nv,) if action_mode == "joint" else (3,))
    # p_ee (3), q (nq), q̇ (nv)
    assert env.observation_space["observation"].shape == (3 + chain.nq + chain.nv,)
    check_env(gym.make("diffkin/Track-v0", robot=chain, action_mode=action_mode).unwrapped,
              skip_render_check=True)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("action_mode", ["joint", "cartesian"])
def test_quaternion_stays_unit_and_the_step_is_mujocos_integrate(dtype, action_mode):
    chain, ref_chain = _ball_arm(dtype), _ball_arm()  # the float64 one converts to and from MuJoCo's qpos
    m = mujoco.MjModel.from_xml_path(str(KINDS))
    env = gym.make("diffkin/Reach-v0", robot=chain, action_mode=action_mode, observation=OBS, dtype=dtype,
                   goal_sampling="joints", episode_steps=200)
    robot = env.unwrapped.robot
    env.reset(seed=4)
    rng = np.random.default_rng(4)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    lo, hi = robot.lower.double().numpy(), robot.upper.double().numpy()
    for _ in range(200):
        q0 = env.unwrapped._state["q"][0].double().numpy().copy()
        a = rng.uniform(-1.5, 1.5, env.action_space.shape).astype(np.float32)  # clipped to ±1
        obs, *_ = env.step(a)
        q1 = env.unwrapped._state["q"][0].double().numpy()
        assert abs(np.linalg.norm(q1[:4]) - 1.0) < tol  # on the sphere after every step
        qd = env.unwrapped._state["joint_velocity"][0].double().numpy()
        np.testing.assert_array_equal(obs["observation"][3 + chain.nq:], qd.astype(np.float32))
        # the velocity observed is MuJoCo's q1 ⊖ q0 over the control period
        v = np.zeros(m.nv)
        p0, p1 = (ref_chain.to_qpos(torch.tensor(x)).numpy() for x in (q0, q1))
        mujoco.mj_differentiatePos(m, v, robot.config.control_dt, p0, p1)
        dofs = np.concatenate([np.arange(m.joint(n).dofadr[0], m.joint(n).dofadr[0] + k)
                               for n, k in zip(chain.joint_names, (3, 1, 1, 1, 1))])
        np.testing.assert_allclose(qd, v[dofs], atol=1e-4 if dtype == torch.float32 else 1e-6, rtol=0)
        if action_mode == "joint":
            step = np.clip(a, -1, 1).astype(np.float64) * robot.step_limit
            ref = _mujoco_integrate(m, ref_chain, q0, step)
            ref[4:] = np.clip(ref[4:], lo[4:], hi[4:])  # the scalar joints are projected onto their limits
            np.testing.assert_allclose(q1, ref, atol=10 * tol, rtol=0)
            inside = (ref[4:] > lo[4:]) & (ref[4:] < hi[4:])
            np.testing.assert_allclose(qd[3:][inside], step[3:][inside] / robot.config.control_dt,
                                       atol=1e-3 if dtype == torch.float32 else 1e-9, rtol=0)
            # and the step is the chain's own integrate
            ours = chain.integrate(torch.tensor(q0, dtype=dtype), torch.tensor(step, dtype=dtype))
            ours = robot.chain.clamp_to_limits(ours.to(dtype)).double().numpy()
            np.testing.assert_allclose(q1, ours, atol=tol, rtol=0)


def test_resets_on_the_manifold_and_vector_equals_single():
    chain = _ball_arm(torch.float32)
    kw = dict(robot=chain, observation=OBS, goal_sampling="joints", episode_steps=5)
    vec = TorchVectorEnv("diffkin/Reach-v0", 3, **kw)
    obs, _ = vec.reset(seed=10)
    for i in range(3):
        single = gym.make("diffkin/Reach-v0", **kw)
        o, _ = single.reset(seed=10 + i)
        np.testing.assert_array_equal(o["observation"], obs["observation"][i].numpy())
        np.testing.assert_array_equal(o["desired_goal"], obs["desired_goal"][i].numpy())
    q = vec.state["q"]
    torch.testing.assert_close(q[:, :4].norm(dim=-1), torch.ones(3))
    assert bool(chain.within_limits(q, tol=1e-6).all())
    # at reset the velocity part is zero and q is the perturbed home: home ⊕ init_noise · (2u − 1)
    assert float(obs["observation"][:, -chain.nv:].abs().max()) == 0.0
    home = vec.task.robot.home
    d = chain.difference(home.expand_as(q), q)
    assert float(d.abs().max()) <= 0.1 + 1e-6  # init_noise
    # the home of a chain without model data: mid-range scalars, the identity quaternion (neutral)
    torch.testing.assert_close(home[:4], torch.tensor([1.0, 0.0, 0.0, 0.0]))


def test_from_uniform_quaternions_are_uniform_on_the_sphere():
    """Shoemake's map against scipy's uniform rotations: the rotation angle's distribution (two-sample KS)."""
    from scipy.spatial.transform import Rotation
    from scipy.stats import ks_2samp

    space = ConfigurationSpace(["R", "S", "P"])
    g = torch.Generator().manual_seed(0)
    u = torch.rand(20000, space.nv, generator=g, dtype=F64)
    lo, hi = torch.tensor([-1.0, 0.0], dtype=F64), torch.tensor([2.0, 0.5], dtype=F64)
    q = space.from_uniform(lo, hi, u)
    assert q.shape == (20000, space.nq)
    torch.testing.assert_close(q[:, 1:5].norm(dim=-1), torch.ones(20000, dtype=F64))
    assert bool((q[:, 1] >= 0).all())  # η ≥ 0
    torch.testing.assert_close(q[:, 0], -1.0 + 3.0 * u[:, 0])
    torch.testing.assert_close(q[:, 5], 0.5 * u[:, 1])  # scalars take the first uniforms, then the quaternion
    ours = 2 * np.arccos(np.clip(q[:, 1].numpy(), -1, 1))
    ref = Rotation.random(20000, random_state=1).magnitude()
    assert ks_2samp(ours, ref).pvalue > 1e-3
    # and every axis direction equally likely: mean of the vector part ≈ 0, E[x²] = E[y²] = E[z²] = 1/4
    vec = q[:, 2:5].numpy()
    np.testing.assert_allclose(vec.mean(0), 0.0, atol=0.02)
    np.testing.assert_allclose((vec ** 2).mean(0), 0.25, atol=0.01)
    # a Euclidean space: exactly the affine map (the envs' 1-DOF draws)
    flat = ConfigurationSpace(["R", "P"])
    u2 = torch.rand(5, 2, generator=g)
    torch.testing.assert_close(flat.from_uniform(torch.zeros(2), 2 * torch.ones(2), u2), 2 * u2, rtol=0,
                               atol=0)


# --------------------------------------------------------------------------- model data (issue 30, 13)
def test_home_and_planar_are_model_data():
    panda, ur5, planar = models.load("panda"), models.load("ur5"), models.load("three_link_planar")
    assert panda.home == [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785] and not panda.planar
    assert ur5.home == [0.0, -1.571, 1.571, -1.571, -1.571, 0.0] and not ur5.planar
    assert planar.home == [0.3, 0.6, 0.6] and planar.planar
    assert models.load("stanford").home is None and not models.load("stanford").planar
    # what the envs start from and how they draw: the model's data, whatever the chain's name
    robot = Robot(planar)
    torch.testing.assert_close(robot.home, torch.tensor([0.3, 0.6, 0.6]))
    assert robot.planar
    renamed = planar.copy()
    renamed.name = "my_arm"
    assert Robot(renamed).planar and renamed.home == planar.home
    bare = DHChain([0.5] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3, name="three_link_planar")
    assert not Robot(bare).planar  # the name no longer decides
    torch.testing.assert_close(Robot(bare).home, torch.zeros(3))  # the middle of ±π


def test_home_and_planar_round_trip_and_errors():
    text = models.load("three_link_planar").to_yaml()
    assert "home:" in text and "planar: true" in text
    again = DHChain.from_yaml(text)
    assert again.home == [0.3, 0.6, 0.6] and again.planar
    base = "name: x\ndh:\n  - {a: 1, alpha: 0, d: 0, theta: 0}\nq_limits: [[-1, 1]]\n"
    assert DHChain.from_yaml(base + "home: [pi/8]\n").home == [np.pi / 8]
    for extra, match in (("home: [0, 0]\n", "home"), ("home: [2]\n", "home\\[0\\].*outside"),
                         ("home: [x]\n", "home"), ("planar: yes please\n", "planar"),
                         ("planar: 1\n", "planar")):
        with pytest.raises(ModelError, match=match):
            DHChain.from_yaml(base + extra)


def test_unknown_robot_names_the_models():
    with pytest.raises(ModelError, match="unknown model 'nobot'.*panda"):
        gym.make("diffkin/Reach-v0", robot="nobot")


def test_cartesian_steps_move_the_ball_arm_towards_the_goal_and_track_stays_on_the_sphere():
    """The Cartesian action's velocity_step (nv velocities) applied with integrate moves the end effector as
    commanded: a step of Δx towards a nearby goal shrinks the distance by about |Δx| (first order)."""
    chain = _ball_arm(F64)
    env = gym.make("diffkin/Reach-v0", robot=chain, action_mode="cartesian", dtype=F64, goal_range=0.1)
    obs, _ = env.reset(seed=2)
    step = env.unwrapped.robot.config.max_ee_step
    d0 = np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"])
    for _ in range(3):
        gap = obs["desired_goal"] - obs["achieved_goal"]
        dx = gap / max(np.linalg.norm(gap), 1e-9) * min(np.linalg.norm(gap), 0.2 * step)
        obs, _, _, _, info = env.step((dx / step).astype(np.float32))
        d1 = info["distance"]
        assert d1 < d0 - 0.5 * np.linalg.norm(dx)  # at least half the commanded progress
        d0 = d1
    track = gym.make("diffkin/Track-v0", robot=chain, dtype=F64, episode_steps=30)
    track.reset(seed=5)
    rng = np.random.default_rng(5)
    for _ in range(30):
        obs, *_ = track.step(rng.uniform(-1, 1, track.action_space.shape).astype(np.float32))
        q = track.unwrapped._state["q"][0]
        assert abs(float(q[:4].norm()) - 1.0) < 1e-12
        np.testing.assert_array_equal(obs[:chain.nq][:4], q[:4].numpy().astype(np.float32))  # as they are
