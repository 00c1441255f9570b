"""File entry of camera calibration (for ``diffkin calibrate --images DIR --joints FILE``): a folder of
board pictures and the joint readings taken with them -> :func:`detect_board` -> :func:`calibrate_camera`."""

from __future__ import annotations

import csv
from pathlib import Path
from urllib.parse import quote

import numpy as np
import torch
from torch import Tensor

from ..errors import DiffkinError, MissingExtraError, ShapeError, require
from ..io.data.formats import _is_number
from .board import BoardDetection, detect_board, image_files
from .camera_api import calibrate_camera
from .camera_result import CameraCalibrationResult
from .io import write_robot

__all__ = ["load_joint_readings", "calibrate_camera_from_files", "write_camera_report"]


def load_joint_readings(path: str | Path, images: list[str], n_joints: int,
                        dtype: torch.dtype = torch.float64) -> Tensor:
    """The joint readings ``(N, n)`` of the N pictures named ``images`` (file names, sorted), from
    ``path``: a ``.csv`` with one row per picture — with a header, an ``image`` column (file names) puts the
    rows in the pictures' order, the joint columns are ``q1..qn`` when so named, else every other column;
    without one, n numbers a row in the pictures' order — or ``.npy`` (N, n) / ``.npz`` key ``q`` in the
    pictures' order. Radians (metres for prismatic joints)."""
    p = Path(path)
    if not p.is_file():
        raise DiffkinError(f"{p}: no such joint-readings file")
    names = None
    if p.suffix.lower() == ".csv":
        with p.open(newline="") as f:
            rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
        if not rows:
            raise DiffkinError(f"{p}: empty")
        header = None if all(_is_number(c) for c in rows[0]) else [c.strip().lower() for c in rows[0]]
        body = rows[1:] if header else rows
        cols = list(range(len(rows[0])))
        if header:
            if "image" in header:
                k = header.index("image")
                names = [r[k].strip() for r in body]
                cols.remove(k)
            wanted = [f"q{i + 1}" for i in range(n_joints)]
            if all(w in header for w in wanted):
                cols = [header.index(w) for w in wanted]
        try:
            q = np.array([[float(r[c]) for c in cols] for r in body], dtype=np.float64)
        except (ValueError, IndexError) as exc:
            raise DiffkinError(f"{p}: a row that is not {len(cols)} numbers ({exc})") from None
    elif p.suffix.lower() in (".npy", ".npz"):
        q = np.load(p)
        if p.suffix.lower() == ".npz":
            if "q" not in q:
                raise DiffkinError(f"{p}: holds no array 'q' (has {', '.join(q.files)})")
            q = q["q"]
        q = np.asarray(q, dtype=np.float64)
    else:
        raise DiffkinError(f"{p}: expected joint readings as .csv, .npy or .npz")
    if q.ndim != 2 or q.shape[1] != n_joints:
        raise ShapeError(f"{p}: expected joint readings (N, {n_joints}) for this robot's {n_joints} joints, "
                         f"got {tuple(q.shape)}")
    if names is not None:
        where = {n: i for i, n in enumerate(names)}
        missing = [n for n in images if n not in where]
        if missing:
            raise DiffkinError(f"{p}: no joint reading for the picture(s) {', '.join(missing[:5])}")
        q = q[[where[n] for n in images]]
    elif q.shape[0] != len(images):
        raise ShapeError(f"{p}: {q.shape[0]} joint readings for {len(images)} pictures (one row a picture, "
                         "in the order of their sorted file names, or name them in an 'image' column)")
    if not np.isfinite(q).all():
        raise DiffkinError(f"{p}: holds NaN or inf")
    return torch.tensor(q, dtype=dtype)


