"""calibrate_camera (issue 38 step 2): the robot's geometry, the camera's and the board's poses from
pixels of a chessboard, against the known truth of synthetic images and beside OpenCV's hand-eye pipelines
(scenes: benchmarks/camera_scenes.py, a Panda eye-to-hand and a UR5 eye-in-hand with 0.3 px noise where
stated and every identifiable geometry parameter perturbed by up to ±1 mm / ±0.1°).
"""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from diffkin.calibration import DegenerateMotionError, calibrate_camera
from diffkin.calibration.camera_api import initial_poses
from diffkin.errors import ConventionError, NonFiniteError, OptionError, ShapeError
from diffkin.models import from_urdf

cv2 = pytest.importorskip("cv2")

from benchmarks.camera_scenes import (  # noqa: E402
    DIST,
    F64,
    SCENES,
    K,
    _pnp,
    chessboard,
    held_out_3d,
    images,
    opencv_pipelines,
    scene,
)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# ------------------------------------------------------------------------------------------------- tests
def test_eye_to_hand_panda_beside_opencv():
    """0.3 px noise, 30 images, 10 % of the corners undetected: fit at the noise floor (χ ≈ 1, RMS ≈ √2 σ,
    held-out images as good), the camera ≥ 5x closer than OpenCV's best method, the board's corners at
    held-out postures ≥ 3x closer; what the images cannot separate is fixed and named."""
    nominal, true, q, q_out, cam, board, _ = scene("panda", 30)
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
        cross_validation=3,
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


def test_misdetected_corners_are_reported_and_a_robust_loss_ignores_them():
    """Six corners 15 px off (a mis-detection) among 0.3 px noise: listed as outliers; the Cauchy loss per
    point keeps the camera's pose at the noise floor where plain least squares is pulled off."""
    nominal, true, q, _, cam, board, _ = scene("ur5", 16)
    uv = images(true, q, cam, board, "eye_in_hand", 0.3)
    bad = [(1, 3), (4, 40), (7, 11), (9, 0), (12, 53), (15, 27)]
    for i, j in bad:
        uv[i, j] += torch.tensor([15.0, -9.0], dtype=F64)
    kw = dict(
        camera_matrix=K,
        dist_coeffs=DIST,
        setup="eye_in_hand",
        measurement_noise=0.3,
        cross_validation=0,
        progress=False,
    )
    with pytest.warns(UserWarning, match="reprojection residual"):
        plain = calibrate_camera(nominal, q, uv, chessboard(), **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no noise warning: the inliers' residual is the noise
        robust = calibrate_camera(nominal, q, uv, chessboard(), loss="cauchy", **kw)
    assert set(bad) <= set(robust.outliers) and len(robust.outliers) <= len(bad) + 2
    assert plain.noise_ratio > 2 and 0.8 < robust.noise_ratio < 1.2  # χ of the inliers
    err = {
        k: float((r.camera_pose[:3, 3] - cam[:3, 3]).norm())
        for k, r in (("plain", plain), ("robust", robust))
    }
    assert err["robust"] < 0.5e-3 and 2 * err["robust"] < err["plain"], err


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


def test_signature_is_the_issues():
    """Issue 38's names: calibrate_camera(chain, q, image_points, board_points, *, camera_matrix,
    dist_coeffs=None, setup="eye_to_hand", visible=None, estimate=("robot", "camera", "board"), ...) and the
    result's fields."""
    import dataclasses
    import inspect

    from diffkin.calibration import CameraCalibrationResult

    sig = inspect.signature(calibrate_camera)
    names = list(sig.parameters)
    assert names[:4] == ["chain", "q", "image_points", "board_points"]
    kw = {n: p for n, p in sig.parameters.items() if p.kind is inspect.Parameter.KEYWORD_ONLY}
    assert kw["camera_matrix"].default is inspect.Parameter.empty and kw["dist_coeffs"].default is None
    assert kw["setup"].default == "eye_to_hand" and kw["visible"].default is None
    assert tuple(kw["estimate"].default) == ("robot", "camera", "board")
    fields = {f.name for f in dataclasses.fields(CameraCalibrationResult)}
    assert {
        "chain",
        "camera_pose",
        "board_pose",
        "camera_matrix",
        "dist_coeffs",
        "reprojection_rms",
        "report",
        "cross_validation",
        "noise_ratio",
        "outliers",
    } <= fields


@pytest.mark.extended
def test_demo_camera_calibration_section(tmp_path):
    """The demo's camera-calibration section (about 5 s): the table beside OpenCV's seven methods, the
    figure, no failure (diffkin's camera at least 5x closer than OpenCV's best)."""
    from diffkin.demo import Report, section_camera_calibration

    report = Report(tmp_path)
    section_camera_calibration(report, quick=True)
    assert report.failures == [] and report.sections[-1].count("| OpenCV ") == 7
    assert (tmp_path / "camera_calibration_residuals.png").stat().st_size > 10_000
