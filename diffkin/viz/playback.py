"""Trajectories for the viewer's playback: joint vectors ``(N, n)`` from tensors, arrays and files, retargeted
clips (:class:`~diffkin.retarget.RetargetResult` or its ``.npz``) and planned motions
(:class:`~diffkin.motion.MotionResult` or the ``.npz`` of ``diffkin plan``), with their frame rates."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..errors import DiffkinError, ShapeError

__all__: list[str] = []  # used through diffkin.viz.Viewer.load_trajectory / play

def _plan_problem(chain, q, t, duration, success, reason, problem: int, where: str) -> tuple[Tensor, float]:
    """Problem ``problem`` of a planned motion (:class:`~diffkin.motion.MotionResult` or the ``.npz`` of
    ``diffkin plan``: ``q (B, S, nq)``, ``t (B, S)`` every dt): its samples up to its end, and 1 / dt."""
    B, S = q.shape[0], q.shape[1]
    if not -B <= problem < B:
        raise ShapeError(f"problem {problem} is not among the {B} problems of {where}")
    problem %= B
    if not bool(success[problem]):
        raise DiffkinError(f"problem {problem} of {where} failed ({reason[problem]}): no motion to play")
    t = np.asarray(t[problem], dtype=np.float64)
    if S < 2:
        return _as_trajectory(chain, q[problem]), None
    dt = float(t[1] - t[0])
    n = min(S, int(math.ceil(float(duration[problem]) / dt - 1e-9)) + 1)  # up to its end, at rest there
    return _as_trajectory(chain, q[problem][:n]), 1.0 / dt


def _read_trajectory(chain, trajectory, clip: int = 0,
                     problem: int = 0) -> tuple[Tensor, float | None, np.ndarray | None]:
    """Joint vectors ``(N, n)``, their frame rate when the source has one (else None) and, for a retargeted
    clip, the human keypoints ``(N, K, 3)`` to draw beside the robot (else None).

    A file is read by :func:`diffkin.io.data.read_joints` (``.npy``, ``.csv``, ``.npz`` entry ``q``); an
    ``.npz`` of ``diffkin trajectory joint`` (entries ``t`` and ``position``) is read too, at its own rate;
    so is one of :meth:`diffkin.retarget.RetargetResult.save` (``q (B, T, nq)`` and ``fps``: clip ``clip``
    at the clip's rate). A :class:`~diffkin.retarget.RetargetResult` itself gives clip ``clip``'s ``q``, its
    rate and its scaled human keypoints. A planned motion (a :class:`~diffkin.motion.MotionResult` or the
    ``.npz`` of ``diffkin plan``) gives problem ``problem`` up to its end, at its rate 1 / dt.
    """
    from ..motion import MotionResult

    if isinstance(trajectory, MotionResult):
        host = trajectory.t.detach().cpu().double().numpy()
        return (*_plan_problem(chain, trajectory.q, host, trajectory.duration.cpu(), trajectory.success.cpu(),
                               trajectory.reason, problem, "the motion result"), None)
    q_clips = getattr(trajectory, "q", None)
    if isinstance(q_clips, Tensor) and hasattr(trajectory, "keypoints") and hasattr(trajectory, "fps"):
        B = q_clips.shape[0]
        if not -B <= clip < B:
            raise ShapeError(f"clip {clip} is not among the result's {B} clips")
        points = trajectory.keypoints[clip].detach().cpu().double().numpy()
        return _as_trajectory(chain, q_clips[clip]), float(trajectory.fps), points
    if not isinstance(trajectory, (str, Path)):
        return _as_trajectory(chain, trajectory), None, None
    path = Path(trajectory)
    if path.suffix == ".npz" and path.is_file():
        with np.load(path, allow_pickle=False) as data:
            if "q" not in data.files and "position" in data.files:
                q = _as_trajectory(chain, data["position"])
                fps = None
                if "t" in data.files and data["t"].shape == (q.shape[0],) and q.shape[0] > 1:
                    span = float(data["t"][-1] - data["t"][0])
                    fps = (q.shape[0] - 1) / span if span > 0 else None
                return q, fps, None
            if {"q", "t", "duration", "success"} <= set(data.files) and data["q"].ndim == 3:  # diffkin plan
                reason = data["reason"] if "reason" in data.files else [""] * data["q"].shape[0]
                return (*_plan_problem(chain, data["q"], data["t"], data["duration"], data["success"], reason,
                                       problem, repr(str(path))), None)
            if "q" in data.files and data["q"].ndim == 3 and "fps" in data.files:  # RetargetResult.save
                B = data["q"].shape[0]
                if not -B <= clip < B:
                    raise ShapeError(f"clip {clip} is not among the {B} clips of {str(path)!r}")
                return _as_trajectory(chain, data["q"][clip]), float(data["fps"]), None
    return _as_trajectory(chain, trajectory), None, None


def _as_trajectory(chain, trajectory) -> Tensor:
    """Joint vectors ``(N, n)`` from a tensor, an array or a .npy/.npz/.csv file."""
    if isinstance(trajectory, (str, Path)):
        from ..io.data import read_joints

        return read_joints(trajectory, chain.n_joints, dtype=chain.dtype, device=chain.device)
    t = trajectory.detach() if isinstance(trajectory, Tensor) else torch.as_tensor(np.asarray(trajectory))
    t = t.to(dtype=chain.dtype, device=chain.device)
    if t.ndim == 1 and t.shape[0] == chain.n_joints:
        t = t[None]
    if t.ndim != 2 or t.shape[1] != chain.n_joints or t.shape[0] == 0:
        raise ShapeError(f"trajectory must have shape (N, {chain.n_joints}), got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise DiffkinError("trajectory must be finite")
    return t
