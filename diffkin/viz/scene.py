"""What the viewer draws and the helpers its modules share: the robot as segments (:func:`segment_points`),
its colours, quaternion <-> pose conversions for viser's nodes, and quiet contexts for viser's banner and the
mesh loaders' warnings. Nothing here imports viser until :func:`_import_viser` is called."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..errors import DiffkinError, ShapeError

__all__ = ["segment_points", "MISSING_EXTRA"]

#: the message (after ``error:``) when viser is not installed
MISSING_EXTRA = "diffkin view needs the 'viz' extra: pip install 'diffkin[viz]'"

_SEGMENT_RGB = (235, 120, 20)  # orange links
_KEYPOINT_RGB = (30, 170, 60)  # green human keypoints of a retargeted clip
_END_RGB = (40, 110, 230)  # blue end-link frames


def _import_viser():
    try:
        import viser
    except ImportError as exc:
        raise DiffkinError(MISSING_EXTRA) from exc
    return viser


def _wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z), w >= 0, of rotation matrices ``(..., 3, 3)``."""
    from ..rotations import matrix_to_quaternion

    return matrix_to_quaternion(torch.as_tensor(R, dtype=torch.float64)).numpy()


def _pose(wxyz, position) -> np.ndarray:
    """4x4 transform from a quaternion (w, x, y, z) and a position."""
    from ..rotations import quaternion_to_matrix

    T = np.eye(4)
    q = torch.as_tensor(np.asarray(wxyz, dtype=np.float64))
    T[:3, :3] = quaternion_to_matrix(q / q.norm()).numpy()
    T[:3, 3] = np.asarray(position, dtype=np.float64)
    return T


def _as_joints(chain, q, name: str = "q") -> Tensor:
    t = torch.as_tensor(np.asarray(q.detach().cpu() if isinstance(q, Tensor) else q, dtype=np.float64))
    if t.ndim != 1 or t.shape[0] != chain.n_joints:
        raise ShapeError(f"{name} must have shape ({chain.n_joints},), got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise DiffkinError(f"{name} must be finite")
    return t.to(dtype=chain.dtype, device=chain.device)


def segment_points(chain, F: np.ndarray, E: np.ndarray, floating: bool = True) -> np.ndarray:
    """The robot's drawing as segments ``(S, 2, 3)``: each joint frame's origin to its parent's, then each end
    link's pose to the frame it hangs from (unless a single end link is the last frame). ``F`` ``(J + 1, 4,
    4)``: ``chain.forward_kinematics(q, all_frames=True)``; ``E`` ``(K, 4, 4)``: the end poses.
    ``floating=False`` leaves out the segments of a free first joint (its three slides and its ball: the
    world origin to the floating body)."""
    topo = chain.topology
    parents = list(topo.parents)
    skip = 0
    if not floating and chain.joint_kinds and chain.joint_kinds[0] == "free":
        skip = list(topo.motions).index("S") + 1  # the free joint's frames: slides x, y, z, then the ball
    pts = [(F[p + 1, :3, 3], F[j + 1, :3, 3]) for j, p in enumerate(parents) if j >= skip]
    if not (chain.single_end and topo.ends[0] == len(parents) - 1):
        pts += [(F[e + 1, :3, 3], E[k, :3, 3]) for k, e in enumerate(topo.ends)]
    return np.asarray(pts, dtype=np.float64).reshape(-1, 2, 3)



def _maybe_quiet(verbose: bool):
    import contextlib
    import io

    return contextlib.nullcontext() if verbose else contextlib.redirect_stdout(io.StringIO())


class _quiet_logs:
    """Silence yourdfpy's and trimesh's warnings about meshes that do not resolve."""

    def __enter__(self):
        import logging
        import warnings

        self._warn = warnings.catch_warnings()
        self._warn.__enter__()
        warnings.simplefilter("ignore")
        self._loggers = [logging.getLogger(n) for n in ("yourdfpy", "trimesh")]
        self._levels = [lg.level for lg in self._loggers]
        for lg in self._loggers:
            lg.setLevel(logging.CRITICAL)
        return self

    def __exit__(self, *exc):
        for lg, lvl in zip(self._loggers, self._levels):
            lg.setLevel(lvl)
        self._warn.__exit__(*exc)
