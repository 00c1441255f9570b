"""The PyRoKi peer of benchmarks/bench_collision_ik.py: its re-check and, when pyroki imports, its wiring.

PyRoKi is not on PyPI (docs/collision.md has the recipe), so the tests that need it skip without it; none
solves IK (the benchmark does that), they check what the comparison rests on: the same end frame as
diffkin's FK, the obstacle cover containing the box, and the independent re-check of answers.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks import peers_pyroki
from benchmarks.bench_collision_ik import recheck, robot, targets, world

needs_pyroki = pytest.mark.skipif(peers_pyroki.available() is not None, reason="pyroki does not import")


def test_recheck_accepts_the_targets_own_configurations_and_rejects_a_1_mrad_miss():
    chain, rc = robot(torch.float64)
    q, T = targets(chain, rc, world("mixed", torch.float64), 40, clear=0.01)
    got = recheck(q, T)
    assert got["success"] == 1.0 and got["collision_free"] == 1.0
    miss = q.clone()
    miss[:, 6] += 2e-3  # the last joint turns the flange about its own axis: 2 mrad, 0 mm
    assert recheck(miss, T)["success"] == 0.0
    assert recheck(torch.full_like(q, float("nan")), T)["success"] == 0.0


@needs_pyroki
def test_pyroki_end_frame_is_diffkins_fr3_link8():
    import jax
    import jax.numpy as jnp
    import jaxlie

    pk_robot, _, _, link = peers_pyroki.problem("mixed")
    chain, _ = robot(torch.float64)
    q = chain.random_configuration((64,), generator=torch.Generator().manual_seed(3))
    T = jax.vmap(pk_robot.forward_kinematics)(jnp.asarray(q.numpy(), jnp.float32))[:, int(link)]
    got = np.asarray(jaxlie.SE3(T).as_matrix(), dtype=np.float64)
    np.testing.assert_allclose(got, chain.forward_kinematics(q).numpy(), atol=5e-6)


@needs_pyroki
def test_box_cover_contains_the_box():
    _, _, geoms, _ = peers_pyroki.problem("mixed")
    caps = geoms[1]
    centre, half = np.array([0.55, 0.0, 0.15]), np.array([0.1, 0.3, 0.02])
    pts = centre + (np.random.default_rng(0).uniform(-1, 1, (4000, 3)) * half)
    pts = np.vstack([pts, centre + half * np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T])  # corners
    pos, axis = np.asarray(caps.pose.translation()), np.asarray(caps.axis)
    r, h = np.asarray(caps.radius), np.asarray(caps.height)
    a, b = pos - axis * h[:, None] / 2, pos + axis * h[:, None] / 2
    t = np.clip(np.einsum("pkj,kj->pk", pts[:, None] - a, b - a) / np.sum((b - a) ** 2, -1), 0, 1)
    d = np.linalg.norm(pts[:, None] - (a + t[..., None] * (b - a)), axis=-1) - r
    assert (d.min(-1) <= 1e-9).all()  # every point of the box is inside a capsule of the cover
