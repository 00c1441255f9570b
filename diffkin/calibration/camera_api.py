"""``calibrate_camera``: the robot's geometry, the camera's and the board's poses (and the intrinsics) from
images of a calibration board, in one least-squares problem over the reprojection error in pixels."""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable

import torch
from torch import Tensor

from .._numerics import tol_for
from ..chain import KinematicChain
from ..errors import ConventionError, DiffkinError, NonFiniteError, OptionError, ShapeError, require
from ..transforms import _transform_inverse, as_measured_transform
from ..validation import as_tensor, check_number, shape_str, tensors
from .camera_model import ESTIMATE, CameraModel, camera_reports
from .camera_result import CameraCalibrationResult
from .error_models import build_model
from .handeye import SETUPS, robot_world_hand_eye
from .solvers import LOSSES, fold_fits, gradient_descent, least_squares

__all__ = ["calibrate_camera", "initial_poses"]

METHODS = ("least_squares", "gradient")


def _check_inputs(model, q, image_points, board_points, camera_matrix, dist_coeffs, visible):
    """Validated ``(q (N, n), image_points (N, M, 2) with zeros where invisible, board_points (M, 3),
    K (3, 3), dist (5,), visible (N, M) bool)`` in the chain's dtype and device."""
    ref = model.chains[0]
    q, board_points, camera_matrix, dist_coeffs = tensors(
        ("q", q, (model.n,)),
        ("board_points", board_points, (3,)),
        ("camera_matrix", camera_matrix, (3, 3)),
        ("dist_coeffs", dist_coeffs, None),
        like=ref,
    )
    (image_points,) = tensors(("image_points", image_points, (2,)), like=ref, finite=False)
    if q.ndim != 2 or q.shape[0] < 3:
        raise ShapeError(f"expected q of shape (N, {model.n}) with N >= 3 images, got {shape_str(q.shape)}")
    N = q.shape[0]
    if board_points.ndim != 2 or board_points.shape[0] < 4:
        raise ShapeError(
            f"expected board_points of shape (M, 3) with M >= 4, got {shape_str(board_points.shape)}"
        )
    M = board_points.shape[0]
    if image_points.shape != (N, M, 2):
        raise ShapeError(
            f"expected image_points of shape (N, M, 2) = ({N}, {M}, 2) for {N} joint readings and "
            f"{M} board points, got {shape_str(image_points.shape)}"
        )
    if camera_matrix.ndim != 2 or not (camera_matrix[0, 0] > 0 and camera_matrix[1, 1] > 0):
        raise DiffkinError(
            "expected camera_matrix (3, 3) [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0,"
            f" got {camera_matrix.tolist()}"
        )
    if dist_coeffs is None:
        dist_coeffs = camera_matrix.new_zeros(5)
    dist_coeffs = dist_coeffs.reshape(-1)
    if dist_coeffs.numel() == 4:  # OpenCV's (k1, k2, p1, p2)
        dist_coeffs = torch.cat((dist_coeffs, dist_coeffs.new_zeros(1)))
    if dist_coeffs.numel() != 5:
        raise ShapeError(
            "expected dist_coeffs (k1, k2, p1, p2[, k3]) of 4 or 5 entries (OpenCV's rational and "
            f"thin-prism models are not supported), got {dist_coeffs.numel()}"
        )
    if visible is None:
        vis = torch.ones(N, M, dtype=torch.bool, device=q.device)
    else:
        vis = torch.as_tensor(visible, device=q.device)
        if vis.dtype != torch.bool:
            raise DiffkinError(f"expected visible as a bool mask (N, M), got dtype {vis.dtype}")
        if vis.shape != (N, M):
            raise ShapeError(f"expected visible of shape (N, M) = ({N}, {M}), got {shape_str(vis.shape)}")
    bad = vis & ~torch.isfinite(image_points).all(-1)
    if bool(bad.any()):
        i, j = bad.nonzero()[0].tolist()
        raise NonFiniteError(
            f"image_points holds NaN or inf at {int(bad.sum())} visible points (first: image "
            f"{i}, point {j}); mark undetected points False in visible"
        )
    if int(vis.sum()) == 0:
        raise DiffkinError("no visible point in any image")
    image_points = torch.where(vis[..., None], image_points, torch.zeros_like(image_points))
    return q, image_points, board_points, camera_matrix, dist_coeffs, vis


