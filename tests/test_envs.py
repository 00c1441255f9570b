"""Single envs: check_env on every registered diffkin ID, determinism, rewards, errors, rendering."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import envs  # noqa: F401
from diffkin.chain import DHChain
from envs.reach import ReachEnv

ENV_IDS = sorted(k for k in gym.registry if k.startswith("diffkin/"))


def test_ids_registered():
    assert {"diffkin/Reach-v0", "diffkin/Track-v0"} <= set(ENV_IDS)


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
