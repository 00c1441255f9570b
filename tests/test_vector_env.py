"""Torch-batched vector env: equals N single envs with the same seeds; one registry; errors."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

import diffkin.envs  # noqa: F401
from diffkin.envs.registry import ENV_IDS as REGISTERED
from diffkin.envs.registry import ENVS
from diffkin.envs.vector import TorchVectorEnv, make_task

ARM_IDS = sorted(k for k in gym.registry if k.startswith("diffkin/") and k != "diffkin/Imitate-v0")
ENV_IDS = ARM_IDS  # diffkin/Imitate-v0 (a humanoid clip, joint actions only): tests/test_envs_imitate.py
CASES = [(e, m) for e in ENV_IDS for m in ("joint", "cartesian")]


def _obs_rows(obs, i):
    if isinstance(obs, dict):
        return {k: v[i].numpy() for k, v in obs.items()}
    return obs[i].numpy()


def _assert_close(a, b):
    if isinstance(a, dict):
        for k in a:
            np.testing.assert_allclose(a[k], b[k], rtol=1e-5, atol=2e-6, err_msg=k)
    else:
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=2e-6)


@pytest.mark.parametrize("env_id,action_mode", CASES)
def test_batched_equals_single_envs_across_episode_boundary(env_id, action_mode):
    n, seed, kw = 4, 7, dict(episode_steps=6, action_mode=action_mode)
    venv = TorchVectorEnv(env_id, n, **kw)
    singles = [gym.make(env_id, **kw) for _ in range(n)]
    obs_b, _ = venv.reset(seed=seed)
    obs_s = [e.reset(seed=seed + i)[0] for i, e in enumerate(singles)]
    for i in range(n):
        _assert_close(obs_s[i], _obs_rows(obs_b, i))
    rng = np.random.default_rng(0)
    for _ in range(15):  # 2.5 episodes: crosses two auto-resets
        actions = rng.uniform(-1, 1, size=(n, *venv.single_action_space.shape)).astype(np.float32)
        obs_b, r_b, te_b, tr_b, info_b = venv.step(torch.as_tensor(actions))
        for i, env in enumerate(singles):
            o, r, te, tr, info = env.step(actions[i])
            assert (te, tr) == (bool(te_b[i]), bool(tr_b[i]))
            assert r == pytest.approx(float(r_b[i]), rel=1e-5, abs=2e-6)
            if te or tr:
                assert bool(info_b["_final_obs"][i])
                _assert_close(o, _obs_rows(info_b["final_obs"], i))
                o, _ = env.reset()
            _assert_close(o, _obs_rows(obs_b, i))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("robot_config", [None, dict(geometry_noise_length=0.04, geometry_noise_angle=0.08)])
def test_reach_velocity_across_partial_resets(dtype, robot_config):
    """Rows that end while others go on (success terminates): an ended row's final observation holds its last
    step's velocity (p_ee difference / control_dt) and achieved goal, its next observation is at rest, and
    every row equals the single env of its seed; float32 and float64, nominal and randomised robots."""
    n, seed = 4, 3
    kw = dict(episode_steps=5, robot_config=robot_config, dtype=dtype, distance_threshold=0.15,
              terminate_on_success=True)
    venv = TorchVectorEnv("diffkin/Reach-v0", n, **kw)
    singles = [gym.make("diffkin/Reach-v0", **kw) for _ in range(n)]
    obs_b, _ = venv.reset(seed=seed)
    for i, e in enumerate(singles):
        _assert_close(e.reset(seed=seed + i)[0], _obs_rows(obs_b, i))
    dt = venv.task.robot.config.control_dt
    rng = np.random.default_rng(1)
    prev, partial = obs_b["achieved_goal"].clone(), 0
    for _ in range(30):
        actions = rng.uniform(-1, 1, (n, 7)).astype(np.float32)
        obs_b, _, te, tr, info = venv.step(torch.as_tensor(actions))
        done = te | tr
        partial += int(bool(done.any()) and not bool(done.all()))
        last = info["final_obs"] if bool(done.any()) else obs_b  # the rows' last observations this step
        last = {k: torch.where(done[:, None], last[k], obs_b[k]) for k in obs_b}
        torch.testing.assert_close(last["observation"][:, 3:], (last["achieved_goal"] - prev) / dt,
                                   atol=5e-5, rtol=0)
        assert torch.equal(last["observation"][:, :3], last["achieved_goal"])
        assert torch.all(obs_b["observation"][done, 3:] == 0)  # a new episode starts at rest
        assert torch.equal(obs_b["observation"][:, :3], obs_b["achieved_goal"])
        prev = obs_b["achieved_goal"].clone()
        for i, env in enumerate(singles):
            o, _, t_i, r_i, _ = env.step(actions[i])
            if t_i or r_i:
                _assert_close(o, _obs_rows(info["final_obs"], i))
                o, _ = env.reset()
            _assert_close(o, _obs_rows(obs_b, i))
            assert venv.single_observation_space.contains(o)
    assert partial >= 2  # the case under test happened


def test_vector_env_metadata_and_spaces():
    venv = TorchVectorEnv("diffkin/Reach-v0", 8)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    obs, _ = venv.reset(seed=0)
    assert obs["observation"].shape == (8, 6) and obs["observation"].dtype == torch.float32
    assert venv.action_space.shape == (8, 7)
    assert venv.observation_space["desired_goal"].shape == (8, 3)
    _, r, te, tr, info = venv.step(torch.zeros(8, 7))
    assert r.shape == te.shape == tr.shape == info["is_success"].shape == (8,)


def test_vector_env_list_seeds_and_compute_reward():
    venv = TorchVectorEnv("diffkin/Reach-v0", 3)
    a, _ = venv.reset(seed=[5, 6, 7])
    b, _ = TorchVectorEnv("diffkin/Reach-v0", 3).reset(seed=5)
    assert torch.equal(a["desired_goal"], b["desired_goal"])
    r = venv.compute_reward(a["achieved_goal"], a["desired_goal"], None)
    assert r.shape == (3,)


@pytest.mark.parametrize("bad", [torch.zeros(4, 6), torch.zeros(7), torch.full((4, 7), float("nan"))])
def test_vector_bad_actions(bad):
    venv = TorchVectorEnv("diffkin/Reach-v0", 4)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="actions"):
        venv.step(bad)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    a = TorchVectorEnv("diffkin/Reach-v0", 16, device="cuda")
    b = TorchVectorEnv("diffkin/Reach-v0", 16)
    oa, _ = a.reset(seed=1)
    ob, _ = b.reset(seed=1)
    act = torch.rand(16, 7) * 2 - 1
    oa, *_ = a.step(act.cuda())
    ob, *_ = b.step(act)
    assert torch.allclose(oa["observation"].cpu(), ob["observation"], atol=1e-5)


def test_vector_env_settings_seeds_and_action_dtypes():
    from diffkin.errors import ConventionError, DiffkinError, DTypeError, ShapeError

    for n in (0, -2, 2.5, True):
        with pytest.raises(DiffkinError, match="num_envs"):
            TorchVectorEnv("diffkin/Reach-v0", n)
    with pytest.raises(ConventionError, match="unknown env id"):
        TorchVectorEnv("diffkin/Fly-v0", 2)
    venv = TorchVectorEnv("diffkin/Reach-v0", 3, robot="three_link_planar")
    with pytest.raises(ShapeError, match="3 seeds"):
        venv.reset(seed=[1, 2])
    with pytest.raises(DTypeError, match="seeds"):
        venv.reset(seed=[1, 2, 3.5])
    with pytest.raises(ConventionError, match="options"):
        venv.reset(seed=0, options={"goal": 1})
    obs_np = None
    for actions in (np.full((3, 3), 0.5), np.full((3, 3), 0.5, dtype=np.float32), torch.full((3, 3), 0.5),
                    torch.full((3, 3), 0.5, dtype=torch.float64), [[0.5] * 3] * 3):
        venv.reset(seed=4)
        obs = venv.step(actions)[0]["observation"]
        assert obs.dtype == torch.float32
        if obs_np is None:
            obs_np = obs
        assert torch.equal(obs, obs_np)
    for bad in (torch.ones(3, 3, dtype=torch.int64), torch.ones(3, 3).half(), np.ones((3, 3), dtype=bool)):
        with pytest.raises(DTypeError, match="actions"):
            venv.step(bad)
    with pytest.raises(ShapeError, match=r"\(3, 3\)"):
        venv.step(np.zeros((0, 3)))


def test_one_registry_serves_gymnasium_and_the_batched_env():
    assert set(ENV_IDS) | {"diffkin/Imitate-v0"} == set(ENVS) == set(REGISTERED)
    for env_id, spec in ((k, ENVS[k]) for k in ARM_IDS):
        assert gym.spec(env_id).entry_point == spec.entry_point == REGISTERED[env_id]
        env = gym.make(env_id, robot="three_link_planar")
        assert isinstance(env.unwrapped, spec.env)
        task = make_task(env_id, robot="three_link_planar")
        assert type(task) is spec.task and type(task.config) is spec.config
        assert type(env.unwrapped.task) is spec.task
    with pytest.raises(ValueError, match="unknown env id"):
        make_task("diffkin/Nope-v0")


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_domain_randomisation_batched_equals_single(env_id):
    """Per-env geometry in the batched env: different robots per env and per episode, env i equal to a
    single env seeded s + i (robots, observations), autoreset draws a new robot."""
    dr = dict(robot_config=dict(geometry_noise_length=0.02, geometry_noise_angle=0.04), episode_steps=3)
    venv = TorchVectorEnv(env_id, 4, **dr)
    obs, _ = venv.reset(seed=7)
    geo = venv.state["geometry"].clone()
    assert geo.shape == (4, 28) and len({tuple(r.tolist()) for r in geo}) == 4
    for i in range(4):
        single = gym.make(env_id, **dr).unwrapped
        sobs, _ = single.reset(seed=7 + i)
        assert torch.allclose(single._state["geometry"][0], geo[i])
        _assert_close(sobs, _obs_rows(obs, i))
    for _ in range(3):
        obs, *_ = venv.step(torch.zeros(4, venv.single_action_space.shape[0]))
    assert not torch.equal(venv.state["geometry"], geo)  # autoreset: new episodes, new robots
    nominal = TorchVectorEnv(env_id, 4, robot_config=dict(geometry_noise_angle=0.0), episode_steps=3)
    nominal.reset(seed=7)
    assert "geometry" not in nominal.state
