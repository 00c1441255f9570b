"""Pictures of the viewer's scene for the docs: ``docs/img/viewer_mjcf.png`` (MJCF models) and
``docs/img/viewer_collision.png`` (collision geometry, a contact in red).

Each picture is what a :class:`diffkin.viz.Viewer` holds: the script starts the viewer (viser, on a free
loopback port), sets the configuration, and draws the scene's own triangle sets at the poses and in the
colours of its nodes (MJCF geoms: body node ∘ geom node; collision geoms and world objects: their nodes)
with matplotlib, headless. No browser is needed (``scripts/view_check.py`` takes a real browser screenshot
where Chromium and Playwright are installed). The vendored Menagerie models have no mesh files, so their
bodies show the collision primitives that stand in for missing meshes.

Usage (from the repository root; needs the ``viz`` and ``mjcf`` extras)::

    python scripts/viewer_pictures.py [--out docs/img]
"""

from __future__ import annotations

import argparse
import functools
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # a script, not library code: headless output
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from diffkin import models, viz  # noqa: E402
from diffkin.collision import RobotCollision, World  # noqa: E402
from diffkin.models.mjcf import compile_mjcf  # noqa: E402
from diffkin.models.mjcf_bodies import body_poses  # noqa: E402
from diffkin.viz import scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "mjcf"
F64 = torch.float64


def _pose(h) -> np.ndarray:
    return scene._pose(h.wxyz, h.position)


def _triangles(ax, v, f, T, rgb, alpha: float) -> np.ndarray:
    """Add the triangles (V, 3), (F, 3) placed by T (4, 4); returns the placed vertices."""
    P = np.asarray(v, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    poly = Poly3DCollection(P[np.asarray(f)], facecolor=np.asarray(rgb) / 255.0, alpha=alpha,
                            edgecolor="none")
    ax.add_collection3d(poly)
    return P


def _skeleton(ax, v) -> list[np.ndarray]:
    seg = np.asarray(v._segments.points, dtype=np.float64)
    for a, b in seg:
        ax.plot(*np.stack((a, b)).T, color=np.asarray(scene._SEGMENT_RGB) / 255.0, lw=2.0)
    return [seg.reshape(-1, 3)]


def _frame_axes(ax, pts: list[np.ndarray], title: str) -> None:
    P = np.concatenate(pts)
    lo, hi = P.min(0), P.max(0)
    c, r = 0.5 * (lo + hi), 0.55 * float((hi - lo).max())
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=15, azim=-55)
    ax.set_title(title, fontsize=9)
    ax.set_xticklabels([])
    ax.set_yticklabels([])
    ax.set_zticklabels([])


def draw_mjcf(ax, v, title: str) -> None:
    """The viewer's MJCF geoms and skeleton."""
    pts = _skeleton(ax, v)
    for g, T, h in zip(v.visual_geoms, v.geom_poses(), v._geom_handles):
        pts.append(_triangles(ax, g.vertices, g.faces, T, h.color, 0.9 if g.opacity >= 1 else g.opacity))
    _frame_axes(ax, pts, title)


def draw_collision(ax, v, title: str) -> None:
    """The viewer's collision geoms and world objects in their current colours."""
    cv = v._collision_view
    pts = _skeleton(ax, v)
    for (verts, faces), h in zip(cv.meshes, cv.handles):
        pts.append(_triangles(ax, verts, faces, _pose(h), h.color, 0.45))
    for (verts, faces), h in zip(cv.world_meshes, cv.world_handles):
        placed = _triangles(ax, verts, faces, _pose(h), h.color, 0.6)
        if "halfspace" not in h.name:  # the floor plate would set the zoom
            pts.append(placed)
    st = v.contacts
    pairs = ", ".join(f"{a} – {b}" for a, b, _ in st["pairs"][:2]) or "none"
    _frame_axes(ax, pts, f"{title}\nin contact: {pairs}; min distance {1e3 * st['min_distance']:+.0f} mm")


