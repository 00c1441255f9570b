"""calibrate_camera against OpenCV's hand-eye pipelines on synthetic chessboard images (issue 38).

    python -m benchmarks.bench_camera_calibration [--seeds 5] [--images 40] [--noise 0.3] [--json out.json]
        [--figures docs/img]

Scenes (benchmarks/camera_scenes.py): a Panda with a 7 x 10-square board (25 mm) on its flange and a fixed
camera (eye-to-hand), a UR5 with the camera on its flange over a fixed board (eye-in-hand); every geometry
parameter the images identify perturbed by up to ±1 mm / ±0.1°; Gaussian pixel noise of ``--noise`` px per
coordinate. Per seed: diffkin's ``calibrate_camera`` (robot + camera + board, least squares) and OpenCV's
seven closed forms (solvePnP per image, then calibrateHandEye Park/Tsai/Horaud/Andreff/Daniilidis and
calibrateRobotWorldHandEye Shah/Li, with the nominal kinematics; the board's pose for the hand-eye methods is
the chordal mean of the loop). Reported, RMS over the seeds: the camera pose's translation [mm] and rotation
[mrad] error against the truth, the held-out 3D error [mm] (the board's corners in the camera frame at 100
postures not used, model against truth) and the held-out reprojection error [px] of the same corners.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path

import torch

from benchmarks.camera_scenes import (
    DIST,
    SCENES,
    K,
    cam_board,
    chessboard,
    held_out_3d,
    images,
    opencv_pipelines,
    scene,
)
from diffkin.calibration import calibrate_camera
from diffkin.calibration.camera import project_points


def _rot_err(A, B) -> float:
    c = ((A[:3, :3].mT @ B[:3, :3]).trace() - 1) / 2
    return float(torch.arccos(c.clamp(-1, 1)))


def _reprojection(chain, cam, board, true, cam_true, board_true, q, setup) -> float:
    """RMS pixel distance of the board's corners at postures ``q``, model against truth."""
    pts = chessboard()
    a = project_points(pts, cam_board(chain, q, cam, board, setup), K, DIST)
    b = project_points(pts, cam_board(true, q, cam_true, board_true, setup), K, DIST)
    return float((a - b).norm(dim=-1).square().mean().sqrt())


def run_one(robot: str, seed: int, n_images: int, noise: float):
    """Rows ``{method: {camera_mm, camera_mrad, held_out_3d_mm, held_out_px}}`` and the diffkin result."""
    nominal, true, q, q_out, cam, board, _ = scene(robot, n_images, seed)
    setup = SCENES[robot][2]
    uv = images(true, q, cam, board, setup, noise, seed + 2)
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = calibrate_camera(
            nominal,
            q,
            uv,
            chessboard(),
            camera_matrix=K,
            dist_coeffs=DIST,
            setup=setup,
            measurement_noise=noise,
            cross_validation=0,
            progress=False,
        )
    seconds = time.perf_counter() - t
    rows = {}

    def row(X, Y, chain):
        return {
            "camera_mm": float((X[:3, 3] - cam[:3, 3]).norm()) * 1e3,
            "camera_mrad": _rot_err(X, cam) * 1e3,
            "held_out_3d_mm": held_out_3d(chain, X, Y, true, cam, board, q_out, setup) * 1e3,
            "held_out_px": _reprojection(chain, X, Y, true, cam, board, q_out, setup),
        }

    rows["diffkin calibrate_camera"] = row(res.camera_pose, res.board_pose, res.chain)
    for name, (X, Y) in opencv_pipelines(nominal, q, uv, setup).items():
        rows[f"OpenCV {name}"] = row(X, Y, nominal)
    return rows, res, seconds, (nominal, true, q, uv, cam, board)


def figures(out: Path, res, data) -> None:
    """docs figures: the residuals per image before/after, and one image's detections beside the
    projections of the nominal (start) and the calibrated model."""
    from matplotlib.figure import Figure

    nominal, true, q, uv, cam, board = data
    res.plot_residuals(out / "camera_calibration_residuals.png")
    pts = chessboard()
    i = int(res.initial_image_rms.argmax())
    start = project_points(
        pts,
        cam_board(nominal, q[i : i + 1], res.initial_camera_pose, res.initial_board_pose, res.setup),
        K,
        DIST,
    )[0]
    fit = project_points(
        pts, cam_board(res.chain, q[i : i + 1], res.camera_pose, res.board_pose, res.setup), K, DIST
    )[0]
    fig = Figure(figsize=(10, 4.2))
    ax, ax2 = fig.subplots(1, 2)
    for a in (ax, ax2):
        a.plot(uv[i, :, 0], uv[i, :, 1], "k+", ms=8, label="detected (0.3 px noise)")
    ax.plot(start[:, 0], start[:, 1], "o", mfc="none", color="tab:red", label="nominal robot + hand-eye")
    ax2.plot(fit[:, 0], fit[:, 1], "o", mfc="none", color="tab:green", label="calibrated")
    c = uv[i].mean(0)
    for a, title in ((ax, "start"), (ax2, "after calibrate_camera")):
        a.set_xlim(float(c[0]) - 40, float(c[0]) + 40)
        a.set_ylim(float(c[1]) + 30, float(c[1]) - 30)
        a.set_aspect("equal")
        a.set_xlabel("u [px]")
        a.set_ylabel("v [px]")
        a.set_title(f"image {i}, centre of the board: {title}", fontsize=10)
        a.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "camera_calibration_detections.png", dpi=110)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--images", type=int, default=40)
    ap.add_argument("--noise", type=float, default=0.3)
    ap.add_argument("--robots", nargs="+", default=list(SCENES))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--figures", type=Path)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    report = {}
    for robot in args.robots:
        acc: dict[str, dict[str, list[float]]] = {}
        times, chi = [], []
        for seed in range(args.seeds):
            rows, res, seconds, data = run_one(robot, seed, args.images, args.noise)
            times.append(seconds)
            chi.append(res.noise_ratio)
            for m, r in rows.items():
                for k, v in r.items():
                    acc.setdefault(m, {}).setdefault(k, []).append(v)
            if args.figures is not None and seed == 0 and robot == args.robots[0]:
                figures(args.figures, res, data)
        table = {
            m: {k: math.sqrt(sum(x * x for x in v) / len(v)) for k, v in r.items()} for m, r in acc.items()
        }
        report[robot] = {"setup": SCENES[robot][2], "table": table, "seconds": times, "noise_ratio": chi}
        best = min((r["camera_mm"], m) for m, r in table.items() if m.startswith("OpenCV"))
        print(
            f"\n{robot} ({SCENES[robot][2]}), {args.seeds} seeds, {args.images} images, {args.noise} px: "
            f"RMS over seeds; diffkin {sum(times) / len(times):.1f} s a fit (contended), noise ratio "
            f"{sum(chi) / len(chi):.2f}"
        )
        print("| method | camera [mm] | camera [mrad] | held-out 3D [mm] | held-out reprojection [px] |")
        print("|---|---:|---:|---:|---:|")
        for m, r in table.items():
            print(
                f"| {m} | {r['camera_mm']:.3f} | {r['camera_mrad']:.3f} | {r['held_out_3d_mm']:.3f} | "
                f"{r['held_out_px']:.3f} |"
            )
        ours = table["diffkin calibrate_camera"]["camera_mm"]
        print(f"camera translation: OpenCV's best ({best[1]}) / diffkin = {best[0] / ours:.1f}x")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
