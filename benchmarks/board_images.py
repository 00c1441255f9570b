"""Rendered chessboard images (issue 38, step 3): the board of ``benchmarks/camera_scenes.py`` drawn through
the true camera projection of each posture, for the end-to-end test of ``detect_board`` ->
``calibrate_camera`` (``tests/test_board_detection.py``) and ``diffkin calibrate --images``.

Each image: a flat chessboard texture (dark square outside the first corner, a white margin of one square)
warped by the homography K [r1 r2 t] of the board's true pose in the camera (``cv2.warpPerspective``), then
OpenCV's lens distortion applied by ``cv2.remap`` through ``cv2.undistortPointsIter`` of every pixel (so
the pixel a corner lands on is ``cv2.projectPoints`` of it), a Gaussian blur and Gaussian pixel noise, on a
mid-grey background.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from diffkin.calibration.board import board_points, charuco_board

from .camera_scenes import DIST, F64, H, K, W, cam_board, chessboard, scene

ROWS, COLS, SQUARE = 6, 9, 0.025  # the scenes' board: 6 x 9 inner corners, 25 mm squares
PPS = 48  # texture pixels per square
# the scenes' board frame (chessboard(): centred) from detect_board's (the first corner at the origin)
OFFSET = torch.eye(4, dtype=F64)
OFFSET[:3, 3] = chessboard()[0]


def texture(rows: int = ROWS, cols: int = COLS) -> np.ndarray:
    """(rows + 3, cols + 3) squares of PPS px: the (rows + 1) x (cols + 1) board in a one-square margin."""
    j, i = np.mgrid[0 : (rows + 3) * PPS, 0 : (cols + 3) * PPS] // PPS
    dark = ((i - 1 + j - 1) % 2 == 0) & (i >= 1) & (i <= cols + 1) & (j >= 1) & (j <= rows + 1)
    return np.where(dark, 30, 225).astype(np.uint8)


def small_camera(scale: float = 0.5) -> tuple[torch.Tensor, tuple[int, int]]:
    """The scenes' camera matrix at ``scale`` of its resolution (a faster image): ``(K (3, 3), (W, H))``."""
    Ks = K.clone()
    Ks[:2] *= scale
    return Ks, (round(W * scale), round(H * scale))


def _distortion_map(Kc, size):
    w, h = size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack((u.ravel(), v.ravel()), -1)[:, None]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)
    ideal = cv2.undistortPoints(pts, Kc, DIST.numpy(), R=None, P=Kc, criteria=crit)[:, 0]
    return ideal[:, 0].reshape(h, w).astype(np.float32), ideal[:, 1].reshape(h, w).astype(np.float32)


def _texture_to_board(origin_px: float, pps: int = PPS) -> np.ndarray:
    """(3, 3): texture pixel (x, y) -> board plane (X, Y), the board's origin at texture (origin_px,
    origin_px) (pixel centres at integers, ``pps`` pixels a square)."""
    s = SQUARE / pps
    return np.array([[s, 0, -origin_px * s], [0, s, -origin_px * s], [0, 0, 1]])


def charuco_texture(marker: float = 0.018, dictionary: str = "DICT_5X5_100"):
    """OpenCV's own picture of the ChArUco board of ROWS x COLS inner corners (``board.generateImage``, 2 PPS
    px a square: OpenCV 5.1 refuses some sizes, e.g. 48 px squares of this board), in a one-square white
    margin: ``(texture, A (3, 3) texture pixel -> board plane of detect_board(marker=...), i.e. OpenCV's
    board frame)``."""
    board = charuco_board(ROWS, COLS, SQUARE, marker, dictionary)
    pps = 2 * PPS
    tex = np.pad(board.generateImage(((COLS + 1) * pps, (ROWS + 1) * pps), marginSize=0), pps,
                 constant_values=255)
    return tex, _texture_to_board(pps - 0.5, pps)  # the board's outer corner at the margin's inner edge


def render(T_cam_board: torch.Tensor, camera_matrix: torch.Tensor = K, size=(W, H), noise: float = 2.0,
           blur: float = 0.8, seed: int = 0, distortion: bool = True, tex=None) -> list[np.ndarray]:
    """uint8 grey images ``(H, W)`` of the board at each pose ``T_cam_board (N, 4, 4)`` (detect_board's
    board frame: the first corner at the origin) seen by ``camera_matrix`` (default the scenes' K) with the
    scenes' DIST; ``size`` (W, H) px; ``noise`` grey levels σ; ``blur`` px σ; ``tex``: ``(texture, A)`` of
    another board (:func:`charuco_texture`), default the chessboard of :func:`texture`."""
    Kc = camera_matrix.numpy()
    # the chessboard's first corner (c, r) = (0, 0) at texture (2 PPS - 0.5, 2 PPS - 0.5)
    tex, A = (texture(), _texture_to_board(2 * PPS - 0.5)) if tex is None else tex
    maps = _distortion_map(Kc, size) if distortion else None
    rng = np.random.default_rng(seed)
    out = []
    for T in T_cam_board.numpy():  # one picture at a time (OpenCV's warp)
        Hb = Kc @ np.stack((T[:3, 0], T[:3, 1], T[:3, 3]), -1)  # board plane -> ideal pixels
        img = cv2.warpPerspective(tex, Hb @ A, size, flags=cv2.INTER_LINEAR, borderValue=128)
        if maps is not None:
            img = cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR, borderValue=128)
        img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), blur) if blur else img.astype(np.float32)
        img = img + rng.normal(0.0, noise, img.shape)
        out.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
    return out


def rendered_scene(n_images: int, n_out: int = 50, seed: int = 0):
    """The Panda eye-to-hand scene with postures whose printed side faces the camera: ``(nominal, true,
    q (n_images, 7), q_out, camera pose, board pose (detect_board's frame), T_cam_board)``."""
    nominal, true, q, q_out, cam, board, _ = scene("panda", 30, seed)
    q_all = torch.cat((q, q_out))
    board = board @ OFFSET
    T = cam_board(true, q_all, cam, board, "eye_to_hand")
    facing = T[:, 2, 2] > 0.5  # the board's z points away from the camera: its printed side is seen
    q_all, T = q_all[facing], T[facing]
    if q_all.shape[0] < n_images + n_out:
        raise ValueError(f"only {q_all.shape[0]} postures face the camera")
    return nominal, true, q_all[:n_images], q_all[n_images : n_images + n_out], cam, board, T[:n_images]


def true_pixels(T_cam_board: torch.Tensor, camera_matrix: torch.Tensor = K) -> torch.Tensor:
    """cv2.projectPoints of detect_board's board points at each pose: (N, M, 2)."""
    pts = board_points(ROWS, COLS, SQUARE).numpy()
    Kc, dist = camera_matrix.numpy(), DIST.numpy()
    return torch.tensor(np.array([
        cv2.projectPoints(pts, cv2.Rodrigues(t[:3, :3])[0], t[:3, 3], Kc, dist)[0][:, 0]
        for t in T_cam_board.numpy()]))