def calibrate_camera_from_files(
    chain,
    images: str | Path,
    joints: str | Path,
    *,
    board: tuple[int, int],
    square: float,
    camera_matrix: Tensor,
    detector: str = "classic",
    marker: float | None = None,
    dictionary: str = "DICT_5X5_100",
    **options,
) -> tuple[CameraCalibrationResult, BoardDetection]:
    """:func:`calibrate_camera` on the pictures of the folder ``images`` (sorted by name) and the joint
    readings of ``joints`` (:func:`load_joint_readings`): corners by :func:`detect_board` (``board``,
    ``square``, ``detector``; a ChArUco board with ``marker`` and ``dictionary``), pictures where the
    board is not found masked out; ``options`` go to
    :func:`calibrate_camera`. Returns ``(result, detections)``."""
    files = image_files(images)
    q = load_joint_readings(joints, [f.name for f in files], chain.n_joints, chain.dtype)
    det = detect_board(files, board, square, dtype=chain.dtype, device=chain.device, detector=detector,
                       marker=marker, dictionary=dictionary)
    if int(det.found.sum()) < 3:
        raise DiffkinError(f"{images}: the board ({board[0]} x {board[1]} inner corners) was found in only "
                           f"{int(det.found.sum())} of {len(files)} pictures; at least 3 are needed")
    res = calibrate_camera(chain, q.to(chain.device), det.image_points, det.board_points,
                           camera_matrix=camera_matrix, visible=det.visible, **options)
    return res, det


def _picture(cv2, image):
    """An image file (RGB array) or array as given; None when it cannot be read (a blank canvas then)."""
    if not isinstance(image, (str, Path)):
        return image
    img = cv2.imread(str(image), cv2.IMREAD_COLOR)
    return None if img is None else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def write_camera_report(result: CameraCalibrationResult, detections: BoardDetection, out_dir: str | Path,
                        robot: bool = True, images=None) -> list[Path]:
    """Write into ``out_dir``: the calibrated robot (``calibrated.yaml|urdf|xml``, unless ``robot`` is
    False), ``camera.yaml`` (:meth:`CameraCalibrationResult.to_yaml`), ``camera_joint.urdf`` (the camera
    as a fixed URDF joint), ``report.md`` (summary, parameters, the pictures' detections and reprojection
    RMS before / after) and, with matplotlib, ``residuals.png`` and per picture where the board was found
    ``residuals/<picture stem>.png`` (:meth:`CameraCalibrationResult.plot_image_residuals`, linked from
    the report's table), drawn over the picture when ``images`` (the folder, or the files or arrays in
    the detections' order; arrays in RGB) is given and OpenCV can read it, else on a blank canvas.
    Returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    try:
        require("matplotlib.figure", "plot", "the camera calibration report's figures")
        plots = True
    except MissingExtraError:  # no matplotlib: the report without its figures
        plots = False
    if images is not None and not isinstance(images, (list, tuple)):
        images = image_files(images)
    if images is not None and len(images) != len(detections.names):
        raise ShapeError(f"expected {len(detections.names)} pictures (one per detection), got {len(images)}")
    try:
        cv2 = require("cv2", "camera", "reading the pictures for the report") if images is not None else None
    except MissingExtraError:
        cv2 = images = None
    stems = [Path(n).stem for n in detections.names]
    figures = {}
    if plots:
        for i, name in enumerate(detections.names):
            if bool(detections.found[i]):
                pic = None if images is None else _picture(cv2, images[i])
                figures[i] = result.plot_image_residuals(i, out / "residuals" / f"{stems[i]}.png", pic,
                                                         title=f"{name}: reprojection before / after")
    written = [write_robot(result.chain, out)] if robot else []
    written.append(out / "camera.yaml")
    result.to_yaml(written[-1])
    written.append(out / "camera_joint.urdf")
    written[-1].write_text(result.camera_joint_urdf() + "\n")
    lines = ["# Camera calibration", "", "```", result.summary(), "```", "", result.to_markdown(), "",
             f"## Pictures (board found in {int(detections.found.sum())} of {len(detections.names)})", "",
             "| picture | board found | RMS before [px] | RMS after [px] | residuals |",
             "|---|---|---|---|---|"]
    for i, name in enumerate(detections.names):
        if bool(detections.found[i]):
            link = f"[{stems[i]}.png](residuals/{quote(stems[i])}.png)" if i in figures else ""
            lines.append(f"| {name} | yes | {float(result.initial_image_rms[i]):.4f} | "
                         f"{float(result.image_rms[i]):.4f} | {link} |")
        else:
            lines.append(f"| {name} | no | | | |")
    written.append(out / "report.md")
    written[-1].write_text("\n".join(lines) + "\n")
    if plots:
        written.append(result.plot_residuals(out / "residuals.png"))
        written += list(figures.values())
    return written
