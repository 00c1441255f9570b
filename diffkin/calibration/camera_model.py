"""Measurement model of calibration from images: the robot's error model, the camera's and the board's
poses and the camera's intrinsics, mapped to the pixels of the board's points (:func:`calibrate_camera`).

The parameter vector θ of :class:`CameraModel` is, in this order::

    θ = [ζ (the robot's error model, P entries: calibrate's),
         camera_x, camera_y, camera_z, camera_rx, camera_ry, camera_rz,   T_cam = T_cam,0 · Δ(camera)
         board_x, board_y, board_z, board_rx, board_ry, board_rz,         T_board = T_board,0 · Δ(board)
         fx, fy, cx, cy, k1, k2, p1, p2, k3]                              the camera matrix and distortion

with Δ(v) the kernel layer's pose correction (translation in metres, rotation vector in radians) on the
starting poses. Eye-to-hand the camera is T_base_cam and the board rides on the flange (T_flange_board);
eye-in-hand the camera rides on the flange (T_flange_cam) and the board is fixed (T_base_board). The board's
pose in the camera frame is then

    eye-to-hand:  T_cam_board(q) = T_base_cam⁻¹ · T_base_flange(ζ, q) · T_flange_board
    eye-in-hand:  T_cam_board(q) = T_flange_cam⁻¹ · T_base_flange(ζ, q)⁻¹ · T_base_board

and pixel j of image i is :func:`~diffkin.calibration.project_points` of board point j (OpenCV's pinhole
and distortion model). The per-image input of the model is x_i = [q_i, v_i] (joint readings and the
visibility mask of the M points, 1 or 0), so that the solvers of :mod:`.solvers` take subsets of images as
they take subsets of poses; invisible points have zero residual and zero rows in Φ.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..kernels.jacobian import twist_of_derivative
from ..kernels.joints import pose_correction
from ..transforms import _transform_inverse, _transform_points
from .camera import _project
from .identifiability import IdentifiabilityReport, _random_configurations, analyse_matrices, merge_reports
from .model import POSE_AXES, ParameterLayout, parameter_jacobian

__all__ = ["CameraModel", "ESTIMATE", "INTRINSICS", "camera_reports"]

#: what calibrate_camera can estimate
ESTIMATE = ("robot", "camera", "board", "intrinsics")
#: the intrinsic parameters, in θ's order
INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


class CameraModel(ParameterLayout):
    """Pixels of the board's points for K robots: ``calibration_matrix``, ``residual``, ``residual_of`` and
    the layout attributes the solvers of :mod:`.solvers` use (``n_params``, ``candidate``, ``names``,
    ``nominal``, ``is_length``, ``chains``).

    ``robot``: the robot's error model (:func:`.error_models.build_model`); ``setup``: ``"eye_to_hand"`` or
    ``"eye_in_hand"``; ``board_points (M, 3)``; ``camera0``, ``board0 (4, 4)``: the starting poses;
    ``intrinsics0 (9,)``: fx, fy, cx, cy, k1, k2, p1, p2, k3; ``estimate``: a subset of :data:`ESTIMATE`.
    """

    def __init__(
        self,
        robot,
        setup: str,
        board_points: Tensor,
        camera0: Tensor,
        board0: Tensor,
        intrinsics0: Tensor,
        estimate: tuple[str, ...],
    ):
        self.robot = robot
        self.setup = setup
        self.board_points = board_points
        self.camera0, self.board0 = camera0, board0
        self.n = robot.n
        self.P_robot = robot.n_params
        self.chains = robot.chains
        self.notes = list(getattr(robot, "notes", []))
        nominal_robot = robot.nominal if robot.nominal.ndim == 1 else robot.nominal[0]
        zeros = nominal_robot.new_zeros(12)
        self.nominal = torch.cat((nominal_robot, zeros, intrinsics0.to(nominal_robot)))
        self.names = (
            tuple(robot.names)
            + tuple(f"camera_{a}" for a in POSE_AXES)
            + tuple(f"board_{a}" for a in POSE_AXES)
            + INTRINSICS
        )
        length = torch.cat(
            (
                robot.is_length().cpu(),
                torch.tensor([True] * 3 + [False] * 3, device="cpu").repeat(2),
                torch.zeros(9, dtype=torch.bool, device="cpu"),
            )
        )
        self._length = length
        cand = torch.cat(
            (
                robot.candidate.cpu() & ("robot" in estimate),
                torch.full((6,), "camera" in estimate, device="cpu"),
                torch.full((6,), "board" in estimate, device="cpu"),
                torch.full((9,), "intrinsics" in estimate, device="cpu"),
            )
        )
        self.candidate = cand.to(self.nominal.device)

    # ----------------------------------------------------------------------------------- layout
    @property
    def n_params(self) -> int:  # (ParameterLayout's dtype and is_length)
        return self.P_robot + 21


    def units(self) -> list[str]:
        """Per entry of θ: ``"m"``, ``"rad"``, ``"px"`` (fx..cy) or ``"1"`` (distortion)."""
        out = ["m" if x else "rad" for x in self._length[: self.P_robot + 12].tolist()]
        return out + ["px"] * 4 + ["1"] * 5

    def split(self, theta: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``(ζ, T_cam, T_board, camera_matrix, dist_coeffs)`` of ``theta (..., P + 21)``."""
        P = self.P_robot
        cam = self.camera0 @ pose_correction(theta[..., P : P + 6])
        board = self.board0 @ pose_correction(theta[..., P + 6 : P + 12])
        fx, fy, cx, cy = theta[..., P + 12 : P + 16].unbind(-1)
        o, z = torch.ones_like(fx), torch.zeros_like(fx)
        K = torch.stack((fx, z, cx, z, fy, cy, z, z, o), -1).unflatten(-1, (3, 3))
        return theta[..., :P], cam, board, K, theta[..., P + 16 :]

    # ------------------------------------------------------------------------------ kinematics
    def _cam_board_one(self, theta: Tensor, q: Tensor) -> Tensor:
        """T_cam_board ``(N, 4, 4)`` of one robot's ``theta (P + 21,)`` at joints ``q (N, n)``."""
        zeta, cam, board, _, _ = self.split(theta)
        T = self.robot._fk_one(zeta, q)
        if self.setup == "eye_to_hand":
            return _transform_inverse(cam) @ T @ board
        return _transform_inverse(cam) @ _transform_inverse(T) @ board

    def _pixels_one(self, theta: Tensor, x: Tensor) -> Tensor:
        """Pixels ``(N, M, 2)``, zero where invisible, of one robot at inputs ``x (N, n + M)``."""
        q, vis = x[..., : self.n], x[..., self.n :]
        _, _, _, K, dist = self.split(theta)
        T = self._cam_board_one(theta, q)
        uv = _project(_transform_points(T[..., None, :, :], self.board_points), K, dist)
        return uv * vis[..., None]

    def pixels(self, theta: Tensor, x: Tensor) -> Tensor:
        """Pixels ``(K, N, M, 2)`` of ``theta (K, P + 21)`` at inputs ``x (K, N, n + M)`` (zero where
        invisible)."""
        return torch.func.vmap(self._pixels_one)(theta, x)

    def residual_of(self, prediction: Tensor, measured: Tensor, orientation_weight: float = 1.0) -> Tensor:
        """Per point ``(K, N·M, 2)``: measured − predicted pixels (both zero where invisible)."""
        return (measured - prediction).flatten(-3, -2)

    def residual(self, theta: Tensor, x: Tensor, measured: Tensor, orientation_weight: float = 1.0) -> Tensor:
        return self.residual_of(self.pixels(theta, x), measured)

    def forward_kinematics(self, theta: Tensor, q: Tensor) -> Tensor:
        """T_cam_board ``(K, N, 4, 4)`` of ``theta (K, P + 21)`` at joints ``q (K, N, n)``."""
        return torch.func.vmap(self._cam_board_one)(theta, q)

    def _jacobian(self, f, theta: Tensor, x: Tensor, columns: Tensor | None) -> Tensor:
        return parameter_jacobian(f, theta, x, self.n_params, columns)

    def calibration_matrix(
        self,
        theta: Tensor,
        x: Tensor,
        position_only: bool = False,
        orientation_weight: float = 1.0,
        columns: Tensor | None = None,
    ):
        """Φ ``(K, N·M, 2, C)``: pixels per unit change of the selected entries of θ (zero rows for
        invisible points), and the predicted pixels ``(K, N, M, 2)``."""
        with torch.no_grad():
            uv = self.pixels(theta, x)
        J = self._jacobian(self._pixels_one, theta, x, columns)  # (K, N, M, 2, C)
        return J.flatten(1, 2), uv

    def pose_matrix(self, theta: Tensor, q: Tensor, orientation_weight: float, columns: Tensor) -> Tensor:
        """Φ of the board's pose in the camera frame ``(K, N, 6, C)`` (twists [δp; w δω]): what images
        determine when the intrinsics are known (the structural analysis)."""
        with torch.no_grad():
            T = self.forward_kinematics(theta, q)
        dT = self._jacobian(self._cam_board_one, theta, q, columns)
        Phi = twist_of_derivative(dT, T)
        return torch.cat((Phi[..., :3, :], orientation_weight * Phi[..., 3:, :]), -2)

    # ---------------------------------------------------------------------------------- chains
    def to_chains(self, theta: Tensor):
        return self.robot.to_chains(theta[..., : self.P_robot])