def mjcf_picture(out: Path) -> None:
    ends = ["left_ankle_link", "right_ankle_link", "left_elbow_link", "right_elbow_link"]
    h1 = models.from_mjcf(DATA / "unitree_h1/h1.xml", ends, dtype=F64)
    cassie = models.from_mjcf(DATA / "agility_cassie/cassie.xml", ["left-achilles-rod", "right-foot"],
                              dtype=F64)
    fig = plt.figure(figsize=(10, 5.2))
    v = viz.show(h1, port=0)
    try:
        q = h1.neutral_configuration()
        q[2] = 1.0
        model = compile_mjcf(DATA / "unitree_h1/h1.xml")[0]
        for name, x in (("left_shoulder_pitch", -0.9), ("right_shoulder_roll", -0.5), ("left_knee", 0.8),
                        ("left_hip_pitch", -0.5), ("right_elbow", 1.2)):
            q[h1.qpos_index().index(model.joint(name).qposadr[0])] = x
        v.set_q(q)
        rz = [i for i, s in enumerate(v._slider_specs) if s.label.endswith(".rz")][0]
        v.sliders[rz].value = 0.5  # the free base turned by its rotation slider (integrated, unit quaternion)
        draw_mjcf(fig.add_subplot(1, 2, 1, projection="3d"), v,
                  f"Unitree H1 (free base + 19 hinges): {len(v.visual_geoms)} geoms\n"
                  "base turned 0.5 rad by its rz slider")
    finally:
        v.close()
    v = viz.show(cassie, port=0)
    try:
        q = cassie.neutral_configuration()
        q[2] = 1.0
        v.set_q(q)
        for label, x in (("left-achilles-rod.rx", 0.6), ("left-achilles-rod.rz", -0.4)):
            v.sliders[[i for i, s in enumerate(v._slider_specs) if s.label == label][0]].value = x
        draw_mjcf(fig.add_subplot(1, 2, 2, projection="3d"), v,
                  f"Agility Cassie: {len(v.visual_geoms)} geoms (capsules, ellipsoids)\n"
                  "ball joint (achilles rod) moved by its rx, rz sliders")
    finally:
        v.close()
    fig.suptitle("diffkin.viz on MJCF models (the scene the viewer serves; meshes not vendored: collision "
                 "primitives stand in)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def collision_picture(out: Path) -> None:
    path = DATA / "unitree_h1/h1.xml"
    h1 = models.from_mjcf(path, ["left_elbow_link", "right_elbow_link"], dtype=F64)
    # H1's hip geoms overlap in every pose (yaw-pitch links, the two roll links): excluded the MJCF way,
    # as an SRDF's disable_collisions would be for a URDF
    ex = "".join(f'<exclude body1="{a}" body2="{b}"/>' for a, b in (
        ("left_hip_yaw_link", "left_hip_pitch_link"), ("right_hip_yaw_link", "right_hip_pitch_link"),
        ("left_hip_roll_link", "right_hip_roll_link")))
    text = path.read_text().replace("</mujoco>", f"<contact>{ex}</contact></mujoco>")
    col = RobotCollision.from_mjcf(compile_mjcf(text)[0], h1, body_poses=functools.partial(body_poses, h1))
    q0 = h1.neutral_configuration()
    q0[2] = 1.0
    world = World(spheres=[[0.35, -0.3, 1.2, 0.08]], halfspaces=[[0.0, 0.0, 1.0, -0.15]], dtype=F64)
    # arm poses of one random draw: the first with a self-contact and one without
    qs = h1.random_configuration((300,), generator=torch.Generator().manual_seed(3))
    qs[:, :7] = q0[:7]
    with torch.no_grad():
        d = col.self_distances(qs).amin(-1)
    hit = int(torch.nonzero((d < 0) & (d > -0.03))[0])
    free = int(torch.nonzero(d > 0.02)[0])
    fig = plt.figure(figsize=(10, 5.2))
    for k, (q, title) in enumerate(((qs[free], "no contact"), (qs[hit], "a self-contact (red)"))):
        v = viz.show(h1, q, port=0, collision=col, world=world)
        try:
            draw_collision(fig.add_subplot(1, 2, k + 1, projection="3d"), v, f"H1, {title}")
        finally:
            v.close()
    fig.suptitle("Viewer(chain, collision=RobotCollision.from_mjcf(...), world=World(...)): "
                 f"{len(col.geoms)} geoms, {len(col.pairs)} pairs; a floor half-space and a sphere",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "img"))
    out = Path(ap.parse_args().out)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # missing meshes and ignored equalities are expected here
        mjcf_picture(out / "viewer_mjcf.png")
        collision_picture(out / "viewer_collision.png")
    print(f"wrote {out / 'viewer_mjcf.png'} and {out / 'viewer_collision.png'}")


if __name__ == "__main__":
    main()
