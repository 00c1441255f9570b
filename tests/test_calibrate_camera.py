"""calibrate_camera (issue 38 step 2): the robot's geometry, the camera's and the board's poses from
pixels of a chessboard, against the known truth of synthetic images and beside OpenCV's hand-eye pipelines.

Set-up: a Franka Panda (its URDF) with a 7 x 10-square chessboard (25 mm squares, 6 x 9 inner corners) on its
flange and a fixed camera 1.2 m away (eye-to-hand), and a UR5 (its URDF) with the camera on its flange over a
board on the table (eye-in-hand); 1000 px focal length, OpenCV distortion; the pixels are
``cv2.projectPoints`` of the true board poses, with 0.3 px Gaussian noise where stated. The true robot is
the nominal URDF with every parameter the images can identify perturbed by up to ±1 mm / ±0.1° (the
others, which the camera's and board's poses absorb, are a choice of frame: kept nominal in both). OpenCV's
pipeline: ``cv2.solvePnP`` per image, then ``calibrateHandEye`` (5 methods) and
``calibrateRobotWorldHandEye`` (2) with the nominal kinematics.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin.calibration import DegenerateMotionError, calibrate_camera
from diffkin.calibration.camera_api import _pnp, initial_poses
from diffkin.calibration.camera_model import CameraModel, camera_reports
from diffkin.calibration.error_models import build_model
from diffkin.calibration.handeye_refine import start_y
from diffkin.errors import ConventionError, NonFiniteError, OptionError, ShapeError
from diffkin.models import from_urdf
from diffkin.transforms import make_transform, transform_inverse

cv2 = pytest.importorskip("cv2")

F64 = torch.float64
ROOT = Path(__file__).resolve().parents[1]
K = torch.tensor([[1000.0, 0, 640], [0, 1000.0, 512], [0, 0, 1]], dtype=F64)
DIST = torch.tensor([-0.1, 0.05, 1e-3, -5e-4, 0.0], dtype=F64)
W, H = 1280, 1024


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


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
    assert q.shape[0] >= n_images + 100
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


# ------------------------------------------------------------------------------------------------- tests
def test_eye_to_hand_panda_beside_opencv():
    """0.3 px noise, 40 images, 10 % of the corners undetected: fit at the noise floor (χ ≈ 1, RMS ≈ √2 σ,
    held-out images as good), the camera ≥ 5x closer than OpenCV's best method, the board's corners at
    held-out postures ≥ 3x closer; what the images cannot separate is fixed and named."""
    nominal, true, q, q_out, cam, board, _ = scene("panda", 40)
    sigma = 0.3
    uv = images(true, q, cam, board, "eye_to_hand", sigma)
    vis = torch.rand(uv.shape[:2], generator=torch.Generator().manual_seed(3)) > 0.1
    uv_masked = torch.where(vis[..., None], uv, torch.full_like(uv, math.nan))  # undetected: NaN
    res = calibrate_camera(
        nominal,
        q,
        uv_masked,
        chessboard(),
        camera_matrix=K,
        dist_coeffs=DIST,
        visible=vis,
        measurement_noise=sigma,
        cross_validation=4,
        progress=False,
    )
    assert res.converged and res.setup == "eye_to_hand" and res.error_model == "general"
    assert 0.85 < res.noise_ratio < 1.15
    assert abs(res.reprojection_rms / (math.sqrt(2) * sigma) - 1) < 0.1
    assert res.initial_reprojection_rms > 1.5 * res.reprojection_rms
    assert res.cross_validation["reprojection_rms"] < 1.2 * math.sqrt(2) * sigma
    assert len(res.outliers) < 0.01 * int(vis.sum())
    # the first joint's origin is the camera's pose, the frames after the last joint are the board's
    rep = res.report
    assert {f"panda_joint1.{c}" for c in ("dx", "dy", "dz", "rx", "ry", "rz")} <= set(rep.unidentifiable)
    assert "camera_" in rep.reasons["panda_joint1.dz"] and "board_" in rep.reasons["panda_joint8.dx"]
    assert rep.rank == 4 * nominal.n_joints + 6 and not rep.undetermined
    # against the truth and OpenCV
    cam_err = float((res.camera_pose[:3, 3] - cam[:3, 3]).norm())
    ours_3d = held_out_3d(res.chain, res.camera_pose, res.board_pose, true, cam, board, q_out, "eye_to_hand")
    cv = opencv_pipelines(nominal, q, uv, "eye_to_hand")
    cv_cam = min(float((X[:3, 3] - cam[:3, 3]).norm()) for X, _ in cv.values())
    cv_3d = min(held_out_3d(nominal, X, Y, true, cam, board, q_out, "eye_to_hand") for X, Y in cv.values())
    assert cam_err < 0.5e-3 and 5 * cam_err < cv_cam, (cam_err, cv_cam)
    assert 3 * ours_3d < cv_3d, (ours_3d, cv_3d)


def test_eye_in_hand_ur5_noise_free_is_exact(tmp_path):
    """Noise-free pixels: the camera and board poses and the robot's loop recovered to rounding, from a
    start given by robot_world_hand_eye on solvePnP poses; the calibrated URDF loads back."""
    nominal, true, q, q_out, cam, board, _ = scene("ur5", 30)
    uv = images(true, q, cam, board, "eye_in_hand")
    res = calibrate_camera(
        nominal,
        q,
        uv,
        chessboard(),
        camera_matrix=K,
        dist_coeffs=DIST,
        setup="eye_in_hand",
        cross_validation=0,
        progress=False,
    )
    assert res.converged and res.reprojection_rms < 1e-7
    assert (res.camera_pose - cam).abs().max() < 1e-9 and (res.board_pose - board).abs().max() < 1e-9
    assert (
        held_out_3d(res.chain, res.camera_pose, res.board_pose, true, cam, board, q_out, "eye_in_hand") < 1e-9
    )
    assert {f"shoulder_pan_joint.{c}" for c in ("dx", "dy", "dz", "rx", "ry", "rz")} <= set(
        res.report.unidentifiable
    )
    path = tmp_path / "ur5_cam.urdf"
    res.chain.to_urdf(path)
    again = from_urdf(path, "tool0", dtype=F64)
    with torch.no_grad():
        assert (again.forward_kinematics(q_out) - res.chain.forward_kinematics(q_out)).abs().max() < 1e-12
    assert 'type="fixed"' in res.camera_joint_urdf() and "camera_pose" in res.to_yaml(tmp_path / "cam.yaml")


def test_initial_poses_are_opencv_robot_world_on_the_loop():
    """initial_poses (Shah's closed form) equals OpenCV's calibrateRobotWorldHandEye, both setups."""
    for robot in ("panda", "ur5"):
        nominal, _, q, _, cam, board, _ = scene(robot, 12)
        setup = SCENES[robot][2]
        uv = images(nominal, q, cam, board, setup)
        C, _ = _pnp(uv, chessboard(), torch.ones(uv.shape[:2], dtype=torch.bool), K, DIST)
        with torch.no_grad():
            X, Y = initial_poses(nominal.forward_kinematics(q), C, setup)
        Xc, Yc = opencv_pipelines(nominal, q, uv, setup)["shah"]
        assert (X - Xc).abs().max() < 1e-9 and (Y - Yc).abs().max() < 1e-9
        assert (X - cam).abs().max() < 1e-7 and (Y - board).abs().max() < 1e-7


def test_bad_inputs_are_refused():
    nominal, _, q, _, cam, board, _ = scene("panda", 12)
    uv = images(nominal, q, cam, board, "eye_to_hand")
    pts = chessboard()
    kw = dict(camera_matrix=K, dist_coeffs=DIST, progress=False, cross_validation=0)
    with pytest.raises(ShapeError, match="image_points"):  # detections of another board size
        calibrate_camera(nominal, q, uv[:, :40], pts, **kw)
    with pytest.raises(ShapeError, match="q"):  # joint readings of another robot
        calibrate_camera(nominal, q[:, :6], uv, pts, **kw)
    bad = uv.clone()
    bad[3, 7] = math.nan
    with pytest.raises(NonFiniteError, match="image 3, point 7"):
        calibrate_camera(nominal, q, bad, pts, **kw)
    with pytest.raises(OptionError):
        calibrate_camera(nominal, q, uv, pts, estimate=("robot", "lens"), **kw)
    with pytest.raises(ConventionError):
        calibrate_camera(nominal, q, uv, pts, setup="eye_on_hand", **kw)
    # postures rotating about one axis only: the camera's pose is not determined
    q1 = q[:1].repeat(8, 1)
    q1[:, 0] += torch.linspace(-0.3, 0.3, 8, dtype=F64)
    with pytest.raises(DegenerateMotionError):
        calibrate_camera(nominal, q1, images(nominal, q1, cam, board, "eye_to_hand"), pts, **kw)


@pytest.mark.extended
@pytest.mark.parametrize("method", ["least_squares", "gradient"])
def test_intrinsics_estimated_with_the_robot(method):
    """Intrinsics started 2 % off: recovered with the geometry (noise-free), by both methods."""
    nominal, true, q, q_out, cam, board, _ = scene("panda", 40)
    uv = images(true, q, cam, board, "eye_to_hand")
    K0 = K.clone()
    K0[0, 0] *= 1.02
    K0[1, 1] *= 0.98
    K0[0, 2] += 5
    res = calibrate_camera(
        nominal,
        q,
        uv,
        chessboard(),
        camera_matrix=K0,
        dist_coeffs=None,
        method=method,
        estimate=("robot", "camera", "board", "intrinsics"),
        cross_validation=0,
        progress=False,
    )
    assert (res.camera_matrix - K).abs().max() < 1e-3 and (res.dist_coeffs - DIST).abs().max() < 1e-5
    assert (
        held_out_3d(res.chain, res.camera_pose, res.board_pose, true, cam, board, q_out, "eye_to_hand") < 1e-6
    )
