"""Operational-space trajectory -> joint trajectory: the FK of the result follows the poses."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from diffkin import models
from diffkin.errors import ConventionError, OptionError, ShapeError
from diffkin.ik.along_path import finite_difference_twists, joint_trajectory_from_poses, refine_path
from diffkin.trajectories import Trajectory, cartesian_trajectory, circle_path

F64 = torch.float64


@pytest.fixture(scope="module")
def arm():
    return models.load("anthropomorphic_wrist", dtype=F64)


@pytest.fixture(scope="module")
def path(arm):
    """A batch of 3 smooth joint motions (cubic blend, 31 samples) and their poses (3, 31, 4, 4)."""
    g = torch.Generator().manual_seed(0)
    qa = torch.tensor([0.3, 0.5, 0.2, 0.4, 0.9, -0.2], dtype=F64) + 0.2 * torch.rand(
        3, 6, generator=g, dtype=F64
    )
    qb = qa + 0.4 * (torch.rand(3, 6, generator=g, dtype=F64) - 0.5)
    s = torch.linspace(0, 1, 31, dtype=F64)[:, None]
    q = qa[:, None] + (qb - qa)[:, None] * (3 * s**2 - 2 * s**3)
    with torch.no_grad():
        return q, arm.forward_kinematics(q)


def test_clik_follows_poses(arm, path):
    q_true, T = path
    res = joint_trajectory_from_poses(arm, T, q_true[:, 0], method="clik", dt=0.02, substeps=4)
    assert res.q.shape == (3, 31, 6) and res.position_error.shape == (3, 31) and res.success.shape == (3, 31)
    assert res.position_error.max() < 1e-4 and res.orientation_error.max() < 1e-3 and res.success.all()
    # independent check of the orientation error with scipy
    R = arm.forward_kinematics(res.q)[..., :3, :3].reshape(-1, 3, 3).detach().numpy()
    Rd = T[..., :3, :3].reshape(-1, 3, 3).numpy()
    angles = (Rotation.from_matrix(Rd) * Rotation.from_matrix(R).inv()).magnitude()
    assert angles.max() < 1e-3
    assert torch.allclose(res.q, q_true, atol=1e-3)  # a non-redundant arm: the same branch as the path
    # more substeps, smaller error (linearisation error of each Euler step)
    coarse = joint_trajectory_from_poses(arm, T, q_true[:, 0], method="clik", dt=0.02)
    assert coarse.position_error.max() > 3 * res.position_error.max()


def test_solve_warm_started_follows_poses(arm, path):
    q_true, T = path
    res = joint_trajectory_from_poses(arm, T[:, ::3], q_true[:, 0], method="solve")
    assert res.q.shape == (3, 11, 6)
    assert res.success.all() and res.position_error.max() < 1e-4 and res.orientation_error.max() < 1e-3
    assert (res.q[:, 1:] - res.q[:, :-1]).abs().max() < 0.3  # warm start keeps one branch: no jumps


def test_positions_with_given_velocities(arm):
    """A circle (4.38) with a cubic timing law, position only, feedforward of the path's own velocity."""
    t = torch.linspace(0, 1, 101, dtype=F64)
    s_f = 2 * math.pi * 0.1
    timing = Trajectory(s_f * (3 * t**2 - 2 * t**3), s_f * (6 * t - 6 * t**2), s_f * (6 - 12 * t))
    q0 = torch.tensor([0.3, 0.5, 0.2, 0.4, 0.9, -0.2], dtype=F64)
    p0 = arm.forward_kinematics(q0)[:3, 3].detach()
    centre = p0 + torch.tensor([0.0, 0.1, 0.0], dtype=F64)
    axis = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    p, v, _ = cartesian_trajectory(lambda s: circle_path(centre, axis, p0, s), timing)
    res = joint_trajectory_from_poses(arm, p, q0, dt=0.01, velocities=v, substeps=2)
    assert res.q.shape == (101, 6) and res.position_error.max() < 1e-4 and res.success.all()
    assert (res.orientation_error == 0).all()


def test_refine_and_finite_differences(path):
    _, T = path
    fine = refine_path(T, 5)
    assert fine.shape == (3, 151, 4, 4)
    assert torch.allclose(fine[:, ::5], T, atol=1e-12)
    R = fine[..., :3, :3]
    assert torch.allclose(R.mT @ R, torch.eye(3, dtype=F64).expand_as(R), atol=1e-12)
    assert refine_path(T, 1) is T
    dt = 0.1
    v = finite_difference_twists(T, dt)
    assert v.shape == (3, 31, 6) and (v[:, -1] == 0).all()
    # one step with the constant twist lands on the next sample: R_{k+1} = exp(S(ω) Δt) R_k (scipy)
    w = v[:, :-1, 3:].reshape(-1, 3).numpy() * dt
    R_next = Rotation.from_rotvec(w).as_matrix() @ T[:, :-1, :3, :3].reshape(-1, 3, 3).numpy()
    assert abs(R_next - T[:, 1:, :3, :3].reshape(-1, 3, 3).numpy()).max() < 1e-12
    assert torch.allclose(T[:, :-1, :3, 3] + v[:, :-1, :3] * dt, T[:, 1:, :3, 3], atol=1e-12)
    pos = refine_path(T[..., :3, 3], 3)
    assert pos.shape == (3, 91, 3) and torch.allclose(pos[:, ::3], T[..., :3, 3])


def test_bad_input(arm, path):
    q_true, T = path
    with pytest.raises(ShapeError):
        joint_trajectory_from_poses(arm, T[..., :3, :], q_true[:, 0])
    with pytest.raises(ConventionError):
        joint_trajectory_from_poses(arm, T, q_true[:, 0], method="newton")
    with pytest.raises(ShapeError):
        joint_trajectory_from_poses(arm, T, q_true[:, 0], velocities=torch.zeros(3, 31, 3, dtype=F64))
    with pytest.raises(OptionError, match="substeps"):  # a numeric option: the one validator's error
        joint_trajectory_from_poses(arm, T, q_true[:, 0], substeps=0)
