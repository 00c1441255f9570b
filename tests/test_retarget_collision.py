"""Self-collision in the whole-clip retargeting (issue 37): the G1's collision model (Menagerie's MJX G1 and
its scene's self pairs) against MuJoCo's ``mj_geomDistance``, the rows' Jacobian against finite
differences, and a clip whose hands sink into the chest: penetrating without ``collision``, clear with it
(checked by MuJoCo on the output, every one of the 26 pairs)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from diffkin import models, retarget
from diffkin.errors import ModelError
from diffkin.retarget.self_collision import G1_MJX_SCENE, SelfCollisionRows

mujoco = pytest.importorskip("mujoco")

F64 = torch.float64


@pytest.fixture(scope="module")
def g1():
    mp = retarget.Mapping.builtin("g1")
    chain = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=F64).requires_grad_(False)
    return mp, chain, retarget.g1_collision(chain)


def _scene():
    """Menagerie's MJX scene compiled by MuJoCo (the visual meshes are not shipped: dropped)."""
    from diffkin.collision.mjcf import load_model

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_model(G1_MJX_SCENE)


def _mujoco_distances(model, rc, q: np.ndarray) -> np.ndarray:
    """mj_geomDistance of every pair of ``rc`` at the qpos rows ``q (N, nq)``: ``(N, P)``."""
    gid = [(model.geom(a).id, model.geom(b).id) for a, b in rc.pairs]
    data = mujoco.MjData(model)
    out = np.empty((len(q), len(gid)))
    for n, row in enumerate(q):
        data.qpos[:] = row
        mujoco.mj_kinematics(model, data)
        for p, (i, j) in enumerate(gid):
            out[n, p] = mujoco.mj_geomDistance(model, data, i, j, 10.0, None)
    return out


def _sinking_hands(frames: int = 24):
    """The shipped walk's first frames with both human wrists moved, linearly over the clip, onto the chest
    joint: the robot's hands end inside its torso."""
    walk = retarget.load_bvh(retarget.example_clips()["walk"]).frames_slice(0, frames)
    P, n = walk.positions.clone(), walk.names
    a = torch.linspace(0, 1, frames, dtype=P.dtype)[:, None]
    for side in ("Left", "Right"):
        k = n.index(side + "Wrist")
        P[:, :, k] = (1 - a) * P[:, :, k] + a * P[:, :, n.index("Chest")]
    return retarget.Motion(P, n, walk.fps)


def test_g1_collision_is_the_mjx_scene_and_equals_mj_geom_distance(g1):
    """26 self pairs of the scene (the floor pairs are not robot pairs), each distance equal to MuJoCo's
    mj_geomDistance on clear configurations near the standing pose (capsules, spheres, the foot boxes)."""
    _, chain, rc = g1
    model = _scene()
    assert len(rc.pairs) == 26 and ("torso_collision", "left_hand_collision") in rc.pairs
    assert model.nq == chain.nq
    gen = torch.Generator().manual_seed(3)
    q = chain.random_configuration((40,), generator=gen)
    q[:, 7:] *= 0.3  # near the zero posture: mostly clear (MuJoCo's box depths are not signed distances)
    q[:, :7] = torch.tensor([0, 0, 0.8, 1, 0, 0, 0], dtype=F64)
    ours = rc.self_distances(q).numpy()
    theirs = _mujoco_distances(model, rc, q.numpy())
    clear = theirs > 0
    assert clear.mean() > 0.9
    np.testing.assert_allclose(ours[clear], theirs[clear], atol=1e-7, rtol=0)


def test_collision_rows_jacobian_against_finite_differences(g1):
    """The rows' Jacobian w.r.t. the step δ (q ⊕ δ) equals central differences of the distances."""
    _, chain, rc = g1
    q = chain.random_configuration((1, 2), generator=torch.Generator().manual_seed(1))
    rows = SelfCollisionRows(rc, chain, q, margin=10.0, screen=0.0)  # every pair active
    assert rows.count == 26
    r, J = rows.rows(q, 1.0)
    torch.testing.assert_close(r, rows.distances(q) - 10.0)
    eps = 1e-6
    space = chain.configuration_space
    d = lambda v: rows.distances(space.integrate(q, v))  # noqa: E731
    fd = torch.stack([(d(eps * e) - d(-eps * e)) / (2 * eps) for e in torch.eye(chain.nv, dtype=F64)], -1)
    torch.testing.assert_close(J, fd, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_collision_rows_jacobian_from_the_bodies_equals_autograd(g1, dtype):
    """The rows' Jacobian from the bodies' geometric Jacobians (each pair's wrench, module
    ``self_collision``) equals the autograd one through all frames' FK: every pair kind of the G1 (capsules,
    spheres, the foot boxes) on random and near-standing configurations, float64 and float32."""
    mp, chain, rc = g1
    if dtype != F64:
        chain = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=dtype).requires_grad_(False)
        rc = retarget.g1_collision(chain)
    q = chain.random_configuration((2, 6), generator=torch.Generator().manual_seed(5))
    q[1, :, 7:] *= 0.3  # some pairs near contact
    rows = SelfCollisionRows(rc, chain, q, margin=10.0, screen=0.0)
    assert rows.count == 26 and rows._bodies is not None
    d, J = rows.jacobian(q.reshape(-1, chain.nq))
    d_ag, J_ag = rows.jacobian(q.reshape(-1, chain.nq), autograd=True)
    tol = 1e-12 if dtype == F64 else 2e-5
    torch.testing.assert_close(d, d_ag, atol=tol, rtol=0)
    torch.testing.assert_close(J, J_ag, atol=tol * 10, rtol=0)
    assert J.abs().amax() > 0.1 and J.dtype == dtype
    # through the broad phase (the rows' call): exact below the threshold, a bound at or above it elsewhere
    t = float(d.median())
    d_b, J_b = rows.jacobian(q.reshape(-1, chain.nq), below=t)
    near = d < t
    assert near.any() and (~near).any()
    torch.testing.assert_close(d_b[near], d[near], atol=tol, rtol=0)
    torch.testing.assert_close(J_b[near], J[near], atol=tol * 10, rtol=0)
    assert bool((d_b[~near] >= t - tol).all()) and bool(torch.isfinite(J_b).all())


