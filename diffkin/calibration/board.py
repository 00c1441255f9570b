"""Chessboard corners from images (OpenCV, the ``camera`` extra): the pixels and the board's points that
:func:`~diffkin.calibration.calibrate_camera` takes, in the same corner order.

The board: ``rows x cols`` inner corners (``(rows + 1) x (cols + 1)`` squares of side ``square`` metres).
Its frame: the first corner at the origin, x along a row (``cols`` corners), y from row to row, z = 0 on the
board and pointing away from the side printed; corner k = r * cols + c is at (c * square, r * square, 0).
The first corner is the one whose outer diagonal square is **dark**. That fixes the order in every image
only when one of ``rows``, ``cols`` is even and the other odd (a board of (odd x even) squares, as OpenCV's
``pattern.png``, 9 x 6 inner corners): boards with both even or both odd are symmetric under a half turn and
are refused (their corner order could flip from image to image and corrupt the calibration).

``cv2.findChessboardCorners`` finds the corners, ``cv2.cornerSubPix`` refines them; the order OpenCV returns
is then made the one above: mirrored orders (row direction x column direction pointing out of the board) are
reversed along the rows, and a half turn is undone by comparing the brightness of the two outer corner
squares (through the homography of the detected grid).

A **ChArUco** board (``marker=`` the ArUco markers' side; OpenCV's ``cv2.aruco.CharucoBoard`` of
``(cols + 1) x (rows + 1)`` squares and ``dictionary``) names every corner by the markers around it, so any
corner counts work, a half turn cannot confuse the order, and a partial view (the board cut by the image's
edge, hidden behind the gripper) still gives the corners it shows: ``visible`` marks them.
``cv2.aruco.CharucoDetector`` finds them (with its sub-pixel refinement), and the board's points are
OpenCV's (``board.getChessboardCorners()``: the board's outer corner at the origin, corner id
k = r * cols + c at ((c + 1) * square, (r + 1) * square, 0)), so ``board.generateImage`` prints the board the
points describe.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor

from ..errors import DiffkinError, OptionError, ShapeError, require
from ..validation import check_number

__all__ = ["BoardDetection", "detect_board", "charuco_board", "image_files", "IMAGE_SUFFIXES", "DETECTORS"]

DETECTORS = ("classic", "sb")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


class BoardDetection(NamedTuple):
    """The result of :func:`detect_board`: unpack as ``image_points, visible, board_points, names``."""

    image_points: Tensor  #: (N, M, 2) pixels (u, v); NaN in images where the board was not found
    visible: Tensor  #: (N, M) bool: the corners found (a whole image's row False where not found)
    board_points: Tensor  #: (M, 3) the corners in the board's frame, metres
    names: list[str]  #: one name per image (the file name; ``image_i`` for arrays)

    @property
    def found(self) -> Tensor:
        """(N,) bool: the images where the board (a ChArUco board: some of its corners) was found."""
        return self.visible.any(-1)

    @property
    def detection_rate(self) -> float:
        """The fraction of images where the board was found."""
        return float(self.found.double().mean()) if len(self.names) else 0.0


def board_points(rows: int, cols: int, square: float, dtype=torch.float64, device=None) -> Tensor:
    """``(rows * cols, 3)`` corners of the board: corner r * cols + c at (c * square, r * square, 0)."""
    r, c = torch.meshgrid(torch.arange(rows, device=device), torch.arange(cols, device=device), indexing="ij")
    p = torch.stack((c.reshape(-1), r.reshape(-1), torch.zeros_like(r.reshape(-1))), -1)
    return p.to(dtype=dtype) * square


def charuco_board(rows: int, cols: int, square: float, marker: float, dictionary: str = "DICT_5X5_100"):
    """OpenCV's ``cv2.aruco.CharucoBoard`` with ``rows x cols`` inner corners (``(cols + 1) x (rows + 1)``
    squares of ``square`` metres, markers of ``marker`` metres from the predefined ``dictionary``): the
    board :func:`detect_board` looks for with ``marker=``; ``.generateImage(size)`` draws it to print."""
    cv2 = require("cv2", "camera", "ChArUco boards")
    if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "CharucoDetector"):
        raise DiffkinError("ChArUco boards need OpenCV >= 4.7 (cv2.aruco.CharucoDetector); this is "
                           f"{cv2.__version__}")
    names = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
    if dictionary not in names:
        raise OptionError(f"unknown ArUco dictionary {dictionary!r}; valid: {', '.join(names)}")
    if not marker < square:
        raise OptionError(f"the markers ({marker} m) must be smaller than the squares ({square} m)")
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    if d.bytesList.shape[0] < (rows + 1) * (cols + 1) // 2:
        raise OptionError(f"dictionary {dictionary} holds {d.bytesList.shape[0]} markers; a board of "
                          f"{(cols + 1)} x {(rows + 1)} squares needs {(rows + 1) * (cols + 1) // 2}")
    return cv2.aruco.CharucoBoard((cols + 1, rows + 1), square, marker, d)


def image_files(directory: str | Path) -> list[Path]:
    """The image files of ``directory`` (by suffix, :data:`IMAGE_SUFFIXES`), sorted by name."""
    d = Path(directory)
    if not d.is_dir():
        raise DiffkinError(f"{d}: not a directory of images")
    files = sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise DiffkinError(f"{d}: holds no image ({', '.join(IMAGE_SUFFIXES)})")
    return files


def _gray(cv2, image, name: str):
    import numpy as np

    if isinstance(image, (str, Path)):
        img = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise DiffkinError(f"{image}: not a readable image")
        return img
    img = image.detach().cpu().numpy() if isinstance(image, Tensor) else np.asarray(image)
    if img.ndim == 3 and img.shape[-1] in (3, 4):
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_BGR2GRAY)
    if img.ndim != 2:
        raise ShapeError(f"expected image {name} of shape (H, W) or (H, W, 3), got {tuple(img.shape)}")
    if img.dtype != np.uint8:
        if img.dtype.kind == "f" and img.max() <= 1.0:
            img = img * 255.0
        img = np.clip(img, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def _canonical(cv2, img, corners, rows: int, cols: int):
    """OpenCV's corners (rows * cols, 2) in the board's order: right-handed, dark outer square first."""
    import numpy as np

    g = corners.reshape(rows, cols, 2)
    a, b = g[0, min(1, cols - 1)] - g[0, 0], g[min(1, rows - 1), 0] - g[0, 0]
    if a[0] * b[1] - a[1] * b[0] < 0:  # mirrored: x cross y would point at the camera
        g = g[:, ::-1]
    grid = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), -1).reshape(-1, 2).astype(np.float64)
    H, _ = cv2.findHomography(grid, g.reshape(-1, 2).astype(np.float64))
    if H is None:
        return g.reshape(-1, 2)

    def brightness(x, y):  # mean intensity over the middle of the square centred at grid (x, y)
        off = np.stack(np.meshgrid(np.linspace(-0.25, 0.25, 5), np.linspace(-0.25, 0.25, 5)), -1)
        pts = (off.reshape(-1, 2) + [x, y])[None].astype(np.float64)
        uv = cv2.perspectiveTransform(pts, H)[0]
        u = np.clip(np.round(uv[:, 0]).astype(int), 0, img.shape[1] - 1)
        v = np.clip(np.round(uv[:, 1]).astype(int), 0, img.shape[0] - 1)
        return float(img[v, u].mean())

    if brightness(-0.5, -0.5) > brightness(cols - 0.5, rows - 0.5):  # half turn
        g = g[::-1, ::-1]
    return np.ascontiguousarray(g).reshape(-1, 2)


def detect_board(
    images: str | Path | Sequence,
    board: tuple[int, int],
    square: float,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
    subpix_window: int = 5,
    detector: str = "classic",
    marker: float | None = None,
    dictionary: str = "DICT_5X5_100",
) -> BoardDetection:
    """Chessboard or ChArUco corners in images, for :func:`~diffkin.calibration.calibrate_camera`.

    Args:
        images: a directory (its image files sorted by name, :func:`image_files`), or a sequence of image
            files or of arrays ``(H, W)`` / ``(H, W, 3)`` (BGR, as ``cv2.imread``; uint8 or floats in
            [0, 1] / [0, 255]).
        board: ``(rows, cols)`` inner corners; a chessboard's one even and one odd (the order is then
            unique, see the module's docstring), a ChArUco board's any.
        square: the squares' side in metres.
        dtype, device: of the returned tensors.
        subpix_window: half side (px) of ``cv2.cornerSubPix``'s search window (at most 0.4 of the
            smallest corner spacing in the image).
        detector: ``"classic"`` (``cv2.findChessboardCorners`` + ``cv2.cornerSubPix``, default) or
            ``"sb"`` (``cv2.findChessboardCornersSB``, OpenCV's sector-based detector: finds boards in
            smaller and more oblique views; then ``cv2.cornerSubPix`` as well). Chessboards only.
        marker: a ChArUco board (:func:`charuco_board`): its markers' side in metres; None: a chessboard.
        dictionary: the ChArUco board's ArUco dictionary (a ``cv2.aruco.DICT_*`` name).

    Returns:
        :class:`BoardDetection` ``(image_points (N, M, 2), visible (N, M), board_points (M, 3), names)``
        with M = rows * cols: NaN pixels and ``visible`` False where a corner was not found (a
        chessboard: the whole image's; a ChArUco board: each corner not seen; pass both to
        ``calibrate_camera``); ``.found`` (N,) and ``.detection_rate``.

    Raises:
        MissingExtraError: OpenCV is not installed (``pip install 'diffkin[camera]'``).
        OptionError: a chessboard of two even or two odd corner counts, fewer than 2 corners a side, a
            ChArUco marker not smaller than the squares, an unknown or too small dictionary, ``detector``
            with ``marker``.
        DiffkinError, ShapeError: no images, an unreadable file, an array of another shape.
    """
    cv2 = require("cv2", "camera", "detect_board (chessboard corners from images)")
    import numpy as np

    try:
        rows, cols = (int(n) for n in board)
    except (TypeError, ValueError):
        raise OptionError(f"expected board=(rows, cols) inner corners, got {board!r}") from None
    if rows < 2 or cols < 2:
        raise OptionError(f"expected board=(rows, cols) with at least 2 inner corners a side, got {board!r}")
    if marker is not None:
        return _detect_charuco(cv2, images, rows, cols, check_number(square, "square", unit=" (metres)"),
                               check_number(marker, "marker", unit=" (metres)"), dictionary, detector, dtype,
                               device)
    if (rows + cols) % 2 == 0:
        raise OptionError(
            f"board=({rows}, {cols}) is symmetric under a half turn (both counts even or both odd), so the "
            "corner order cannot be fixed from image to image; use a board with one even and one odd count "
            "of inner corners (e.g. (6, 9))"
        )
    square = check_number(square, "square", unit=" (metres)")
    if detector not in DETECTORS:
        raise OptionError(f"unknown detector {detector!r}; valid: {', '.join(DETECTORS)}")
    images, names = _image_list(images)
    M = rows * cols
    uv = np.full((len(images), M, 2), np.nan)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    for i, im in enumerate(images):  # OpenCV's detector, one image at a time
        img = _gray(cv2, im, names[i])
        if detector == "sb":
            ok, corners = cv2.findChessboardCornersSB(img, (cols, rows), flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        else:
            ok, corners = cv2.findChessboardCorners(img, (cols, rows), flags=flags)
        if not ok or corners is None or len(corners) != M:
            continue
        # the search window stays inside one square (small boards in the image: a few pixels a square)
        d = np.linalg.norm(np.diff(corners.reshape(rows, cols, 2), axis=1), axis=-1).min()
        w = max(1, min(int(subpix_window), int(0.4 * d)))
        corners = cv2.cornerSubPix(img, corners.astype(np.float32), (w, w), (-1, -1), crit)
        uv[i] = _canonical(cv2, img, corners.reshape(-1, 2).astype(np.float64), rows, cols)
    pixels = torch.tensor(uv, dtype=dtype, device=device)
    visible = torch.isfinite(pixels).all(-1)
    return BoardDetection(pixels, visible, board_points(rows, cols, square, dtype, device), names)


def _image_list(images) -> tuple[list, list[str]]:
    """The images of a directory or sequence, and their names (file names; ``image_i`` for arrays)."""
    if isinstance(images, (str, Path)):
        images = image_files(images)
    images = list(images)
    if not images:
        raise DiffkinError("detect_board: no images given")
    names = [Path(im).name if isinstance(im, (str, Path)) else f"image_{i}" for i, im in enumerate(images)]
    return images, names


def _detect_charuco(cv2, images, rows: int, cols: int, square: float, marker: float, dictionary: str,
                    detector: str, dtype, device) -> BoardDetection:
    """:func:`detect_board` of a ChArUco board: each corner where OpenCV's CharucoDetector finds it."""
    import numpy as np

    if detector != "classic":
        raise OptionError(f"detector={detector!r} is for chessboards; a ChArUco board is found by its "
                          "markers")
    board = charuco_board(rows, cols, square, marker, dictionary)
    find = cv2.aruco.CharucoDetector(board)
    images, names = _image_list(images)
    uv = np.full((len(images), rows * cols, 2), np.nan)
    for i, im in enumerate(images):  # OpenCV's detector, one image at a time
        corners, ids, _, _ = find.detectBoard(_gray(cv2, im, names[i]))
        if ids is not None and len(ids):
            uv[i, ids.reshape(-1)] = corners.reshape(-1, 2)
    pixels = torch.tensor(uv, dtype=dtype, device=device)
    # OpenCV's board.getChessboardCorners(), but exact (OpenCV keeps them in float32)
    points = board_points(rows, cols, square, dtype, device)
    points[:, :2] += square
    return BoardDetection(pixels, torch.isfinite(pixels).all(-1), points, names)
