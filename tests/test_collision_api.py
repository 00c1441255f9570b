"""The collision API's boundary: the collision model must belong to the chain it is used with, it holds the
chain by reference (its parameters and conversions are the geometry's only), input checks of ``World``,
``from_urdf`` and the exported distance functions, q-independent geoms in IK and sampling, and the
collision-free sampler's early stop."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import torch

import diffkin
import diffkin.sampling
from diffkin import ik, models
from diffkin.collision import RobotCollision
from diffkin.errors import DTypeError, ModelError

DATA = Path(__file__).parent / "data"
FR3 = DATA / "urdf" / "fr3.urdf"
F64 = torch.float64
SRDF = '<robot><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" reason="Default"/></robot>'


def _fr3(dtype=F64):
    chain = models.from_urdf(FR3, "fr3_link8", dtype=dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's meshes are not shipped
        return chain, RobotCollision.from_urdf(FR3, chain, srdf=SRDF)


def _targets(chain, n=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return chain.forward_kinematics(chain.random_configuration((n,), generator=g)).detach()


# ------------------------------------------------------------------ 1. the collision model's chain
def test_a_collision_model_of_another_chain_is_refused():
    chain, rc = _fr3()
    panda = models.load("panda").double()  # the Panda's DH chain: another chain of 7 joints
    T = _targets(panda)
    with pytest.raises(ModelError, match=r"built for URDFChain.*fr3_joint1.*chain given is DHChain"):
        ik.solve(panda, T, collision=rc)
    with pytest.raises(ModelError, match="random_configuration"):
        diffkin.sampling.random_configuration(panda, (3,), collision=rc)
    with pytest.raises(ModelError, match="ik"):
        ik.optimize(panda, T, torch.zeros(4, 7, dtype=F64), collision=rc, max_iterations=2)
    with pytest.raises(ModelError, match="CollisionCost"):
        ik.optimize(panda, T, torch.zeros(4, 7, dtype=F64), max_iterations=2,
                    costs=[ik.CollisionCost(collision=rc)])
    # another copy of the same robot is another chain too (its parameters may differ): rebind to use it
    twin = models.from_urdf(FR3, "fr3_link8", dtype=F64)
    with pytest.raises(ModelError, match="rebind"):
        ik.solve(twin, _targets(twin), collision=rc)
    rc.chain = twin
    assert rc.chain is twin and "chain" not in dict(rc.named_children())
    res = ik.solve(twin, _targets(twin), collision=rc, seed=0)
    assert res.success.any()


def test_the_chain_is_held_by_reference():
    chain, rc = _fr3(torch.float32)
    names = {n for n, _ in rc.named_parameters()}
    assert names == {"capsule_a", "capsule_b", "capsule_radius", "box_center", "box_rpy", "box_half_extents"}
    assert not any(p is c for p in rc.parameters() for c in chain.parameters())
    rc.double()
    assert chain.dtype == torch.float32 and rc.capsule_radius.dtype == F64  # the user's chain untouched
    q = torch.zeros(7)
    with pytest.raises(DTypeError, match=r"geometry is torch.float64, the chain is torch.float32"):
        rc.self_distances(q)
    chain.double()
    d = rc.self_distances(q.double())
    assert d.dtype == F64
    # an optimiser over rc.parameters() moves the geometry, never the robot
    before = [p.detach().clone() for p in chain.parameters()]
    opt = torch.optim.SGD(rc.parameters(), lr=0.1)
    (-rc.min_distance(torch.rand(5, 7, dtype=F64))).sum().backward()
    opt.step()
    assert all(torch.equal(a, b) for a, b in zip(before, chain.parameters()))
