"""diffkin/Imitate-v0: check_env, the shipped reference clip against MuJoCo's FK, reward 1 on the reference
(actions read from the observation alone), episode over the clip, seeding, batched = single, errors."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import diffkin.envs  # noqa: F401
from diffkin.envs.imitate import ImitateEnv, default_clip, load_reference
from diffkin.envs.vector import TorchVectorEnv
from diffkin.errors import ConventionError, ModelError, ShapeError

ID = "diffkin/Imitate-v0"


@pytest.fixture(scope="module")
def env64():
    return gym.make(ID, dtype=torch.float64, random_start=0.0).unwrapped  # every episode: the whole clip


def test_check_env_and_shapes():
    env = gym.make(ID).unwrapped
    check_env(env, skip_render_check=True)
    nq, nv = env.robot.n, env.robot.nv
    assert (nq, nv) == (36, 35)  # the 29-DoF G1 on a free joint
    assert env.action_space.shape == (nv,) and env.observation_space.shape == (nq - 2 + 2 * nv + 1,)
    obs, _ = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape and obs.dtype == np.float32


def test_shipped_clip_keypoints_equal_mujoco_fk(env64):
    """The reference keypoints the reward uses are MuJoCo's body positions of the reference q."""
    mujoco = pytest.importorskip("mujoco")
    task = env64.task
    q, fps, names = load_reference(default_clip())
    assert q.shape[:2] == (1, 150) and fps == pytest.approx(60.0) and len(names) == 29
    from diffkin.models.mjcf import compile_mjcf  # MuJoCo's own compile, mesh files dropped (frames kept)

    m = compile_mjcf(task.robot.chain.source_path)[0]
    d = mujoco.MjData(m)
    for f in (0, 77, 149):
        d.qpos[:] = q[0, f]
        mujoco.mj_kinematics(m, d)
        want = np.stack([d.body(name).xpos for name in task.keypoint_frames])
        np.testing.assert_allclose(task.ref_keypoints[0, f].numpy(), want, atol=1e-9)


def test_reward_is_one_on_the_reference_from_the_observation_alone(env64):
    """Acting by the observation's first look-ahead (q_ref(f + skip) ⊖ q) / step_limit follows the reference
    exactly: reward 1 at every step, the episode runs to the clip's end (the root walking out of the
    chain's nominal ±1 m box for a free joint); standing still scores lower."""
    env, task = env64, env64.task
    nq, nv = env.robot.n, env.robot.nv
    assert np.abs(task.ref_q[0, :, :2].numpy()).max() > 1.0
    obs, _ = env.reset(seed=5)
    start = int(env._state["start"][0])
    assert start == 0 and np.allclose(env.q, task.ref_q[0, start].numpy())
    steps, rewards = 0, []
    while True:
        a = obs[nq - 2:nq - 2 + nv].astype(np.float64) / env.robot.step_limit
        assert np.abs(a).max() <= 1.0
        obs, r, term, trunc, info = env.step(a)
        steps += 1
        rewards.append(r)
        assert info["tracking_error"] < 1e-5 and info["joint_error"] < 1e-5 and not term
        if trunc:
            break
    assert steps == (149 - start) // task.config.frame_skip
    np.testing.assert_allclose(rewards, 1.0, atol=1e-8)
    env.reset(seed=5)
    _, r0, *_ = env.step(np.zeros(nv))
    assert r0 < 0.999  # the clip moves on without the robot


