"""Synthetic camera-calibration scenes (issue 38): a chessboard seen by a camera, a robot with perturbed
geometry, OpenCV's hand-eye pipelines on the same pixels. Used by ``tests/test_calibrate_camera.py`` and
``benchmarks/bench_camera_calibration.py``.

Set-up: a Franka Panda (its URDF) with a 7 x 10-square chessboard (25 mm squares, 6 x 9 inner corners) on its
flange and a fixed camera 1.2 m away (eye-to-hand), and a UR5 (its URDF) with the camera on its flange over a
board on the table (eye-in-hand); 1000 px focal length, 1280 x 1024 px, OpenCV distortion; the pixels are
``cv2.projectPoints`` of the true board poses (plus Gaussian noise where asked). The true robot is the nominal
URDF with every parameter the images can identify perturbed by up to ±1 mm / ±0.1° (uniform); the others,
which the camera's and board's poses absorb, are a choice of frame and stay nominal in both. OpenCV's
pipeline: ``cv2.solvePnP`` per image, then ``calibrateHandEye`` (5 methods) and ``calibrateRobotWorldHandEye``
(2) with the nominal kinematics.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import torch

from diffkin.calibration.camera_api import _pnp
from diffkin.calibration.camera_model import CameraModel, camera_reports
from diffkin.calibration.error_models import build_model
from diffkin.calibration.handeye_refine import start_y
from diffkin.models import from_urdf
from diffkin.transforms import make_transform, transform_inverse

F64 = torch.float64
ROOT = Path(__file__).resolve().parents[1]
K = torch.tensor([[1000.0, 0, 640], [0, 1000.0, 512], [0, 0, 1]], dtype=F64)
DIST = torch.tensor([-0.1, 0.05, 1e-3, -5e-4, 0.0], dtype=F64)
W, H = 1280, 1024


def chessboard() -> torch.Tensor:
    """The 6 x 9 inner corners of a 7 x 10-square board of 25 mm squares, centred, z = 0: (54, 3)."""
    i, j = np.meshgrid(np.arange(9), np.arange(6))
    return torch.tensor(
        np.stack([(i.ravel() - 4) * 0.025, (j.ravel() - 2.5) * 0.025, 0 * i.ravel()], -1), dtype=F64
    )


def look_at(eye, target) -> torch.Tensor:
    eye, target = torch.tensor(eye, dtype=F64), torch.tensor(target, dtype=F64)
    z = (target - eye) / (target - eye).norm()
    x = torch.linalg.cross(torch.tensor([0.0, 0, 1], dtype=F64), z)
    x = x / x.norm()
    T = torch.eye(4, dtype=F64)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, torch.linalg.cross(z, x), z, eye
    return T


def cam_board(chain, q, cam, board, setup):
    with torch.no_grad():
        F = chain.forward_kinematics(q)
    if setup == "eye_to_hand":
        return transform_inverse(cam) @ F @ board
    return transform_inverse(cam) @ transform_inverse(F) @ board


def project(T, points):
    """cv2.projectPoints of ``points`` at each pose ``T (N, 4, 4)``: (N, M, 2)."""
    out = [
        cv2.projectPoints(
            points.numpy(), cv2.Rodrigues(t[:3, :3].numpy())[0], t[:3, 3].numpy(), K.numpy(), DIST.numpy()
        )[0][:, 0]
        for t in T
    ]
    return torch.tensor(np.array(out))


def in_view(T, points):
    """Postures whose board faces the camera with every corner in the image."""
    p = (T[:, None, :3, :3] @ points[None, :, :, None])[..., 0] + T[:, None, :3, 3]
    uv = p[..., :2] / p[..., 2:3] * 1000 + torch.tensor([640.0, 512.0], dtype=F64)
    inside = (uv[..., 0] > 20) & (uv[..., 0] < W - 20) & (uv[..., 1] > 20) & (uv[..., 1] < H - 20)
    return (T[:, 2, 2].abs() > 0.5) & (p[..., 2] > 0.2).all(-1) & inside.all(-1)


SCENES = {  # robot: (urdf, end link, setup, camera pose, board pose)
    "panda": (
        "diffkin/models/data/panda.urdf",
        "panda_link8",
        "eye_to_hand",
        look_at([1.4, 0.3, 0.6], [0.45, 0.0, 0.35]),
        make_transform(torch.eye(3, dtype=F64), torch.tensor([0.0, 0.0, 0.03], dtype=F64)),
    ),
    "ur5": (
        "diffkin/models/data/ur5.urdf",
        "tool0",
        "eye_in_hand",
        make_transform(torch.eye(3, dtype=F64), torch.tensor([0.0, 0.05, 0.04], dtype=F64)),
        make_transform(torch.eye(3, dtype=F64), torch.tensor([0.45, 0.25, 0.0], dtype=F64)),
    ),
}


def scene(robot: str, n_images: int, seed: int = 0):
    """(nominal, true chain, q (n_images, n), held-out q, camera, board, fixed names) of a scene."""
    path, end, setup, cam, board = SCENES[robot]
    nominal = from_urdf(ROOT / path, end, dtype=F64)
    pts = chessboard()
    g = torch.Generator().manual_seed(seed)
    if robot == "ur5":  # around a posture looking down at the table
        q0 = torch.tensor([0.5, -1.8, 1.6, -1.4, -1.57, 0.0], dtype=F64)
        q = q0 + 0.6 * (2 * torch.rand(3000, 6, generator=g, dtype=F64) - 1)
    else:
        q = nominal.random_configuration(3000, generator=g)
    q = q[in_view(cam_board(nominal, q, cam, board, setup), pts)]
    if q.shape[0] < n_images + 100:
        raise ValueError(f"only {q.shape[0]} postures see the board")
    model, _ = build_model(nominal)
    cm = CameraModel(
        model,
        setup,
        pts,
        cam,
        board,
        torch.cat((K[0, 0:1], K[1, 1:2], K[:2, 2], DIST)),
        ("robot", "camera", "board"),
    )
    vis = torch.ones(n_images, pts.shape[0], dtype=F64)
    (report,), _ = camera_reports(cm, cm.nominal[None], torch.cat((q[:n_images], vis), -1)[None])
    fixed = set(report.unidentifiable)
    g = torch.Generator().manual_seed(seed + 1)
    zeta = model.nominal.clone()
    length = model.is_length()
    for j in model.candidate.nonzero().flatten().tolist():
        if model.names[j] not in fixed:
            zeta[j] += (2 * float(torch.rand((), generator=g, dtype=F64)) - 1) * (
                1e-3 if length[j] else math.radians(0.1)
            )
    true = model.to_chains(zeta[None])[0]
    return nominal, true, q[:n_images], q[n_images : n_images + 100], cam, board, report


def images(true, q, cam, board, setup, noise=0.0, seed=2):
    uv = project(cam_board(true, q, cam, board, setup), chessboard())
    return uv + noise * torch.randn(uv.shape, generator=torch.Generator().manual_seed(seed), dtype=F64)


def points_3d(T, pts):
    return (T[:, None, :3, :3] @ pts[None, :, :, None])[..., 0] + T[:, None, :3, 3]


def held_out_3d(chain, cam, board, true, cam_true, board_true, q, setup) -> float:
    """RMS distance (m) of the board's corners in the camera frame, model against truth, at postures ``q``."""
    pts = chessboard()
    a = points_3d(cam_board(chain, q, cam, board, setup), pts)
    b = points_3d(cam_board(true, q, cam_true, board_true, setup), pts)
    return float((a - b).norm(dim=-1).square().mean().sqrt())


