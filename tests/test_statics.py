"""Statics (§3.8): diffkin.statics (re-exported by diffkin.jacobian).

References: kineto-statics duality (power τᵀq̇ = γᵀv), the Jacobian of an offset frame computed by
diffkin.jacobian (3.112)–(3.113), and Example 3.5 (3.121).
"""

from __future__ import annotations

import torch

from diffkin.jacobian import geometric_jacobian
from diffkin.rotations import rotvec_to_matrix
from diffkin.statics import (
    closed_chain_torques,
    joint_torques_from_wrench,
    transform_velocity,
    transform_wrench,
    velocity_transform,
    wrench_transform,
)
from tests.helpers import random_chain

F64 = torch.float64


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def test_joint_torques_duality():  # (3.111): τ = Jᵀγ, and the power balance τᵀq̇ = γᵀv
    chain = random_chain(0, "standard")
    q = chain.random_configuration((4,), generator=_gen(0))
    J = geometric_jacobian(chain, q).detach()
    gamma = torch.randn(4, 6, dtype=F64, generator=_gen(1))
    qd = torch.randn(4, 6, dtype=F64, generator=_gen(2))
    tau = joint_torques_from_wrench(J, gamma)
    torch.testing.assert_close(tau, (J.mT @ gamma.unsqueeze(-1)).squeeze(-1))
    v = (J @ qd.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close((tau * qd).sum(-1), (gamma * v).sum(-1))


def test_velocity_transform_matches_the_jacobian_of_an_offset_frame():  # (3.113)
    chain = random_chain(1, "modified")
    q = chain.random_configuration((3,), generator=_gen(3))
    qd = torch.randn(3, 6, dtype=F64, generator=_gen(4))
    R12 = rotvec_to_matrix(torch.tensor([0.4, -0.3, 0.8], dtype=F64))  # frame 2 on the EE body (frame 1)
    r12 = torch.tensor([0.1, 0.25, -0.2], dtype=F64)
    R_e = chain.forward_kinematics(q)[..., :3, :3].detach()
    v1 = (geometric_jacobian(chain, q, frame="ee") @ qd.unsqueeze(-1)).squeeze(-1).detach()
    J2 = geometric_jacobian(chain, q, point=r12, frame=R_e @ R12).detach()  # frame 2's own Jacobian
    v2 = (J2 @ qd.unsqueeze(-1)).squeeze(-1)
    M = velocity_transform(R12, r12)
    torch.testing.assert_close((M @ v1.unsqueeze(-1)).squeeze(-1), v2)
    torch.testing.assert_close(transform_velocity(R12, r12, v1), v2)
    T12 = torch.eye(4, dtype=F64)
    T12[:3, :3], T12[:3, 3] = R12, r12
    torch.testing.assert_close(velocity_transform(T12), M)


def test_wrench_transform_is_the_dual():  # (3.115)–(3.116)
    R = rotvec_to_matrix(torch.randn(5, 3, dtype=F64, generator=_gen(5)))
    r = torch.randn(5, 3, dtype=F64, generator=_gen(6))
    W = wrench_transform(R, r)
    torch.testing.assert_close(W, velocity_transform(R, r).mT)
    gamma2 = torch.randn(5, 6, dtype=F64, generator=_gen(7))
    gamma1 = transform_wrench(R, r, gamma2)
    torch.testing.assert_close(gamma1, (W @ gamma2.unsqueeze(-1)).squeeze(-1))
    v1 = torch.randn(5, 6, dtype=F64, generator=_gen(8))
    v2 = transform_velocity(R, r, v1)
    torch.testing.assert_close((gamma1 * v1).sum(-1), (gamma2 * v2).sum(-1))  # same power in both frames
    # a pure force at frame 2 gives the moment r × f at frame 1
    f = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=F64)
    out = transform_wrench(torch.eye(3, dtype=F64), torch.tensor([1.0, 0.0, 0.0], dtype=F64), f)
    torch.testing.assert_close(out, torch.tensor([0.0, 0.0, 1.0, 0.0, -1.0, 0.0], dtype=F64))


def test_closed_chain_torques_example_3_5():  # (3.121)
    upsilon = torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 1.0], [1.0, -1.0]], dtype=F64)
    tau_o = torch.tensor([0.3, -0.2, 0.7, 1.1], dtype=F64)  # τ1', τ1'', τ2', τ3'
    t1, t1b, t2, t3 = tau_o.tolist()
    expected = torch.tensor([t1 - t2 + t3, t1b + t2 - t3], dtype=F64)
    torch.testing.assert_close(closed_chain_torques(upsilon, tau_o), expected)