def _order(model: CameraModel, mask: Tensor) -> list[int]:
    """Indices into θ of the ``mask``-ed entries with the camera and board first (then the robot, then the
    intrinsics): what a column depends on is reported against the poses the images cannot separate it
    from (a base shift absorbed by the camera's pose, a last-link frame by the board's)."""
    P = model.P_robot
    idx = mask.nonzero().flatten().tolist()
    return [j for j in idx if P <= j < P + 12] + [j for j in idx if j < P] + [j for j in idx if j >= P + 12]


def camera_reports(
    model: CameraModel,
    theta: Tensor,
    x: Tensor,
    orientation_weight: float = 0.1,
    rank_tol: float | None = None,
) -> tuple[list[IdentifiabilityReport], Tensor]:
    """Identifiability of K robots (``theta (K, P + 21)``, inputs ``x (K, N, n + M)``) and the free mask
    ``(K, C)`` over the C candidates of ``model``.

    Structural (as :func:`.identifiability.model_reports`): the board's pose in the camera frame at random
    configurations, which is what images determine for known intrinsics; parameters it cannot separate
    from the camera's and board's poses (or from each other) are fixed at their starting values and
    reported with their dependencies. Data: the pixel matrix at the images given, with the intrinsics;
    what these images leave undetermined is estimated in the span they determine (minimum norm) and listed
    as ``undetermined``.
    """
    K, N = x.shape[0], x.shape[1]
    cand = model.candidate.cpu()
    names = model.names
    poses = cand.clone()
    poses[model.P_robot + 12 :] = False
    order_s, order_d = _order(model, poses), _order(model, cand)
    with torch.no_grad():
        C_s = len(order_s)
        M = 2 * math.ceil(max(C_s, 1) / 6) + 8
        qs = _random_configurations(model.robot, M, theta.dtype, theta.device).expand(K, M, model.n)
        struct = None
        if C_s:
            cols = torch.zeros_like(cand)
            cols[order_s] = True
            Phi_s = model.pose_matrix(theta, qs, orientation_weight, cols)  # columns in θ's order
            pos = {j: k for k, j in enumerate(cols.nonzero().flatten().tolist())}
            Phi_s = Phi_s[..., [pos[j] for j in order_s]]
            struct = analyse_matrices(Phi_s.reshape(K, -1, C_s), [names[j] for j in order_s], M, rank_tol)
        Phi_d, _ = model.calibration_matrix(theta, x, columns=cand)
        pos = {j: k for k, j in enumerate(cand.nonzero().flatten().tolist())}
        Phi_d = Phi_d[..., [pos[j] for j in order_d]]
        data = analyse_matrices(Phi_d.reshape(K, -1, len(order_d)), [names[j] for j in order_d], N, rank_tol)
    cand_names = [names[j] for j in cand.nonzero().flatten().tolist()]
    rows = 2 * max(int(x[:, :, model.n :].sum(-1).max()), 1)
    return merge_reports(data, struct, cand_names, rows, theta.device)
