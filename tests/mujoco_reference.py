"""MuJoCo as the reference for the MJCF collision tests: body poses by MuJoCo's own FK and random qpos."""

from __future__ import annotations

import numpy as np
import torch

mujoco = __import__("pytest").importorskip("mujoco")


class MuJoCoPoses:
    """``body_poses(q) -> (..., nbody, 4, 4)`` by MuJoCo's FK (``mj_kinematics`` per row; q is qpos)."""

    def __init__(self, m):
        self.m, self.d = m, mujoco.MjData(m)

    def __call__(self, q: torch.Tensor) -> torch.Tensor:
        rows = []
        for qq in q.reshape(-1, self.m.nq).detach().cpu().numpy():
            self.d.qpos[:] = qq
            mujoco.mj_kinematics(self.m, self.d)
            T = np.tile(np.eye(4), (self.m.nbody, 1, 1))
            T[:, :3, :3] = self.d.xmat.reshape(-1, 3, 3)
            T[:, :3, 3] = self.d.xpos
            rows.append(T)
        return torch.tensor(np.stack(rows), dtype=q.dtype).reshape(*q.shape[:-1], self.m.nbody, 4, 4)


def random_qpos(m, n: int, seed: int) -> np.ndarray:
    """``(n, nq)`` random qpos, all rows at once: hinges and slides uniform in their range (unlimited: ±π),
    ball and free joints a uniformly random unit quaternion, a free joint's position in [-1, 1]^3."""
    rng = np.random.default_rng(seed)
    q = np.tile(m.qpos0, (n, 1))
    for j in range(m.njnt):
        a, kind = m.jnt_qposadr[j], m.jnt_type[j]
        if kind in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL):
            if kind == mujoco.mjtJoint.mjJNT_FREE:
                q[:, a: a + 3] = rng.uniform(-1.0, 1.0, (n, 3))
                a += 3
            quat = rng.normal(size=(n, 4))
            q[:, a: a + 4] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
        else:
            lo, hi = m.jnt_range[j] if m.jnt_limited[j] else (-np.pi, np.pi)
            q[:, a] = rng.uniform(lo, hi, n)
    return q
