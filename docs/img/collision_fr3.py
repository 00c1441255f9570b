"""docs/img/collision_fr3.png: the FR3's collision geometry (Franka's self-collision spheres and capped
cylinders, as diffkin's capsules) at the ready pose beside a self-colliding one, with an obstacle box;
pairs in contact are drawn red. Run from the repository root: ``python docs/img/collision_fr3.py``."""

from __future__ import annotations

import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from diffkin import models  # noqa: E402
from diffkin.collision import RobotCollision, World, box  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
URDF = ROOT / "tests" / "data" / "urdf" / "fr3.urdf"
# MoveIt's "Default" rule: a pair in contact at the ready pose is not checked (Franka's link-1 and link-3
# spheres overlap at the shoulder in every pose)
SRDF = """<robot name="fr3"><disable_collisions link1="fr3_link1_sc" link2="fr3_link3_sc" reason="Default"/>
</robot>"""


def capsule_surface(a, b, r, n=18):
    """(X, Y, Z) of a capsule's surface: a tube from a to b and a sphere at each end."""
    d = b - a
    length = np.linalg.norm(d)
    z = d / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n), np.linspace(0, np.pi, n))
    parts = []
    for c, lo, hi in ((a, np.pi / 2, np.pi), (b, 0.0, np.pi / 2)):
        vv = lo + (hi - lo) * v / np.pi
        pts = c[:, None, None] + r * (np.cos(u) * np.sin(vv) * x[:, None, None]
                                      + np.sin(u) * np.sin(vv) * y[:, None, None]
                                      + np.cos(vv) * z[:, None, None])
        parts.append(pts)
    t = np.linspace(0, 1, 2)[:, None]
    tube = (a[:, None, None] + (t * length)[None] * z[:, None, None]
            + r * (np.cos(u[:2]) * x[:, None, None] + np.sin(u[:2]) * y[:, None, None]))
    parts.append(tube)
    return parts


def box_edges(c, R, h):
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
    P = c + corners @ R.T
    return [(P[i], P[j]) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]


def draw(ax, rc, q, world, title):
    with torch.no_grad():
        a, b, r, *_ = (x.detach() for x in rc.placed(q))
        d = rc.self_distances(q)
        dw = rc.world_distances(q, world)
    contact = {n for (ga, gb), x in zip(rc.pairs, d.tolist()) if x < 0 for n in (ga, gb)}
    contact |= {rc.geoms[g].name for g in range(len(rc.geoms)) if (dw[g] < 0).any()}
    links = sorted({g.link for g in rc.geoms})
    colours = plt.cm.viridis(np.linspace(0.1, 0.9, len(links)))
    for g, geom in enumerate(rc.geoms):
        colour = "tab:red" if geom.name in contact else colours[links.index(geom.link)]
        for X in capsule_surface(a[g].numpy(), b[g].numpy(), float(r[g])):
            ax.plot_surface(X[0], X[1], X[2], color=colour, alpha=0.35, linewidth=0, shade=True)
    B = world.boxes
    for p0, p1 in box_edges(B.center[0].numpy(), B.rotation[0].numpy(), B.half_extents[0].numpy()):
        ax.plot(*np.stack((p0, p1)).T, color="0.3", lw=1)
    with torch.no_grad():
        m = float(rc.min_distance(q, world))
    ax.set_title(f"{title}\nmin distance {1000 * m:+.1f} mm", fontsize=10)
    ax.set_xlim(-0.45, 0.65)
    ax.set_ylim(-0.55, 0.55)
    ax.set_zlim(0.0, 1.1)
    ax.set_box_aspect((1.1, 1.1, 1.1))
    ax.view_init(elev=18, azim=-60)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def main() -> None:
    chain = models.from_urdf(URDF, "fr3_link8", dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the STL meshes are not shipped: Franka's primitives remain
        rc = RobotCollision.from_urdf(URDF, chain, srdf=SRDF)
    world = World(boxes=box([0.55, 0.0, 0.25], [0.1, 0.25, 0.25], dtype=torch.float64), dtype=torch.float64)
    ready = torch.tensor([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785], dtype=torch.float64)
    q = chain.random_configuration((400,), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():  # a random pose with a light contact (min distance nearest -2 cm)
        folded = q[(rc.min_distance(q, world) + 0.02).abs().argmin()]
    fig = plt.figure(figsize=(10, 5))
    for k, (q, title) in enumerate(((ready, "FR3, ready pose"), (folded, "a folded pose, contacts red"))):
        draw(fig.add_subplot(1, 2, k + 1, projection="3d"), rc, q, world, title)
    fig.suptitle(f"{len(rc.geoms)} geoms (spheres and capped cylinders as capsules), {len(rc.pairs)} "
                 "checked pairs (SRDF: link 1-3 off); the box is a World obstacle", fontsize=10)
    fig.tight_layout()
    fig.savefig(Path(__file__).with_suffix(".png"), dpi=110)


if __name__ == "__main__":
    main()
