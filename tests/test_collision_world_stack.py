"""World.stack: scenes of different sizes as one batched World; every row's distances are its own world's
(computed alone), the padding never collides, gradients pass."""

from __future__ import annotations

import pytest
import torch

import diffkin
from benchmarks import motion_problems as mp
from diffkin.collision import RobotCollision, World, box
from diffkin.collision.world_stack import PAD_DISTANCE, stacked_columns
from diffkin.errors import DiffkinError

F64 = torch.float64


@pytest.fixture(scope="module")
def setup():
    chain = diffkin.models.from_urdf(mp.PANDA_SPHERIZED_URDF, "panda_hand", dtype=F64)
    rc = RobotCollision.from_urdf(mp.PANDA_SPHERIZED_URDF, chain, mp.PANDA_SRDF)
    problems = mp.load_problems(families={"bookshelf_small", "table_pick"}, indices={1, 2})
    worlds = [p.scene.to_world(dtype=F64) for p in problems]
    worlds.append(World(spheres=[[0.4, 0.0, 0.5, 0.1]], points=[[0.3, 0.2, 0.6], [0.1, 0.1, 0.9]],
                        halfspaces=[[0.0, 0.0, 1.0, 0.0]], dtype=F64,
                        boxes=box([0.5, 0.3, 0.2], [0.1, 0.1, 0.1], dtype=F64)))
    worlds.append(World(dtype=F64))  # an empty scene
    q = torch.stack([torch.tensor(p.start, dtype=F64) for p in problems]
                    + [torch.tensor(problems[0].goal, dtype=F64), chain.q_limits.mean(-1)])
    return chain, rc, worlds, q


def test_stacked_world_rows_equal_each_world_alone(setup):
    chain, rc, worlds, q = setup
    w = World.stack(worlds)
    assert w.spheres.shape[0] == w.capsules.shape[0] == w.boxes.center.shape[0] == len(worlds)
    counts = torch.tensor([list(x.counts) for x in worlds])
    assert list(w.counts) == counts.amax(0).tolist()
    with torch.no_grad():
        d = rc.world_distances(q, w)  # (B, G, W_max)
        for b, world in enumerate(worlds):
            cols = stacked_columns(worlds, b)
            alone = rc.world_distances(q[b], world)
            torch.testing.assert_close(d[b][:, cols], alone, rtol=0, atol=1e-12)
            pad = torch.ones(d.shape[-1], dtype=torch.bool)
            pad[cols] = False
            assert (d[b][:, pad] > 0.5 * PAD_DISTANCE).all()
            torch.testing.assert_close(rc.min_distance(q[b:b + 1], World.stack([world])),
                                       rc.min_distance(q[b:b + 1], world), rtol=0, atol=1e-12)
    assert (d < 0).any()  # a real contact among the rows (the scenes touch the robot somewhere)


def test_stacked_world_gradients_equal_each_world_alone(setup):
    chain, rc, worlds, q = setup
    w = World.stack(worlds)
    qq = q.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(rc.min_distance(qq, w).sum(), qq)
    assert torch.isfinite(g).all()
    for b, world in enumerate(worlds):
        qb = q[b].clone().requires_grad_(True)
        (gb,) = torch.autograd.grad(rc.min_distance(qb, world), qb)
        torch.testing.assert_close(g[b], gb, rtol=0, atol=1e-10)


def test_stack_errors():
    a = World(spheres=[[0, 0, 0, 0.1]], dtype=F64)
    with pytest.raises(DiffkinError, match="float32"):
        World.stack([a, World(spheres=[[0, 0, 0, 0.1]], dtype=torch.float32)])
    with pytest.raises(DiffkinError, match="already batched"):
        World.stack([World.stack([a, a]), a])
    with pytest.raises(DiffkinError, match="non-empty"):
        World.stack([])
    with pytest.raises(DiffkinError, match="list of diffkin.collision.World"):
        World.stack(a)  # one world, not a list
