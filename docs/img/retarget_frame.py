"""docs/img/retarget_frame.png: three shipped CMU clips retargeted onto the 29-DoF G1 (``retarget.clip``'s
defaults: the frame-by-frame warm start, then the whole-clip optimisation), one frame of each with the human
skeleton beside the robot (``retarget.plot_frame``): mid-stride in the walk, the deepest frame of the crouch
and the last frame of the reach. Run from the repository root: ``python docs/img/retarget_frame.py``."""

from __future__ import annotations

from pathlib import Path

import torch
from matplotlib.figure import Figure

from diffkin import models, retarget

OUT = Path(__file__).resolve().parent / "retarget_frame.png"


def main() -> None:
    mp = retarget.Mapping.builtin("g1")
    g1 = models.load_chain("g1", end_link=mp.frames, dtype=torch.float64).requires_grad_(False)
    clips = retarget.example_clips()
    fig = Figure(figsize=(15, 5.6))
    for k, (name, frames) in enumerate((("walk", 90), ("crouch", 120), ("reach", 74))):
        motion = retarget.load_bvh(clips[name]).frames_slice(0, frames)
        r = retarget.clip(g1, motion, mp)
        hips = motion.joint("Hips")[0, :, 2]
        t = {"walk": 45, "crouch": int(hips.argmin()), "reach": frames - 1}[name]
        m = r.metrics
        title = (f"{name}, frame {t} of {frames}: skating {float(m.foot_skating[0]):.1f} mm, floating "
                 f"{float(m.floating[0]):.1f} mm,\nkeypoint error {float(m.keypoint_error[0]):.0f} mm, "
                 f"{int(m.joint_limit_violations[0])} limit violations")
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        retarget.plot_frame(g1, r, motion, t, ax=ax, title=title)
        ax.title.set_fontsize(9)
        print(name, title.replace("\n", " "), flush=True)
    fig.subplots_adjust(left=0.0, right=0.98, bottom=0.02, top=0.88, wspace=0.08)
    fig.savefig(OUT, dpi=100)
    print(OUT)


if __name__ == "__main__":
    main()
