"""A retargeted frame as a picture: the human skeleton beside the robot at the same frame (matplotlib 3-D).

Drawn on a :class:`matplotlib.figure.Figure` (no pyplot: the process's backend and settings are left
alone). The robot is drawn as in the viewer (:func:`diffkin.viz.segment_points`: segments between joint
origins), the human as its bones (``motion.parents``), in metres, z up. The human stands beside the robot:
moved by ``gap`` along the horizontal axis of the view, which looks at the robot ``azim`` degrees off its
heading (the heading of the clip's right-to-left foot line, turned 90°, as retargeting's start uses).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..errors import ShapeError, require
from .motion import Motion

__all__ = ["plot_frame"]


def _heading(points: np.ndarray, left: int, right: int) -> float:
    """Yaw (rad) of the forward direction: the left-minus-right line of two joints turned by -90°."""
    d = points[left] - points[right]
    return math.atan2(d[1], d[0]) - math.pi / 2


def plot_frame(chain, result, motion: Motion, t: int, *, clip: int = 0, ax=None, azim: float = 35.0,
               gap: float = 0.9, title: str | None = None, path=None):
    """Draw frame ``t`` of clip ``clip``: the human skeleton of ``motion`` beside the robot at
    ``result.q[clip, t]`` (the scaled human keypoints the robot tracked as dots on the robot).

    Args:
        chain: the chain ``result`` was computed on.
        result: a :class:`~diffkin.retarget.RetargetResult` (``q (B, T, nq)``, ``keypoints (B, T, K, 3)``).
        motion: the human clip retargeted (``positions (B, T, J, 3)``, ``parents``).
        t: the frame (negative counts from the end).
        ax: a matplotlib 3-D axes to draw into; None: a new Figure (6 x 5 in) with one.
        azim: the view's angle from the heading (degrees; 0 looks at the robot's front).
        gap: metres between the robot and the human along the view's horizontal axis.
        path: where to save the figure as PNG (110 dpi), if given.

    Returns the Figure.
    """
    from ..viz import segment_points

    B, T = result.q.shape[:2]
    if not -B <= clip < B or not -T <= t < T:
        raise ShapeError(f"clip {clip}, frame {t} is not in the result's {B} clips of {T} frames")
    if motion.positions.shape[0] not in (1, B) or motion.positions.shape[1] != T:
        raise ShapeError(f"the motion has {tuple(motion.positions.shape[:2])} (clips, frames), the result "
                         f"{(B, T)}")
    parents = getattr(motion, "parents", None)
    if parents is None:
        raise ShapeError("the motion has no skeleton (parents): load it with retarget.load_bvh")
    if ax is None:
        Figure = require("matplotlib.figure", "plot", "retarget.plot_frame").Figure
        fig = Figure(figsize=(6, 5))
        ax = fig.add_subplot(projection="3d")
    fig = ax.figure
    q = result.q[clip, t].detach()
    with torch.no_grad():
        F = chain.forward_kinematics(q, all_frames=True).cpu().double().numpy()
        E = chain.forward_kinematics(q).reshape(-1, 4, 4).cpu().double().numpy()
    robot = segment_points(chain, F, E, floating=False)
    human = motion.positions[min(clip, motion.positions.shape[0] - 1), t].detach().cpu().double().numpy()
    kp = result.keypoints[clip, t].detach().cpu().double().numpy()
    frames = list(result.keypoint_frames)
    feet = [frames.index(f) for f in frames[:2]]  # the feet come first (Mapping.frames)
    yaw = _heading(kp, *feet)
    view = yaw + math.radians(azim)  # the direction the camera looks from
    across = np.array([-math.sin(view), math.cos(view), 0.0])  # the view's horizontal axis
    centre = kp.mean(0) * np.array([1.0, 1.0, 0.0])
    human = human - human.mean(0) * np.array([1.0, 1.0, 0.0]) + centre + gap * across
    for a, b in robot:
        ax.plot(*np.stack([a, b]).T, color="tab:orange", lw=2.2)
    for j, p in enumerate(parents):
        if p >= 0:
            ax.plot(*human[[p, j]].T, color="tab:blue", lw=1.6)
    ax.scatter(*kp.T, color="tab:green", s=14, depthshade=False, label="scaled human joints (targets)")
    ax.plot([], [], color="tab:orange", lw=2.2, label="robot")
    ax.plot([], [], color="tab:blue", lw=1.6, label="human (clip)")
    pts = np.concatenate([robot.reshape(-1, 3), human, kp])
    lo, hi = pts.min(0), pts.max(0)
    mid, half = (lo + hi) / 2, (hi - lo).max() / 2 + 0.05
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(0.0, 2 * half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=12, azim=math.degrees(view))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(title if title is not None else f"frame {t % T} of {T}")
    ax.legend(loc="upper left", fontsize=7)
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    return fig