def _pnp(image_points: Tensor, board_points: Tensor, vis: Tensor, K: Tensor, dist: Tensor):
    """Per image the board's pose in the camera frame by ``cv2.solvePnP`` (iterative; planar boards from
    their homography): ``(T_cam_board (N, 4, 4), ok (N,) bool)``; images with too few visible points (4 on
    a planar board, else 6) or where OpenCV fails are not ok."""
    cv2 = require("cv2", "camera", "calibrate_camera's initial poses (or pass camera_pose= and board_pose=)")
    import numpy as np

    from ..rotations import rotvec_to_matrix

    pts = board_points.detach().cpu().double().numpy()
    centred = pts - pts.mean(0)
    planar = np.linalg.svd(centred, compute_uv=False)[-1] < 1e-9 * max(1.0, np.abs(centred).max())
    need = 4 if planar else 6
    Kn, dn = K.detach().cpu().double().numpy(), dist.detach().cpu().double().numpy()
    img, v = image_points.detach().cpu().double().numpy(), vis.cpu().numpy()
    rv, tv, ok = np.zeros((len(img), 3)), np.zeros((len(img), 3)), np.zeros(len(img), dtype=bool)
    for i in range(len(img)):  # OpenCV's solver, one image at a time (the initialiser only)
        if v[i].sum() < need:
            continue
        good, r, t = cv2.solvePnP(pts[v[i]], img[i][v[i]], Kn, dn, flags=cv2.SOLVEPNP_ITERATIVE)
        if good and np.all(np.isfinite(r)) and np.all(np.isfinite(t)) and t[2, 0] > 0:
            rv[i], tv[i], ok[i] = r[:, 0], t[:, 0], True
    like = dict(dtype=K.dtype, device=K.device)
    T = torch.eye(4, **like).repeat(len(img), 1, 1)
    T[:, :3, :3] = rotvec_to_matrix(torch.tensor(rv, **like))
    T[:, :3, 3] = torch.tensor(tv, **like)
    return T, torch.tensor(ok, device=K.device)


def initial_poses(T_base_flange: Tensor, T_cam_board: Tensor, setup: str) -> tuple[Tensor, Tensor]:
    """``(camera_pose, board_pose)`` from the flange poses ``(N, 4, 4)`` (nominal kinematics) and the board's
    poses in the camera frame ``(N, 4, 4)`` by :func:`robot_world_hand_eye` (Shah's closed form; the
    reprojection fit refines it): eye-in-hand
    (T_flange_cam, T_base_board); eye-to-hand (T_base_cam, T_flange_board), from the inverted flange poses
    (the camera is then fixed to the "gripper" of the loop and the board is the "world" on the flange)."""
    G = T_base_flange if setup == "eye_in_hand" else _transform_inverse(T_base_flange)
    world, cam = robot_world_hand_eye(G, T_cam_board, refine=False)
    return cam, world


def _intrinsics(K: Tensor, dist: Tensor) -> Tensor:
    return torch.stack((K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist.unbind(-1)))


def _point_rms(r: Tensor, vis: Tensor) -> Tensor:
    """√(Σ|r|² / visible points) over the last two dims of ``r (..., N, M, 2)``, ``vis (..., N, M)``."""
    return (r.square().sum((-1, -2, -3)) / vis.sum((-1, -2)).clamp_min(1)).sqrt()