def opencv_pipelines(nominal, q, uv, setup):
    """{method: (camera_pose, board_pose)} of OpenCV's seven closed forms on solvePnP poses, nominal FK."""
    C, ok = _pnp(uv, chessboard(), torch.ones(uv.shape[:2], dtype=torch.bool), K, DIST)
    assert bool(ok.all())
    with torch.no_grad():
        G = nominal.forward_kinematics(q)
    Gl = G if setup == "eye_in_hand" else transform_inverse(G)  # the loop G_l X C = Y
    args = ([a[:3, :3].numpy() for a in C], [a[:3, 3:].numpy() for a in C])
    out = {}

    def mat(R, t):
        T = torch.eye(4, dtype=F64)
        T[:3, :3], T[:3, 3] = torch.tensor(R), torch.tensor(t).reshape(3)
        return T

    for m in ("PARK", "TSAI", "HORAUD", "ANDREFF", "DANIILIDIS"):
        R, t = cv2.calibrateHandEye(
            [a[:3, :3].numpy() for a in Gl],
            [a[:3, 3:].numpy() for a in Gl],
            *args,
            method=getattr(cv2, f"CALIB_HAND_EYE_{m}"),
        )
        X = mat(R, t)
        out[m.lower()] = (X, start_y(Gl, C, X))
    Gi = transform_inverse(Gl)
    for m in ("SHAH", "LI"):
        Rb, tb, Rg, tg = cv2.calibrateRobotWorldHandEye(
            *args,
            [a[:3, :3].numpy() for a in Gi],
            [a[:3, 3:].numpy() for a in Gi],
            method=getattr(cv2, f"CALIB_ROBOT_WORLD_HAND_EYE_{m}"),
        )
        out[m.lower()] = (transform_inverse(mat(Rg, tg)), transform_inverse(mat(Rb, tb)))
    return out
