"""Single envs: check_env on every registered diffkin ID, determinism, rewards, errors, rendering."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import diffkin.envs  # noqa: F401
from diffkin.chain import DHChain
from diffkin.envs.reach import ReachEnv

# the arm envs (any chain, joint and Cartesian actions); diffkin/Imitate-v0: tests/test_envs_imitate.py
ENV_IDS = sorted(k for k in gym.registry if k.startswith("diffkin/") and k != "diffkin/Imitate-v0")


def test_ids_registered():
    assert {"diffkin/Reach-v0", "diffkin/Track-v0"} <= set(ENV_IDS)
    assert "diffkin/Imitate-v0" in gym.registry


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("action_mode", ["joint", "cartesian"])
def test_check_env(env_id, action_mode):
    env = gym.make(env_id, action_mode=action_mode)
    check_env(env.unwrapped, skip_render_check=True)
    assert env.action_space.shape == ((7,) if action_mode == "joint" else (3,))


@pytest.mark.parametrize("robot", ["ur5", "three_link_planar"])
def test_check_env_other_robots(robot):
    for env_id in ENV_IDS:
        env = gym.make(env_id, robot=robot)
        check_env(env.unwrapped, skip_render_check=True)


def _rollout(env, seed, steps=60):
    env.action_space.seed(seed)
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for _ in range(steps):
        obs, r, term, trunc, info = env.step(env.action_space.sample())
        out.append((obs, r, term, trunc))
        if term or trunc:
            out.append(env.reset()[0])
    return out


def _flat(items):
    flat = []
    for it in items:
        if isinstance(it, tuple):
            flat.extend(_flat(list(it)))
        elif isinstance(it, dict):
            flat.extend(np.ravel(it[k]) for k in sorted(it))
        else:
            flat.append(np.ravel(np.asarray(it, dtype=np.float64)))
    return flat


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_seed_determinism(env_id):
    a = _flat(_rollout(gym.make(env_id), 3))
    b = _flat(_rollout(gym.make(env_id), 3))
    c = _flat(_rollout(gym.make(env_id), 4))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


def test_goals_reachable_and_in_plane_for_planar_arm():
    env = ReachEnv(robot="three_link_planar")
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        assert obs["desired_goal"][2] == pytest.approx(0.0, abs=1e-6)
        assert np.linalg.norm(obs["desired_goal"][:2]) <= 1.5 + 1e-5  # reach of 3 × 0.5 m links


def test_any_dhchain_instance():
    chain = DHChain([0.4, 0.3], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], q_limits=[(-2.0, 2.0)] * 2,
                    name="two_link")
    env = ReachEnv(robot=chain)
    check_env(env, skip_render_check=True)
    assert env.action_space.shape == (2,)


@pytest.mark.parametrize("reward_type", ["sparse", "dense"])
def test_compute_reward_vectorised_equals_per_sample(reward_type):
    env = gym.make("diffkin/Reach-v0", reward_type=reward_type).unwrapped
    rng = np.random.default_rng(0)
    ag = rng.normal(size=(64, 3)).astype(np.float32) * 0.1
    dg = ag + rng.normal(size=(64, 3)).astype(np.float32) * 0.04
    batch = env.compute_reward(ag, dg, [{}] * 64)
    single = np.array([env.compute_reward(a, d, {}) for a, d in zip(ag, dg)])
    assert batch.shape == (64,)
    np.testing.assert_array_equal(batch, single)
    d = np.linalg.norm(ag - dg, axis=-1)
    expected = -(d > 0.05).astype(np.float32) if reward_type == "sparse" else -d
    np.testing.assert_allclose(batch, expected, rtol=1e-6)
    assert len(set(np.unique(batch))) > 1


def test_step_reward_matches_compute_reward_and_success():
    env = gym.make("diffkin/Reach-v0").unwrapped
    obs, _ = env.reset(seed=0)
    for _ in range(10):
        obs, r, _, _, info = env.step(env.action_space.sample())
        assert r == pytest.approx(float(env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)))
        assert info["is_success"] == (np.linalg.norm(obs["achieved_goal"] - obs["desired_goal"]) < 0.05)


def test_joint_limits_respected():
    env = gym.make("diffkin/Reach-v0").unwrapped
    env.reset(seed=0)
    for _ in range(60):
        env.step(np.ones(7, dtype=np.float32))
    q = env._state["q"][0]
    assert bool(env.robot.chain.within_limits(q, tol=1e-6))
    assert torch.allclose(q, env.robot.upper)


BAD = [np.zeros(6), np.zeros((1, 7)), np.array([np.nan] * 7), np.array([np.inf] + [0] * 6)]


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("bad", BAD)
def test_bad_actions_raise_value_error(env_id, bad):
    env = gym.make(env_id).unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(bad.astype(np.float32))


def test_track_reward_is_minus_tracking_error_and_starts_on_path():
    env = gym.make("diffkin/Track-v0").unwrapped
    obs, _ = env.reset(seed=1)
    n = env.robot.n
    assert np.allclose(obs[n + 3:n + 6], 0.0, atol=1e-6)  # first target = current EE position
    _, r, term, _, info = env.step(np.zeros(7, dtype=np.float32))
    assert r == pytest.approx(-info["tracking_error"]) and not term


@pytest.mark.parametrize("env_id", ENV_IDS)
@pytest.mark.parametrize("robot", ["panda", "three_link_planar"])
def test_render_rgb_array(env_id, robot):
    env = gym.make(env_id, robot=robot, render_mode="rgb_array")
    env.reset(seed=0)
    env.step(env.action_space.sample())
    img = env.render()
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.std() > 0  # something was drawn
    env.close()


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_actions_by_the_input_rule(env_id):
    """numpy (any float or integer dtype), lists and float32/float64 tensors are the same action; integer,
    bool, complex and half tensors and bool/complex numpy arrays are typed errors, never cast silently."""
    from diffkin.errors import DTypeError, NonFiniteError, ShapeError

    env = gym.make(env_id).unwrapped
    a = np.array([1, 0, -1, 0, 1, 0, -1])
    ref = None
    for action in (a.astype(np.float32), a.astype(np.float64), a, a.tolist(), torch.tensor(a).float(),
                   torch.tensor(a).double()):
        env.reset(seed=3)
        obs = env.step(action)[0]
        obs = obs["observation"] if isinstance(obs, dict) else obs
        if ref is None:
            ref = obs
        np.testing.assert_array_equal(obs, ref)
    for bad in (torch.tensor(a), torch.tensor(a).bool(), torch.tensor(a).half(), torch.tensor(a).bfloat16(),
                torch.tensor(a).to(torch.complex64), a.astype(bool), a.astype(np.complex64), "0101010"):
        env.reset(seed=3)
        with pytest.raises(DTypeError):
            env.step(bad)
    env.reset(seed=3)
    with pytest.raises(NonFiniteError, match="action"):
        env.step(torch.full((7,), float("nan")))
    with pytest.raises(ShapeError, match=r"\(7,\)"):
        env.step(torch.zeros(1, 7))
    q_before = env._state["q"].clone()
    with pytest.raises(NonFiniteError):
        env.step(np.array([0, 0, 0, np.inf, 0, 0, 0]))
    assert torch.equal(env._state["q"], q_before)  # a refused action leaves the state alone


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_reset_options_and_constructor_settings(env_id):
    from diffkin.errors import ConventionError, DiffkinError, DTypeError, ModelError, ShapeError

    env = gym.make(env_id).unwrapped
    env.reset(seed=0, options=None)
    env.reset(seed=0, options={})
    with pytest.raises(ConventionError, match="goal"):
        env.reset(seed=0, options={"goal": [0.1, 0.2, 0.3]})  # not an option of these envs: not ignored
    bad = [dict(episode_steps=0), dict(episode_steps=2.5), dict(init_noise=float("nan")),
           dict(init_noise=-0.1), dict(robot_config=dict(control_dt=0.0)),
           dict(robot_config=dict(max_joint_speed=float("inf")))]
    if env_id == "diffkin/Reach-v0":
        bad += [dict(distance_threshold=float("nan")), dict(distance_threshold=0.0), dict(goal_spread=1.5),
                dict(goal_sampling="sphere"), dict(goal_range=-0.1), dict(goal_range=float("inf")),
                dict(goal_center=(0.5, 0.0)), dict(goal_center=(0.5, float("nan"), 0.2)),
                dict(robot_config=dict(geometry_noise_length=-0.01)),
                dict(robot_config=dict(geometry_noise_angle=float("nan")))]
    else:
        bad += [dict(radius_range=(0.2, 0.1)), dict(line_fraction=-0.5), dict(lookahead=-1)]
    for kwargs in bad:
        with pytest.raises(DiffkinError):
            gym.make(env_id, **kwargs)
    with pytest.raises(ConventionError, match="action_mode"):
        gym.make(env_id, action_mode="torque")
    with pytest.raises(DTypeError, match="float16"):
        gym.make(env_id, dtype=torch.float16)
    with pytest.raises(ShapeError, match="home"):
        gym.make(env_id, home=[0.0] * 6)
    with pytest.raises(DiffkinError, match="home"):
        gym.make(env_id, home=[float("nan")] * 7)
    with pytest.raises(ModelError):
        gym.make(env_id, robot="no_such_robot")
    if env_id == "diffkin/Reach-v0":
        with pytest.raises(ConventionError, match="reward_type"):
            gym.make(env_id, reward_type="shaped")


def test_reach_reward_numpy_and_torch_agree_and_refuse_bad_goals():
    from diffkin.envs.reach import reach_reward
    from diffkin.errors import DTypeError, NonFiniteError, ShapeError

    g = np.random.default_rng(0)
    a, d = g.uniform(-1, 1, (5, 3)), g.uniform(-1, 1, (5, 3))
    dist = np.linalg.norm(a - d, axis=-1)
    r_np = reach_reward(a, d, "dense", 0.05)
    assert r_np.dtype == np.float32 and r_np.shape == (5,)
    np.testing.assert_allclose(r_np, -dist, rtol=1e-6)
    r_t = reach_reward(torch.from_numpy(a), torch.from_numpy(d), "dense", 0.05)
    assert r_t.dtype == torch.float64 and torch.allclose(r_t, torch.from_numpy(-dist))
    sparse = reach_reward(a, d[0], "sparse", 1.0)  # (5, 3) against one goal (3,)
    np.testing.assert_array_equal(sparse, -(np.linalg.norm(a - d[0], axis=-1) > 1.0).astype(np.float32))
    assert reach_reward(a[0], d[0], "dense", 0.05).shape == ()
    with pytest.raises(NonFiniteError, match="desired_goal"):
        reach_reward(a, np.full((5, 3), np.nan), "dense", 0.05)
    with pytest.raises(ShapeError, match="achieved_goal"):
        reach_reward(a[:, :2], d, "dense", 0.05)
    with pytest.raises(ShapeError, match="broadcast"):
        reach_reward(a, d[:4], "dense", 0.05)
    with pytest.raises(DTypeError, match="float32"):
        reach_reward(torch.from_numpy(a).float(), torch.from_numpy(d), "dense", 0.05)


def test_goal_box_default_and_centre():
    """Goals uniform in the cube of edge goal_range around goal_center (default: p_ee at home), base frame."""
    env = ReachEnv()  # default: a 0.3 m cube around the end effector at the home pose
    home_ee = env.robot.ee_position(env.robot.home[None])[0].numpy()
    goals = np.array([env.reset(seed=s)[0]["desired_goal"] for s in range(200)])
    assert np.all(np.abs(goals - home_ee) <= 0.15 + 1e-6)
    assert np.all(goals.max(0) - goals.min(0) > 0.25)  # spread over the whole cube, each axis
    env = ReachEnv(goal_center=(0.6, 0.0, 0.255), goal_range=0.1)
    goals = np.array([env.reset(seed=s)[0]["desired_goal"] for s in range(50)])
    assert np.all(np.abs(goals - [0.6, 0.0, 0.255]) <= 0.05 + 1e-6)
    env = ReachEnv(goal_range=0.0, goal_center=[0.5, 0.1, 0.3])  # a list (YAML) works as a tuple
    assert np.allclose(env.reset(seed=3)[0]["desired_goal"], [0.5, 0.1, 0.3], atol=1e-6)
    planar = ReachEnv(robot="three_link_planar")
    assert all(abs(planar.reset(seed=s)[0]["desired_goal"][2]) < 1e-6 for s in range(10))


def test_goal_sampling_joints_keeps_the_old_distribution():
    """goal_sampling="joints": goals are end-effector positions of random joints (goal_spread=0: home)."""
    env = ReachEnv(goal_sampling="joints", goal_spread=0.0)
    home_ee = env.robot.ee_position(env.robot.home[None])[0].numpy()
    assert np.allclose(env.reset(seed=1)[0]["desired_goal"], home_ee, atol=1e-6)
    wide = ReachEnv(goal_sampling="joints")
    goals = np.array([wide.reset(seed=s)[0]["desired_goal"] for s in range(50)])
    assert np.linalg.norm(goals - home_ee, axis=1).max() > 0.5  # the whole workspace, not a 0.3 m cube


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("robot_config", [None, dict(geometry_noise_length=0.02, geometry_noise_angle=0.04)])
def test_observation_end_effector_position_and_velocity(dtype, robot_config):
    """Default observation: [p_ee, (p_ee(t) − p_ee(t−1)) / control_dt], the velocity 0 right after a
    reset; p_ee is the episode's robot's (domain randomisation), so the velocity is the achieved goal's
    difference."""
    env = ReachEnv(dtype=dtype, robot_config=robot_config, episode_steps=4)
    dt = env.robot.config.control_dt
    obs, _ = env.reset(seed=0)
    assert obs["observation"].shape == (6,) and env.observation_space.contains(obs)
    np.testing.assert_array_equal(obs["observation"][:3], obs["achieved_goal"])
    np.testing.assert_array_equal(obs["observation"][3:], 0.0)
    rng = np.random.default_rng(0)
    prev = obs["achieved_goal"].astype(np.float64)
    for _ in range(9):  # over two episode ends: the first observation of an episode is at rest again
        obs, _, _, truncated, _ = env.step(rng.uniform(-1, 1, 7).astype(np.float32))
        ee = obs["achieved_goal"].astype(np.float64)
        assert env.observation_space.contains(obs)
        tol = 2e-4 if dtype == torch.float32 else 1e-5  # the observation is float32 either way
        np.testing.assert_allclose(obs["observation"][3:], (ee - prev) / dt, atol=tol)
        assert np.linalg.norm(obs["observation"][3:]) > 0.05  # a random joint step moves the end effector
        prev = ee
        if truncated:
            obs, _ = env.reset()
            np.testing.assert_array_equal(obs["observation"][3:], 0.0)
            prev = obs["achieved_goal"].astype(np.float64)


def test_observation_parts_order_and_errors():
    """``observation`` picks and orders the parts; before issue 19 it was (joint_positions, ee_position)."""
    from diffkin.errors import ConventionError

    old = ReachEnv(observation=["joint_positions", "ee_position"])  # a YAML list works as a tuple
    obs, _ = old.reset(seed=2)
    q = old._state["q"]
    assert obs["observation"].shape == (10,) and old.observation_space["observation"].shape == (10,)
    np.testing.assert_allclose(obs["observation"][:7], old.robot.normalize_q(q)[0].numpy(), atol=1e-6)
    np.testing.assert_array_equal(obs["observation"][7:], obs["achieved_goal"])
    lo, hi = old.robot.lower.numpy(), old.robot.upper.numpy()
    np.testing.assert_allclose(obs["observation"][:7], 2 * (q[0].numpy() - lo) / (hi - lo) - 1, atol=1e-6)
    assert "ee" not in old._state  # no velocity bookkeeping when it is not observed
    swapped = ReachEnv(observation=("ee_velocity", "ee_position", "joint_positions"))
    o2, _ = swapped.reset(seed=2)
    o2, *_ = swapped.step(np.full(7, 0.5, np.float32))
    assert o2["observation"].shape == (13,) and swapped.observation_space.contains(o2)
    np.testing.assert_array_equal(o2["observation"][3:6], o2["achieved_goal"])
    assert np.linalg.norm(o2["observation"][:3]) > 0.05
    for bad in ((), ("ee_position", "ee_position"), ("joint_torques",), "ee_position", None):
        with pytest.raises(ConventionError, match="observation"):
            ReachEnv(observation=bad)


def _geometry(env):
    return env.task.geometry(env._state)


DR = dict(geometry_noise_length=0.02, geometry_noise_angle=0.04)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_domain_randomisation_per_episode_seeded_nominal_at_zero(env_id):
    env = gym.make(env_id, robot_config=DR).unwrapped
    env.reset(seed=0)
    g0 = _geometry(env).clone()
    env.reset()
    g1 = _geometry(env).clone()
    assert g0.shape == (1, 28) and not torch.equal(g0, g1)  # a new robot every episode (Panda: 4 × 7 DH)
    nominal = env.robot.nominal_geometry(1)
    dev = (g0 - nominal)[0].reshape(4, 7)  # a, d, alpha, theta: lengths within 2 cm, angles within 0.04 rad
    assert dev[:2].abs().max() <= 0.02 + 1e-6 and dev[2:].abs().max() <= 0.04 + 1e-6
    assert dev[2:].abs().max() > 0.02  # the angles have their own (larger) noise
    assert dev.abs().max() > 0.01
    again = gym.make(env_id, robot_config=DR).unwrapped
    again.reset(seed=0)
    assert torch.equal(_geometry(again), g0)  # deterministic under seeding
    # the end effector is the FK of the episode's robot, not of the nominal one
    q = env._state["q"]
    ee = env.task.ee(env._state)
    assert torch.linalg.vector_norm(ee - env.robot.ee_position(q)) > 1e-3
    chain = env.robot.chain.copy()
    with torch.no_grad():
        for k, v in env.robot.geometry_dict(env._state["geometry"][0]).items():
            getattr(chain, k).copy_(v)
    assert torch.allclose(ee[0], chain.forward_kinematics(q[0])[:3, 3], atol=1e-5)
    # zero noise: no geometry in the state, nominal FK, the same episodes as without the option
    plain = gym.make(env_id).unwrapped
    zero = gym.make(env_id, robot_config=dict(geometry_noise_length=0.0)).unwrapped
    a, b = plain.reset(seed=5)[0], zero.reset(seed=5)[0]
    assert _geometry(zero) is None
    for x, y in zip(_flat([a]), _flat([b])):
        np.testing.assert_array_equal(x, y)
    # with the noise, the same seed gives the same goal/path and start pose as the nominal env
    rnd = gym.make(env_id, robot_config=DR).unwrapped
    rnd.reset(seed=5)
    assert torch.equal(rnd._state["q"], plain._state["q"])
    if env_id == "diffkin/Reach-v0":
        assert torch.equal(rnd._state["goal"], plain._state["goal"])


def test_domain_randomisation_needs_dh_parameters():
    from diffkin.errors import ModelError

    chain = DHChain([0.4, 0.3], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], q_limits=[(-2.0, 2.0)] * 2, name="two")
    env = ReachEnv(robot=chain, robot_config=DR)  # a DH chain of any size works
    env.reset(seed=0)
    assert _geometry(env).shape == (1, 8)

    class Plain(torch.nn.Module):
        pass

    from diffkin.envs.robot import Robot

    robot = Robot(chain)
    robot.config = type(robot.config)(**DR)
    robot.chain = chain  # a chain without DH names is refused with a typed error, not silently nominal
    for name in ("a", "alpha", "d", "theta"):
        delattr(chain, name)
        chain.register_parameter(name, None)
    with pytest.raises(ModelError, match="geometry noise"):
        robot._init_geometry()