def calibrate_camera(
    chain: KinematicChain,
    q: Tensor,
    image_points: Tensor,
    board_points: Tensor,
    *,
    camera_matrix: Tensor,
    dist_coeffs: Tensor | None = None,
    setup: str = "eye_to_hand",
    visible: Tensor | None = None,
    estimate: Iterable[str] = ("robot", "camera", "board"),
    method: str = "least_squares",
    camera_pose: Tensor | None = None,
    board_pose: Tensor | None = None,
    error_model: str = "auto",
    parameters: str | Iterable[str] = "all",
    joint_offsets: bool = True,
    measurement_noise: float | None = None,
    loss: str | None = None,
    cross_validation: int | None = 5,
    max_iterations: int | None = None,
    tol: float | None = None,
    rank_tol: float | None = None,
    progress: bool = True,
    **solver_options,
) -> CameraCalibrationResult:
    """Calibrate a robot's geometry together with a camera's and a board's poses from images of the board.

    One least-squares problem over the robot's error model (as :func:`~diffkin.calibration.calibrate`'s
    ``error_model``), the camera's pose, the board's pose and, with ``"intrinsics"`` in ``estimate``, the
    camera matrix and distortion, minimising the reprojection error in pixels (model in
    :mod:`.camera_model`). Started from the nominal robot and the poses of
    :func:`~diffkin.calibration.robot_world_hand_eye` on per-image ``cv2.solvePnP`` poses (needs the
    ``camera`` extra), unless ``camera_pose`` and ``board_pose`` are given.

    Args:
        chain: the nominal robot (DHChain, URDFChain or MJCFChain); its end frame is the flange.
        q: joint readings ``(N, n)``, one per image, N >= 3.
        image_points: detected pixels ``(N, M, 2)`` of the M board points (anything where not visible).
        board_points: the board's points ``(M, 3)`` in its own frame (metres), e.g. chessboard corners.
        camera_matrix: ``(3, 3)`` [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (the start when intrinsics are
            estimated).
        dist_coeffs: OpenCV's (k1, k2, p1, p2[, k3]) or None (no distortion).
        setup: ``"eye_to_hand"``: a fixed camera, the board on the flange (``camera_pose`` T_base_cam,
            ``board_pose`` T_flange_board); ``"eye_in_hand"``: the camera on the flange, a fixed board
            (T_flange_cam, T_base_board).
        visible: bool ``(N, M)``: the points detected in each image (default all; NaN pixels must be
            marked False).
        estimate: any of ``"robot"``, ``"camera"``, ``"board"``, ``"intrinsics"`` (fx, fy, cx, cy and the
            five distortion coefficients); what is not estimated stays at its given or initial value.
        method: ``"least_squares"`` (Levenberg-Marquardt-style iterations of :func:`.solvers.least_squares`
            on the pixel residuals, default) or ``"gradient"`` (:func:`.solvers.gradient_descent`, L-BFGS).
        camera_pose, board_pose: ``(4, 4)`` starting (or, when not estimated, known) poses; both or neither.
        error_model, parameters, joint_offsets: the robot's parameters, as in :func:`calibrate` (the base
            and tool corrections are the camera's and board's poses here).
        measurement_noise: σ, pixels per coordinate of the detections: ``result.noise_ratio`` compares the
            fit residual with it (≈ 1 expected; a ``UserWarning`` above 2), and the outlier threshold is
            3 √2 σ per point (else 3 × the median residual × 1.2). With a robust ``loss`` and outliers
            fewer than half the points, χ is that of the inliers.
        loss: ``"l2"`` (default) or a robust loss of :data:`.LOSSES` per point, quadratic up to ``scale``
            pixels (``scale=`` in ``solver_options``, default 2 √2 σ, else 1 px).
        cross_validation: k of the k-fold held-out reprojection error over images (default 5; run with at
            least 4k images; 0/None: off); the k fits run as one batch.
        max_iterations, tol, rank_tol, progress, solver_options: as :func:`calibrate`.

    Returns:
        :class:`CameraCalibrationResult`. What the images cannot separate from the camera's and board's
        poses (e.g. the first joint's origin, absorbed by the camera pose eye-to-hand; frames after the last
        joint, absorbed by the board's pose) is reported in ``result.report.unidentifiable`` with the
        dependency and kept nominal.

    Raises:
        ShapeError, NonFiniteError, DiffkinError: inputs of the wrong shape (image points of another board
            size, joint readings of another robot), NaN at visible points, no visible point.
        DegenerateMotionError: the postures do not determine the camera's pose (rotations about one axis).
        ConventionError, OptionError: unknown ``setup``, ``estimate`` entry, ``method`` or ``loss``.
    """
    if setup not in SETUPS:
        raise ConventionError(f"unknown setup {setup!r}; valid: {', '.join(SETUPS)}")
    estimate = (estimate,) if isinstance(estimate, str) else tuple(estimate)
    unknown = [e for e in estimate if e not in ESTIMATE]
    if unknown or not estimate:
        raise OptionError(f"unknown estimate entries {unknown!r}; choose among {', '.join(ESTIMATE)}")
    if method not in METHODS:
        raise ConventionError(f"unknown calibration method {method!r}; valid: {', '.join(METHODS)}")
    if (camera_pose is None) != (board_pose is None):
        raise OptionError("pass both camera_pose and board_pose (starting or known poses) or neither")
    if camera_pose is None and not {"camera", "board"} <= set(estimate):
        raise OptionError(
            "the camera's and the board's poses are estimated unless both are given: add "
            "'camera' and 'board' to estimate or pass camera_pose= and board_pose="
        )
    sigma = (
        None
        if measurement_noise is None
        else check_number(measurement_noise, "measurement_noise", unit=" (pixels)")
    )
    loss = "l2" if loss is None else loss
    if loss not in LOSSES:
        raise ConventionError(f"unknown loss {loss!r}; valid: {', '.join(LOSSES)}")
    scale = solver_options.pop("scale", None)
    scale = check_number(
        scale if scale is not None else (2 * math.sqrt(2) * sigma if sigma else 1.0),
        "scale",
        unit=" (pixels)",
    )

    robot, kind = build_model(chain, error_model, parameters, False, False, joint_offsets)
    ref = robot.chains[0]
    q = as_tensor(q, "q", dtype=ref.dtype, device=ref.device) if q is not None else q
    q, img, pts, K, dist, vis = _check_inputs(
        robot, q, image_points, board_points, camera_matrix, dist_coeffs, visible
    )
    q, img = q.detach(), img.detach()
    N, M = img.shape[:2]
    nominal_robot = robot.nominal if robot.nominal.ndim == 1 else robot.nominal[0]
    with torch.no_grad():
        T_flange = robot._fk_one(nominal_robot, q)
    notes = []
    if camera_pose is None:
        C, ok = _pnp(img, pts, vis, K, dist)
        if int(ok.sum()) < 3:
            raise DiffkinError(
                f"solvePnP found the board's pose in only {int(ok.sum())} of {N} images; at least"
                " 3 are needed to start (or pass camera_pose= and board_pose=)"
            )
        if not bool(ok.all()):
            notes.append(
                f"{int((~ok).sum())} image(s) with too few points for solvePnP were left out of the "
                "initial hand-eye estimate (they are used in the fit)"
            )
        cam0, board0 = initial_poses(T_flange[ok], C[ok], setup)
    else:
        cam0 = as_measured_transform(
            as_tensor(camera_pose, "camera_pose", dtype=ref.dtype, device=ref.device), "camera_pose"
        )
        board0 = as_measured_transform(
            as_tensor(board_pose, "board_pose", dtype=ref.dtype, device=ref.device), "board_pose"
        )
    model = CameraModel(robot, setup, pts, cam0.detach(), board0.detach(), _intrinsics(K, dist), estimate)
    model.notes = list(model.notes) + notes
    x = torch.cat((q, vis.to(q.dtype)), -1)
    theta0 = model.nominal[None].clone()
    reports, free = camera_reports(model, theta0, x[None], rank_tol=rank_tol)
    report = reports[0]
    solve = least_squares if method == "least_squares" else gradient_descent
    opts = dict(
        max_iterations=max_iterations, tol=tol, progress=progress, loss=loss, scale=scale, **solver_options
    )
    if method == "gradient":
        opts.setdefault("gtol", tol_for(q, 1e-6, 1e-3))  # pixels
    opts = {k: v for k, v in opts.items() if v is not None}
    out = solve(model, theta0, free, x[None], img[None], orientation_weight=1.0, **opts)
    theta = out.zeta[0]

    # --------------------------------------------------------------------------------------- report
    n_vis = int(vis.sum())
    to_px = math.sqrt(N * M / n_vis)  # the solvers' RMS runs over every point slot, invisible ones zero
    history = [float(h[0]) * to_px for h in out.position_rms]
    with torch.no_grad():
        # the projections the report draws (plot_image_residuals) are those its RMS figures come from
        uv, uv0 = model.pixels(torch.cat((theta[None], theta0)), x[None].expand(2, -1, -1)).unbind(0)
        r = model.residual_of(uv, img).reshape(N, M, 2)
        r0 = model.residual_of(uv0, img).reshape(N, M, 2)
    per_image = (r.square().sum((-1, -2)) / vis.sum(-1).clamp_min(1)).sqrt()
    per_image0 = (r0.square().sum((-1, -2)) / vis.sum(-1).clamp_min(1)).sqrt()
    rms = float(_point_rms(r, vis))
    norms = r.norm(dim=-1)
    threshold = (
        3.0 * math.sqrt(2.0) * sigma if sigma is not None else 3.0 * 1.2011 * float(norms[vis].median())
    )
    out_mask = (norms > threshold) & vis
    outliers = [tuple(ij) for ij in out_mask.nonzero().tolist()]
    ratio = None
    if sigma is not None:
        # a robust fit's χ is that of its inliers while they are the majority (as calibrate's)
        robust = loss != "l2" and 0 < len(outliers) < n_vis / 2
        keep = vis & ~out_mask if robust else vis
        dof = max(2 * int(keep.sum()) - report.rank, 1)
        ratio = math.sqrt(float((r[keep] / sigma).square().sum()) / dof)
        if ratio > 2.0:
            warnings.warn(
                f"camera calibration of '{ref.name}': the reprojection residual is {ratio:.1f}x what "
                f"{sigma:g} px of detection noise explains. Likely causes: wrong joint readings (order, "
                "units, timing), a board of other dimensions, wrong intrinsics (estimate them), "
                "mis-detected corners (use loss='cauchy' or 'huber'), or an error model that cannot "
                "represent the robot.",
                UserWarning,
                stacklevel=2,
            )
    cv = None
    if cross_validation and N >= 4 * int(cross_validation):
        cv = _cross_validate(model, theta0, free, x, img, vis, solve, opts, int(cross_validation))
    if report.undetermined:
        notes.append(
            f"these {N} images determine only {report.rank} of {report.structural_rank} identifiable "
            f"parameters; {len(report.undetermined)} ({', '.join(report.undetermined[:4])}"
            f"{', ...' if len(report.undetermined) > 4 else ''}) are minimum-norm estimates: add "
            "images at other postures"
        )
        warnings.warn(f"camera calibration of '{ref.name}': {notes[-1]}", UserWarning, stacklevel=2)
    _, cam, board, K_fit, dist_fit = model.split(theta)
    cand = model.candidate.nonzero().flatten().tolist()
    units = model.units()
    return CameraCalibrationResult(
        chain=model.to_chains(theta[None])[0],
        nominal_chain=robot.chains[0].copy(),
        camera_pose=cam.detach(),
        board_pose=board.detach(),
        camera_matrix=K_fit.detach(),
        dist_coeffs=dist_fit.detach(),
        reprojection_rms=rms,
        setup=setup,
        method=method,
        estimate=estimate,
        names=[model.names[j] for j in cand],
        units=[units[j] for j in cand],
        nominal=theta0[0, cand].clone(),
        identified=theta[cand].detach().clone(),
        report=report,
        residuals=history,
        iterations=out.iterations,
        converged=bool(out.converged[0]),
        initial_camera_pose=cam0.detach(),
        initial_board_pose=board0.detach(),
        initial_reprojection_rms=float(_point_rms(r0, vis)),
        error_model=kind,
        noise_ratio=ratio,
        cross_validation=cv,
        outliers=outliers,
        outlier_threshold=threshold,
        image_rms=per_image,
        initial_image_rms=per_image0,
        image_points=torch.where(vis[..., None], img, torch.nan),
        visible=vis,
        reprojected=torch.where(vis[..., None], uv, torch.nan),
        initial_reprojected=torch.where(vis[..., None], uv0, torch.nan),
        loss=loss,
        notes=list(model.notes) + [n for n in notes if n not in model.notes],
    )


def _cross_validate(model, theta0, free, x, img, vis, solve, opts, folds: int) -> dict | None:
    """k-fold held-out reprojection RMS over images; the k fits run as one batch."""
    fits = fold_fits(model, theta0, free, x, img, solve, opts, folds, min_train=3)
    if fits is None:
        return None
    out, test = fits
    with torch.no_grad():
        r = model.residual(out.zeta, x[test], img[test]).unflatten(1, (test.shape[1], img.shape[1]))
    v = vis[test]
    per_image = (r.square().sum((-1, -2)) / v.sum(-1).clamp_min(1)).sqrt()
    return {
        "folds": test.shape[0],
        "reprojection_rms": float(_point_rms(r.flatten(0, 1), v.flatten(0, 1))),
        "reprojection_max": float(r.norm(dim=-1).max()),
        "image_rms_max": float(per_image.max()),
    }
