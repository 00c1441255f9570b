"""Matplotlib (Agg) drawing of the arm, its target(s) and the end-effector trace as an RGB array."""

from __future__ import annotations

import numpy as np

__all__ = ["ArmRenderer"]


class ArmRenderer:
    """Reusable off-screen figure; ``draw`` returns an ``(H, W, 3)`` uint8 image."""

    def __init__(self, planar: bool = False, extent: float = 1.0, size: tuple[int, int] = (480, 480)):
        from diffkin.errors import require

        Figure = require("matplotlib.figure", "plot", "render_mode='rgb_array'").Figure
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        self.planar, self.extent = planar, extent
        self.fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
        self.canvas = FigureCanvasAgg(self.fig)
        self.ax = self.fig.add_subplot(111) if planar else self.fig.add_subplot(111, projection="3d")

    def draw(self, frames: np.ndarray, trace: np.ndarray, targets: dict) -> np.ndarray:
        """frames ``(n + 1, 3)`` link origins; trace ``(T, 3)``; targets {"goal": (3,), "path": (M, 3)}."""
        ax, e = self.ax, self.extent
        ax.clear()
        dims = 2 if self.planar else 3
        cols = lambda pts: [pts[:, i] for i in range(dims)]  # noqa: E731
        ax.plot(*cols(frames), "-o", color="tab:blue", lw=3, ms=4, label="arm")
        if "path" in targets:
            ax.plot(*cols(np.asarray(targets["path"])), "--", color="tab:gray", lw=1, label="path")
        if len(trace) > 1:
            ax.plot(*cols(trace), color="tab:orange", lw=1.5, label="trace")
        if "goal" in targets:
            g = np.asarray(targets["goal"])[None]
            ax.scatter(*cols(g), color="tab:red", s=40, label="target")
        ax.set_xlim(-e, e)
        ax.set_ylim(-e, e)
        if not self.planar:
            ax.set_zlim(-0.2 * e, e)
        else:
            ax.set_aspect("equal")
        ax.legend(loc="upper right", fontsize=7)
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def close(self) -> None:
        self.fig.clear()
