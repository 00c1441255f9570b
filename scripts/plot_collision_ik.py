"""docs/img/collision_ik_fr3.png: one FR3 target solved by ``ik.solve`` (its solution collides) and by
``ik.solve(..., collision=, world=)`` (clear), among the obstacles of ``benchmarks/bench_collision_ik.py``
(two spheres and a box). Geoms in contact are red. Run from the repository root:
``python scripts/plot_collision_ik.py``."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks.bench_collision_ik import robot, targets, world  # noqa: E402
from diffkin import ik  # noqa: E402


def _figure_helpers():
    """``draw`` and ``capsule_surface`` of docs/img/collision_fr3.py (one drawing of the geoms)."""
    spec = importlib.util.spec_from_file_location("collision_fr3", ROOT / "docs" / "img" / "collision_fr3.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.draw, mod.capsule_surface


def main() -> None:
    draw, capsule_surface = _figure_helpers()
    chain, rc = robot(torch.float64)
    w = world("mixed", torch.float64)
    _, T = targets(chain, rc, w, 200, seed=2)
    plain = ik.solve(chain, T, seed=0)
    with torch.no_grad():
        d = rc.min_distance(plain.q, w)
    k = int(torch.nonzero(plain.success & (d < -0.01))[0])  # a target the plain solve puts in collision
    free = ik.solve(chain, T[k], collision=rc, world=w, margin=0.005, seed=0)
    assert bool(free.success)
    fig = plt.figure(figsize=(10, 5))
    for i, (q, title) in enumerate(((plain.q[k], "ik.solve(chain, T)"),
                                    (free.q, "ik.solve(chain, T, collision=rc, world=w, margin=5 mm)"))):
        ax = fig.add_subplot(1, 2, i + 1, projection="3d")
        draw(ax, rc, q, w, title)
        for *c, r in w.spheres.tolist():
            for X in capsule_surface(torch.tensor(c).numpy(), torch.tensor(c).numpy(), r):
                ax.plot_surface(X[0], X[1], X[2], color="0.55", alpha=0.25, linewidth=0)
        p = T[k, :3, 3].numpy()
        ax.scatter(*p, color="k", marker="x", s=40)
    fig.suptitle("the same target (x, 0.1 mm / 1 mrad): the plain solution collides, the collision-aware "
                 "one is clear", fontsize=10)
    fig.tight_layout()
    out = ROOT / "docs" / "img" / "collision_ik_fr3.png"
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
