"""``diffkin demo`` sections: human motion retargeted onto the G1."""

from __future__ import annotations

import torch

from ._common import Report, _figure, _md_table, _shipped, _timed

__all__ = ["section_retarget"]


def section_retarget(report: Report, quick: bool) -> None:
    """Human motion onto the G1 (issue 37): the shipped CMU walk through retarget.clip, the artefact
    metrics of the frame-by-frame warm start and of the whole-clip optimisation, a frame of the clip beside
    the robot, the sole heights."""
    title = "Human motion onto a humanoid (retargeting)"
    urdf = _shipped("g1_urdf")
    if not urdf.is_file():
        report.add(title, f"Skipped: {urdf} is not installed.")
        return
    from .. import models, retarget

    mapping = retarget.Mapping.builtin("g1")
    g1 = models.from_urdf(urdf, mapping.frames, floating_base=True, dtype=torch.float64).requires_grad_(False)
    frames = 60 if quick else 150
    walk = retarget.load_bvh(retarget.example_clips()["walk"]).frames_slice(0, frames)
    r, dt = _timed(lambda: retarget.clip(g1, walk, mapping))
    rows = []
    for name, m in (("frame by frame (ik.solve)", r.warm_start), ("whole clip", r.metrics)):
        rows.append([name, int(m.joint_limit_violations[0]), f"{float(m.foot_skating[0]):.1f}",
                     f"{float(m.ground_penetration[0]):.2f}", f"{float(m.floating[0]):.1f}",
                     f"{float(m.keypoint_error[0]):.0f}"])
    fig = _figure(figsize=(7, 3.2))
    ax = fig.subplots()
    t = torch.arange(frames, dtype=torch.float64) / walk.fps
    ends = list(g1.end_links)
    for k, (foot, colour) in enumerate(zip(mapping.feet, ("tab:blue", "tab:orange"))):
        sole = retarget.sole_of(g1, foot)
        with torch.no_grad():
            T = g1.forward_kinematics(r.q[0])[:, ends.index(foot)]
        h = sole.lowest(T)[0] * 1000
        ax.plot(t, h, color=colour, label=f"{foot.split('_')[0]} sole")
        c = r.contacts[0, :, k]
        ax.fill_between(t, -40 - 30 * k, -20 - 30 * k, where=c.numpy(), color=colour, alpha=0.6, step="mid")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("lowest sole point [mm]")
    ax.legend(loc="upper right")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(report.out / "retarget_soles.png", dpi=110)
    shown = frames * 3 // 10  # a frame of the walk's stride
    retarget.plot_frame(g1, r, walk, shown, path=report.out / "retarget_frame.png",
                        title=f"the walk, frame {shown}: the clip's skeleton beside the G1")
    body = (
        f"{frames} frames of the shipped CMU walk (60 fps) onto the 29-DoF G1 with the built-in mapping: a "
        f"per-clip scale ({float(r.scale[0]):.3f}), a frame-by-frame warm start with `ik.solve`, then one "
        "Levenberg–Marquardt optimisation over all frames (feet on the ground without sliding while in "
        f"contact, no penetration, joint limits, smoothness; a block-banded solve). {dt:.1f} s in all "
        f"({frames / dt:.0f} frames/s on this machine). Metrics per `retarget.metrics` (mm):\n\n"
        + _md_table(["stage", "limit violations", "skating", "penetration", "floating", "keypoint error"],
                    rows)
        + f"\n\nFrame {shown} (`retarget.plot_frame`): the human skeleton of the clip (blue) beside the G1 "
        "(orange) and the scaled human joints it tracks (green):\n\n"
        "![a retargeted frame](retarget_frame.png)\n\nThe lowest sole point of each foot after the "
        "optimisation (bars: contact detected in the human clip):\n\n![sole heights](retarget_soles.png)\n"
    )
    report.add(title, body)
    m = r.metrics
    if int(m.joint_limit_violations[0]) or float(m.ground_penetration[0]) > 1.0 or float(
            m.foot_skating[0]) > float(r.warm_start.foot_skating[0]):
        report.failures.append("retargeting: the whole-clip result violates a limit, penetrates or skates")
