"""``diffkin/Reach-v0`` with ``self_collision=`` (issue 27, "where users see it"): the episode ends (or the
reward is penalised) when the arm folds onto itself; the distances checked against MuJoCo's own
``mj_geomDistance`` / ``mj_collision`` on the same URDF (an independent reference), never only against the
collision layer the env uses.
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import diffkin.envs  # noqa: F401
from diffkin import models
from diffkin.collision import RobotCollision
from diffkin.envs.vector import TorchVectorEnv
from diffkin.errors import ConventionError, DiffkinError, ModelError, ShapeError

mujoco = pytest.importorskip("mujoco")

FOLD = Path(__file__).parent / "data" / "envs" / "fold_arm.urdf"
FOLDING = np.array([0.0, 1.0, 1.0], np.float32)  # joints 2 and 3 bend: link3 swings back onto the base
START = dict(home=[0.0, 1.5, 0.5], init_noise=0.0, episode_steps=100)


def _arm(dtype=torch.float32):
    return models.from_urdf(FOLD, "tool", dtype=dtype)


class _MuJoCo:
    """The same URDF compiled by MuJoCo (static bodies kept): signed distances of the env's checked pairs."""

    def __init__(self, pairs_links):
        self.m = mujoco.MjModel.from_xml_path(str(FOLD))
        self.d = mujoco.MjData(self.m)
        geom = {self.m.body(self.m.geom(g).bodyid[0]).name: g for g in range(self.m.ngeom)}  # one per link
        self.pairs = [(geom[a], geom[b]) for a, b in pairs_links]

    def set(self, q):
        self.d.qpos[:] = np.asarray(q, dtype=np.float64)
        mujoco.mj_forward(self.m, self.d)

    def min_distance(self, q) -> float:
        self.set(q)
        return min(mujoco.mj_geomDistance(self.m, self.d, a, b, 10.0, None) for a, b in self.pairs)

    def contacts(self, q) -> set[frozenset[int]]:
        self.set(q)
        return {frozenset((int(c.geom1), int(c.geom2))) for c in self.d.contact[:self.d.ncon]}


def _links(collision: RobotCollision) -> list[tuple[str, str]]:
    link = {g.name: g.link for g in collision.geoms}
    return [(link[a], link[b]) for a, b in collision.pairs]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_terminates_on_self_collision_checked_by_mujoco(dtype):
    env = gym.make("diffkin/Reach-v0", robot=_arm(dtype), self_collision="terminate", dtype=dtype, **START)
    task = env.unwrapped.task
    assert task.collision.chain is env.unwrapped.robot.chain  # placed by the env's own chain
    assert sorted(_links(task.collision)) == [("base", "link2"), ("base", "link3"), ("link1", "link3")]
    ref = _MuJoCo(_links(task.collision))
    env.reset(seed=0)
    tol = 1e-5 if dtype == torch.float32 else 1e-9
    steps = 0
    for _ in range(30):
        _, r, terminated, truncated, info = env.step(FOLDING)
        steps += 1
        q = env.unwrapped._state["q"][0].double().numpy()
        d = ref.min_distance(q)
        assert info["min_distance"] == pytest.approx(d, abs=tol)
        assert info["in_collision"] == (d < 0.0) and terminated == (d < 0.0)
        if terminated:
            break
    assert terminated and steps > 3  # it started free and folded into a collision
    # MuJoCo's own collision pass sees the contact, between a pair the env checks
    assert ref.contacts(q) & {frozenset(p) for p in ref.pairs}


def test_penalize_keeps_the_episode_and_compute_reward_agrees():
    kw = dict(robot=_arm(), self_collision="penalize", collision_penalty=0.5, reward_type="dense", **START)
    env = gym.make("diffkin/Reach-v0", **kw).unwrapped
    plain = gym.make("diffkin/Reach-v0", **{**kw, "self_collision": None}).unwrapped
    ref = _MuJoCo(_links(env.task.collision))
    env.reset(seed=1)
    plain.reset(seed=1)
    hits = 0
    for _ in range(25):
        obs, r, terminated, _, info = env.step(FOLDING)
        _, r0, _, _, info0 = plain.step(FOLDING)
        assert "min_distance" not in info0  # not checked unless asked
        hit = ref.min_distance(env._state["q"][0].double().numpy()) < 0.0
        assert not terminated and info["in_collision"] == hit
        assert r == pytest.approx(r0 - 0.5 * hit, abs=1e-6)
        assert float(env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)) == pytest.approx(r)
        hits += hit
    assert 0 < hits < 25
    # HER's form: arrays of goals and a sequence of infos
    infos = np.array([{"in_collision": True}, {"in_collision": False}], dtype=object)
    g = np.zeros((2, 3), np.float32)
    np.testing.assert_allclose(env.compute_reward(g, g + 1, infos), -np.sqrt(3) - np.array([0.5, 0.0]),
                               rtol=1e-6)
    with pytest.raises(ConventionError, match="in_collision"):
        env.compute_reward(g, g, [{}, {}])


