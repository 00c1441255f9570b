"""Reachable workspace (§2.10.1) of a bundled model: sample the joint-limit box, one batched FK pass, plot the
end-effector positions in a top view (x, y) and a side view (radius in the xy-plane, z).

    python examples/workspace.py [--robot panda] [--n 50000] [--seed 0] [--out runs/examples]

Writes ``<out>/workspace_<robot>.png`` (matplotlib, Agg backend). For a planar arm (all points at z = 0) the
side view is replaced by a histogram of the distance from the base (cf. Example 2.6, Fig. 2.30).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from diffkin import models  # noqa: E402


def plot_workspace(name: str, n: int, seed: int, out_dir: Path) -> Path:
    chain = models.load(name, dtype=torch.float32)
    p = models.sample_workspace(chain, n, generator=torch.Generator().manual_seed(seed))
    x, y, z = p.unbind(-1)
    r = torch.sqrt(x**2 + y**2)
    planar = bool(z.abs().max() < 1e-6)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10.5, 4.6), layout="constrained")
    colour = r if planar else z
    points = ax1.scatter(x, y, s=0.5, c=colour, cmap="viridis", alpha=0.4, linewidths=0,
                         vmin=float(colour.min()), vmax=float(colour.max()))
    title = "plane of the arm (colour: distance)" if planar else "top view (colour: z)"
    ax1.set(xlabel="x [m]", ylabel="y [m]", title=title)
    ax1.set_aspect("equal")
    if planar:
        ax2.hist(r.numpy(), bins=100, color="tab:blue")
        ax2.set(xlabel="distance from the base axis [m]", ylabel="samples", title="reach")
    else:
        ax2.scatter(r, z, s=0.5, c=z, cmap="viridis", alpha=0.4, linewidths=0, norm=points.norm)
        ax2.set(xlabel="sqrt(x² + y²) [m]", ylabel="z [m]", title="side view (all azimuths folded)")
        ax2.set_aspect("equal")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    opaque = matplotlib.cm.ScalarMappable(norm=points.norm, cmap=points.cmap)  # the bar without the alpha
    bar = fig.colorbar(opaque, ax=[ax1] if planar else [ax1, ax2], shrink=0.85)
    bar.set_label("distance from the base axis [m]" if planar else "end-effector height z [m]")
    fig.suptitle(f"{name}: {n} reachable end-effector positions, joints uniform within their limits")
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"workspace_{name}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="panda", choices=models.available())
    p.add_argument("--n", type=int, default=50000, help="number of joint samples")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/examples"))
    args = p.parse_args(argv)
    path = plot_workspace(args.robot, args.n, args.seed, args.out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
