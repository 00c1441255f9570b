"""The stable-baselines3 adapter (diffkin.training.sb3): a VecEnv over the batched env, seeded like it."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from stable_baselines3.common.vec_env import VecEnv  # noqa: E402

from diffkin.envs.vector import TorchVectorEnv  # noqa: E402
from diffkin.training.sb3 import SB3VecEnv, make_sb3_vec_env  # noqa: E402

ENV_IDS = ["diffkin/Reach-v0", "diffkin/Track-v0"]


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_sb3_adapter(env_id):
    venv = make_sb3_vec_env(env_id, 3, robot="three_link_planar", episode_steps=4)
    assert isinstance(venv, VecEnv) and isinstance(venv, SB3VecEnv)
    venv.seed(11)
    obs = venv.reset()
    ref = TorchVectorEnv(env_id, 3, robot="three_link_planar", episode_steps=4).reset(seed=11)[0]
    if isinstance(obs, dict):
        assert set(obs) == {"observation", "achieved_goal", "desired_goal"}
        np.testing.assert_array_equal(obs["desired_goal"], ref["desired_goal"].numpy())
    else:
        np.testing.assert_array_equal(obs, ref.numpy())
    for _ in range(4):
        obs, rew, done, infos = venv.step(np.zeros((3, *venv.action_space.shape), dtype=np.float32))
        assert rew.shape == (3,) and rew.dtype == np.float32 and done.dtype == bool and len(infos) == 3
    assert done.all()
    assert all("terminal_observation" in i and i["TimeLimit.truncated"] for i in infos)
    if env_id == "diffkin/Reach-v0":
        args = (obs["achieved_goal"], obs["desired_goal"], infos)
        r = venv.env_method("compute_reward", *args, indices=[0])[0]
        assert r.shape == (3,)


def test_seed_argument_seeds_the_first_reset():
    a = make_sb3_vec_env("diffkin/Reach-v0", 2, seed=5, robot="three_link_planar").reset()
    b = TorchVectorEnv("diffkin/Reach-v0", 2, robot="three_link_planar").reset(seed=5)[0]
    np.testing.assert_array_equal(a["desired_goal"], b["desired_goal"].numpy())


def test_signature_names_the_arguments():
    """help() shows the arguments (not only **kwargs), and the name is not SB3's own make_vec_env."""
    params = inspect.signature(make_sb3_vec_env).parameters
    assert {"env_id", "num_envs", "device", "seed", "robot", "action_mode", "robot_config"} <= set(params)
    doc = inspect.getdoc(make_sb3_vec_env)
    for name in ("reward_type", "distance_threshold", "episode_steps", "MultiInputPolicy", "n_steps"):
        assert name in doc, name
    with pytest.raises(TypeError, match="rewrd_type"):
        make_sb3_vec_env("diffkin/Reach-v0", 2, rewrd_type="dense")