def test_given_collision_model_and_vector_env():
    chain = _arm(torch.float64)
    collision = RobotCollision.from_urdf(FOLD, chain)
    vec = TorchVectorEnv("diffkin/Reach-v0", 4, robot=chain, collision=collision, self_collision="terminate",
                         **START)
    assert vec.task.collision.chain is vec.task.robot.chain and vec.task.collision is not collision
    assert vec.task.collision.capsule_radius.dtype == torch.float32  # on the env's dtype
    vec.reset(seed=3)
    ref = _MuJoCo(_links(collision))
    for _ in range(10):
        _, _, terminated, _, info = vec.step(torch.tensor(FOLDING).expand(4, 3))
        assert info["min_distance"].shape == (4,)
        if bool(terminated.any()):
            break
        for i in range(4):  # not reset yet: the state is the step's
            assert float(info["min_distance"][i]) == pytest.approx(
                ref.min_distance(vec.state["q"][i].double().numpy()), abs=1e-5)
    assert bool(terminated.all())  # the same start and actions in every env
    final = info["final_info"]
    assert bool((final["min_distance"] < 0).all()) and bool(final["in_collision"].all())


def test_collision_option_errors():
    with pytest.raises(ModelError, match="collision geometry.*panda"):
        gym.make("diffkin/Reach-v0", robot="panda", self_collision="terminate")
    with pytest.raises(ConventionError, match="self_collision"):
        gym.make("diffkin/Reach-v0", self_collision="stop")
    with pytest.raises(DiffkinError, match="collision_penalty"):
        gym.make("diffkin/Reach-v0", self_collision="penalize", collision_penalty=-1.0)
    with pytest.raises(ModelError, match="RobotCollision"):
        gym.make("diffkin/Reach-v0", robot=_arm(), collision="yes")
    other = RobotCollision.from_urdf(FOLD, models.from_urdf(FOLD, "link2"))
    with pytest.raises(ShapeError, match="nq 2"):
        gym.make("diffkin/Reach-v0", robot=_arm(), collision=other, self_collision="terminate")


def test_an_mjcf_robot_builds_its_collision_model_from_its_own_file():
    """An MJCF robot with self_collision: the geoms are placed by the chain's q (every body through
    models.mjcf_bodies), and the env's min distance is MuJoCo's own mj_geomDistance over the same pairs."""
    path = Path(__file__).parent / "data" / "mjcf_extra" / "joint_kinds.xml"  # primitive geoms only
    arm = models.from_mjcf(path, "palm", root_link="torso", dtype=torch.float64)
    vec = TorchVectorEnv("diffkin/Reach-v0", 3, robot=arm, self_collision="penalize", init_noise=0.5)
    vec.reset(seed=3)
    _, _, _, _, info = vec.step(torch.zeros(vec.action_space.shape))
    from diffkin.models.mjcf import compile_mjcf

    m = compile_mjcf(path)[0]
    d = mujoco.MjData(m)
    col = vec.task.collision
    names = [g.name for g in col.geoms]
    ids = {n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in names}
    assert col.pairs and all(i >= 0 or "/" in n for n, i in ids.items())
    for i in range(3):  # every env's state, its distances by MuJoCo
        d.qpos[:] = arm.to_qpos(vec.state["q"][i].double()).numpy()
        mujoco.mj_kinematics(m, d)
        ref = min(mujoco.mj_geomDistance(m, d, _geom_id(m, a), _geom_id(m, b), 10.0, None)
                  for a, b in col.pairs)
        assert float(info["min_distance"][i]) == pytest.approx(ref, abs=1e-5)
    assert not info["min_distance"].requires_grad  # no autograd graph built in a step


def _geom_id(m, name: str) -> int:
    """MuJoCo's id of a geom by the collision layer's name (MJCF name, or "<body>/<i>" when unnamed)."""
    g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)
    if g >= 0:
        return g
    body, i = name.rsplit("/", 1)
    return int(m.body(body).geomadr[0]) + int(i)


def test_a_given_mjcf_collision_model_follows_the_env_dtype():
    """A float64 MJCF RobotCollision given to a float32 env: the env's copy converts its geometry and the
    chain its body poses read (the model holds its chain by reference, so to() alone would not), and the
    user's chain and model are left as they were."""
    path = Path(__file__).parent / "data" / "mjcf_extra" / "joint_kinds.xml"
    arm = models.from_mjcf(path, "palm", root_link="torso", dtype=torch.float64)
    given = RobotCollision.from_mjcf(path, arm)
    vec = TorchVectorEnv("diffkin/Reach-v0", 2, robot=arm, collision=given, self_collision="penalize",
                         init_noise=0.5)
    vec.reset(seed=1)
    _, _, _, _, info = vec.step(torch.zeros(vec.action_space.shape))
    assert vec.task.collision.capsule_radius.dtype == torch.float32
    assert torch.isfinite(info["min_distance"]).all()
    q = vec.state["q"].double()
    torch.testing.assert_close(info["min_distance"].double(), given.min_distance(q).detach(), atol=1e-5,
                               rtol=0)
    assert arm.dtype == torch.float64 and given.capsule_radius.dtype == torch.float64