def test_whole_clip_keeps_the_hands_out_of_the_torso(g1):
    """Hands sinking into the chest: without ``collision`` MuJoCo finds penetrating pairs in many frames;
    with it none of the 26 pairs penetrates in any frame, the screen kept only some pairs, and the other
    metrics stay within their bounds."""
    mp, chain, rc = g1
    motion = _sinking_hands()
    model = _scene()
    free = retarget.clip(chain, motion, mp, warm_start="batched", iterations=8)
    kept = retarget.clip(chain, motion, mp, collision=rc, warm_start="batched", iterations=8)
    d_free = _mujoco_distances(model, rc, free.q[0].numpy())
    d_kept = _mujoco_distances(model, rc, kept.q[0].numpy())
    assert (d_free.min(-1) < -0.01).sum() >= 8  # centimetres deep, in a third of the frames
    assert d_kept.min() >= 0.0
    np.testing.assert_allclose(rc.self_distances(kept.q[0]).numpy(), d_kept, atol=1e-7, rtol=0)
    screened = SelfCollisionRows(rc, chain, free.q, 0.01, 0.1)  # the screen on a clip without the rows
    assert 0 < screened.count < 26
    m = kept.metrics
    assert int(m.joint_limit_violations) == 0 and m.ground_penetration.item() <= 1e-9
    assert m.foot_skating.item() < 5.0 and m.keypoint_error.item() < 100.0


def test_collision_in_float32_and_argument_errors(g1):
    mp, chain, rc = g1
    motion = _sinking_hands(4)
    # 8 frames: the steps push the right hand out of the chest onto the right hip, a pair the screen of the
    # warm start leaves out (18 cm apart there): the second screen adds it and another round clears it
    c32 = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=torch.float32)
    rc32 = retarget.g1_collision(c32)
    warm = retarget.clip(c32, _sinking_hands(8), mp, whole_clip=False, warm_start="batched")
    assert ("right_hip_collision", "right_hand_collision") not in SelfCollisionRows(rc32, c32, warm.q, 0.01,
                                                                                     0.1).pairs
    r32 = retarget.clip(c32, _sinking_hands(8), mp, collision=rc32, iterations=6, warm_start="batched")
    assert r32.q.dtype == torch.float32 and bool(torch.isfinite(r32.q).all())
    assert float(rc.self_distances(r32.q[0].double()).min()) > -1e-4
    assert r32.cost.shape[0] > 7  # more than one round of 6 iterations
    with pytest.raises(ModelError, match="RobotCollision"):
        retarget.clip(chain, motion, mp, collision="torso", iterations=1)
    other = models.from_mjcf(models.model_path("g1"), mp.frames, dtype=F64)
    with pytest.raises(ModelError, match="collision model was built for"):
        retarget.clip(other, motion, mp, collision=rc, iterations=1)
    h1 = models.from_mjcf(models.model_path("h1"), ["left_ankle_link", "right_ankle_link"], dtype=F64)
    with pytest.raises(ModelError, match="29-DoF G1"):
        retarget.g1_collision(h1)


def test_rows_with_no_pair_kept_are_empty(g1):
    """A screen that keeps no pair (every pair far beyond the margin) gives empty rows and Jacobians, not an
    error (the Jacobian's wrench tables exist only once a pair is kept)."""
    _, chain, rc = g1
    q = chain.random_configuration((1, 3), generator=torch.Generator().manual_seed(2))
    rows = SelfCollisionRows(rc, chain, q, margin=-10.0, screen=0.0)
    assert rows.count == 0
    d, J = rows.jacobian(q.reshape(-1, chain.nq))
    assert d.shape == (3, 0) and J.shape == (3, 0, chain.nv)
    r, Jr = rows.rows(q, 1.0)
    assert r.shape == (1, 3, 0) and Jr.shape == (1, 3, 0, chain.nv)