def test_seeds_determinism_and_batched_equals_single():
    kw = dict(episode_steps=4, init_noise=0.05)
    a, b = gym.make(ID, **kw).unwrapped, gym.make(ID, **kw).unwrapped
    oa, ob = a.reset(seed=3)[0], b.reset(seed=3)[0]
    np.testing.assert_array_equal(oa, ob)
    starts = {int(gym.make(ID).unwrapped.reset(seed=s)[0][-1] * 149) for s in range(6)}
    assert len(starts) > 1  # a random start frame
    n, seed = 3, 11
    venv = TorchVectorEnv(ID, n, **kw)
    singles = [gym.make(ID, **kw).unwrapped for _ in range(n)]
    obs_b, _ = venv.reset(seed=seed)
    obs_s = [e.reset(seed=seed + i)[0] for i, e in enumerate(singles)]
    rng = np.random.default_rng(0)
    for step in range(9):  # crosses two auto-resets (episode_steps=4)
        for i in range(n):
            np.testing.assert_allclose(obs_s[i], obs_b[i].numpy(), rtol=1e-5, atol=2e-6)
        act = rng.uniform(-1, 1, (n, 35)).astype(np.float32)
        obs_b, r_b, te_b, tr_b, _ = venv.step(torch.as_tensor(act))
        for i, e in enumerate(singles):
            o, r, te, tr, _ = e.step(act[i])
            assert r == pytest.approx(float(r_b[i]), rel=1e-5, abs=2e-6) and tr == bool(tr_b[i])
            obs_s[i] = e.reset()[0] if te or tr else o
        assert bool(tr_b.all()) == (step % 4 == 3)


def test_clip_from_a_result_or_npz_and_errors(tmp_path):
    from diffkin.retarget import RetargetResult

    q, fps, names = load_reference(None)
    res = RetargetResult(q=torch.from_numpy(q[:, :40]), contacts=torch.zeros(1, 40, 2, dtype=torch.bool),
                         metrics=None, scale=torch.ones(1), keypoints=None, keypoint_frames=[], fps=fps,
                         joint_names=names, scalar_columns=list(range(7, 36)))
    env = ImitateEnv(clip=res, random_start=0.0)
    assert env.task.frames == 40 and env.reset(seed=0)[0][-1] == 0.0
    path = res.save(tmp_path / "c.npz")
    env2 = ImitateEnv(clip=str(path), random_start=0.0)
    assert torch.equal(env2.task.ref_q, env.task.ref_q)
    # a chain as the robot: its end links are the keypoints (Unitree's G1 URDF, the clip's joint layout);
    # the same keypoints as Menagerie's MJCF the default loads
    from pathlib import Path

    from diffkin import models
    from diffkin.retarget import Mapping

    urdf = Path(__file__).parent / "data" / "urdf" / "g1_29dof_rev_1_0.urdf"
    g1 = models.from_urdf(urdf, Mapping.builtin("g1").frames, floating_base=True)
    env3 = ImitateEnv(robot=g1, clip=res)
    assert env3.task.keypoint_frames == env.task.keypoint_frames
    torch.testing.assert_close(env3.task.ref_keypoints, env.task.ref_keypoints, atol=1e-5, rtol=0)
    with pytest.raises(ConventionError, match="end links"):
        ImitateEnv(robot=g1, clip=res, keypoint_frames=("pelvis",))
    np.savez(tmp_path / "bad.npz", q=q)
    with pytest.raises(ModelError, match="fps"):
        ImitateEnv(clip=tmp_path / "bad.npz")
    np.savez(tmp_path / "short.npz", q=q[..., :-1], fps=np.array(fps), joint_names=np.array(names))
    with pytest.raises(ShapeError, match="nq"):
        ImitateEnv(clip=tmp_path / "short.npz")
    with pytest.raises(ConventionError, match="joint"):
        gym.make(ID, action_mode="cartesian")
    with pytest.raises(ConventionError, match="render"):
        gym.make(ID, render_mode="rgb_array")
    bad = np.array(q)
    bad[0, 3, 10] = np.nan
    np.savez(tmp_path / "nan.npz", q=bad, fps=np.array(fps), joint_names=np.array(names))
    with pytest.raises(ValueError, match="reference q"):
        ImitateEnv(clip=tmp_path / "nan.npz")
    with pytest.raises(ValueError, match="frame_skip"):
        gym.make(ID, frame_skip=0)
