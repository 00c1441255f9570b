"""Hand-eye (AX = XB) and robot-world/hand-eye (AX = ZB) calibration with OpenCV's conventions, batched.

``hand_eye(T_base_gripper (..., N, 4, 4), T_cam_target (..., N, 4, 4), method=, setup=)`` returns the camera
in the gripper frame (``setup="eye_in_hand"``: OpenCV's ``cam2gripper``) or in the base frame
(``"eye_to_hand"``: what OpenCV returns when given the inverted gripper poses). The five closed forms are
OpenCV's ``calibrateHandEye`` arithmetic (Tsai-Lenz 1989, Park-Martin 1994, Horaud-Dornaika 1995,
Andreff et al. 1999, Daniilidis 1999) on the motion pairs i < j, A_ij = G_j⁻¹ G_i, B_ij = C_j C_i⁻¹,
A X = X B, including OpenCV's quaternion sign choices, so that the results equal OpenCV's to rounding.

``robot_world_hand_eye(T_base_gripper, T_cam_target, method="shah"|"li")`` is OpenCV's
``calibrateRobotWorldHandEye`` (Shah 2013, Li et al. 2010) for a camera on the gripper looking at a fixed
board (the "world"): it returns ``T_base_world`` (the board in the base frame, the inverse of OpenCV's
``base2world``) and ``T_gripper_cam`` (the camera in the gripper frame, the inverse of OpenCV's
``gripper2cam``).

``refine=True`` (default) follows either closed form with Gauss-Newton on SE(3) over both unknown transforms
of the loop G_i X C_i = Y (:mod:`.handeye_refine`). Motion sets that do not determine X (fewer than three
poses, or relative rotations about fewer than two distinct axes) raise :class:`DegenerateMotionError`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._numerics import broadcast_shapes
from ..errors import ConventionError, DiffkinError, ShapeError
from ..kernels.quaternion import _matrix_to_quaternion
from ..rotations import (
    _matrix_to_rotvec,
    _quaternion_conjugate,
    _quaternion_multiply,
    _quaternion_to_matrix,
    _skew,
)
from ..transforms import _make_transform, _transform_inverse, as_measured_transform
from ..validation import check_number, shape_str

__all__ = ["DegenerateMotionError", "HAND_EYE_METHODS", "ROBOT_WORLD_METHODS", "SETUPS", "hand_eye",
           "robot_world_hand_eye", "motion_axis_spread"]

HAND_EYE_METHODS = ("park", "tsai", "horaud", "andreff", "daniilidis")
ROBOT_WORLD_METHODS = ("shah", "li")
SETUPS = ("eye_in_hand", "eye_to_hand")


class DegenerateMotionError(DiffkinError):
    """The robot motions do not determine the hand-eye transform: fewer than 3 poses, or all relative
    rotations about one axis (or none at all). ``problems`` lists the batch indices concerned."""

    def __init__(self, message: str, problems: list[tuple[int, ...]] | None = None):
        super().__init__(message)
        self.problems = problems or []


# ----------------------------------------------------------------------------------------- helpers
def _opencv_quaternion(R: Tensor) -> Tensor:
    """Unit quaternion (η, ε) of R with η >= 0 (diffkin's one encoding; OpenCV's sign choice as well)."""
    return _matrix_to_quaternion(R)


def _kron33(A: Tensor, B: Tensor) -> Tensor:
    """Kronecker product of (..., a, b) and (..., c, d) -> (..., a c, b d)."""
    a, b = A.shape[-2:]
    c, d = B.shape[-2:]
    K = A[..., :, None, :, None] * B[..., None, :, None, :]
    return K.reshape(*K.shape[:-4], a * c, b * d)


def _lstsq(A: Tensor, b: Tensor) -> Tensor:
    """Minimum-norm least squares (OpenCV's ``solve(..., DECOMP_SVD)``): (..., m, n), (..., m) -> (..., n)."""
    return (torch.linalg.pinv(A) @ b[..., None])[..., 0]


def _normalize_rotation(R: Tensor) -> Tensor:
    """OpenCV's ``normalizeRotation``: scale to unit determinant, polar factor U Vᵀ, reflection fixed."""
    det = torch.linalg.det(R)
    scale = torch.sign(det) * det.abs().clamp_min(torch.finfo(R.dtype).tiny).pow(-1.0 / 3.0)
    R = R * scale[..., None, None]
    U, _, Vh = torch.linalg.svd(R)
    s = torch.sign(torch.linalg.det(U @ Vh))
    D = torch.ones(*s.shape, 3, dtype=R.dtype, device=R.device)
    D = torch.cat((D[..., :2], s[..., None]), -1)
    return U @ (D[..., :, None] * Vh)


def _pairs(G: Tensor, C: Tensor) -> tuple[Tensor, Tensor]:
    """A_ij = G_j⁻¹ G_i, B_ij = C_j C_i⁻¹ for i < j in OpenCV's order: (..., N, 4, 4) -> (..., K, 4, 4)."""
    N = G.shape[-3]
    i, j = torch.triu_indices(N, N, 1, device=G.device)
    A = _transform_inverse(G[..., j, :, :]) @ G[..., i, :, :]
    B = C[..., j, :, :] @ _transform_inverse(C[..., i, :, :])
    return A, B


def _translation_lstsq(A: Tensor, B: Tensor, R: Tensor) -> Tensor:
    """(I − R_A) t = t_A − R t_B stacked over the pairs (Park, Horaud; Tsai with signs flipped)."""
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    M = (eye - A[..., :3, :3]).flatten(-3, -2)
    rhs = (A[..., :3, 3] - (R[..., None, :, :] @ B[..., :3, 3:])[..., 0]).flatten(-2)
    return _lstsq(M, rhs)


# ------------------------------------------------------------------------------------ closed forms
def _tsai(A: Tensor, B: Tensor) -> tuple[Tensor, Tensor]:
    Pg = 2 * _opencv_quaternion(A[..., :3, :3])[..., 1:]
    Pc = 2 * _opencv_quaternion(B[..., :3, :3])[..., 1:]
    p = _lstsq(_skew(Pg + Pc).flatten(-3, -2), (Pc - Pg).flatten(-2))  # (12) of Tsai-Lenz
    Pcg = 2 * p / torch.sqrt(1 + (p * p).sum(-1, keepdim=True))  # (14)
    eps = Pcg / 2
    eta = torch.sqrt((1 - (eps * eps).sum(-1, keepdim=True)).clamp_min(0))
    R = _quaternion_to_matrix(torch.cat((eta, eps), -1))
    return R, _translation_lstsq(A, B, R)  # (15)


def _park(A: Tensor, B: Tensor) -> tuple[Tensor, Tensor]:
    a = _matrix_to_rotvec(A[..., :3, :3])
    b = _matrix_to_rotvec(B[..., :3, :3])
    M = (b[..., :, None] * a[..., None, :]).sum(-3)  # Σ β αᵀ
    lam, V = torch.linalg.eigh(M.mT @ M)
    R = V @ (lam.rsqrt()[..., :, None] * V.mT) @ M.mT  # (MᵀM)^(-1/2) Mᵀ
    return R, _translation_lstsq(A, B, R)


def _left_right(q: Tensor, right: bool) -> Tensor:
    """Horaud's Q(r) (left product) or W(r) (right product) 4 x 4 matrix of quaternions (..., 4)."""
    r0, x, y, z = q.unbind(-1)
    s = -1 if right else 1
    rows = [[r0, -x, -y, -z], [x, r0, -s * z, s * y], [y, s * z, r0, -s * x], [z, -s * y, s * x, r0]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def _horaud(A: Tensor, B: Tensor) -> tuple[Tensor, Tensor]:
    D = _left_right(_opencv_quaternion(A[..., :3, :3]), False) - _left_right(
        _opencv_quaternion(B[..., :3, :3]), True)
    _, V = torch.linalg.eigh((D.mT @ D).sum(-3))
    R = _quaternion_to_matrix(V[..., :, 0])  # eigenvector of the smallest eigenvalue
    return R, _translation_lstsq(A, B, R)


def _andreff(A: Tensor, B: Tensor) -> tuple[Tensor, Tensor]:
    dt, dev = A.dtype, A.device
    RA, RB, tA, tB = A[..., :3, :3], B[..., :3, :3], A[..., :3, 3], B[..., :3, 3]
    I3 = torch.eye(3, dtype=dt, device=dev).expand_as(RA)
    top = torch.cat((torch.eye(9, dtype=dt, device=dev) - _kron33(RA, RB),
                     torch.zeros(*RA.shape[:-2], 9, 3, dtype=dt, device=dev)), -1)
    bottom = torch.cat((_kron33(I3, tB[..., None, :]), I3 - RA), -1)
    M = torch.cat((top, bottom), -2).flatten(-3, -2)  # (10) of Andreff et al.
    rhs = torch.cat((torch.zeros(*tA.shape[:-1], 9, dtype=dt, device=dev), tA), -1).flatten(-2)
    x = _lstsq(M, rhs)
    return _normalize_rotation(x[..., :9].unflatten(-1, (3, 3))), x[..., 9:]


def _dual_quaternion(T: Tensor) -> tuple[Tensor, Tensor]:
    q = _opencv_quaternion(T[..., :3, :3])
    t = torch.cat((torch.zeros_like(T[..., :1, 3]), T[..., :3, 3]), -1)
    return q, 0.5 * _quaternion_multiply(t, q)


def _daniilidis(A: Tensor, B: Tensor) -> tuple[Tensor, Tensor]:
    qa, qa_ = _dual_quaternion(A)
    qb, qb_ = _dual_quaternion(B)
    a, b, a_, b_ = qa[..., 1:], qb[..., 1:], qa_[..., 1:], qb_[..., 1:]
    zero = torch.zeros_like(a[..., None, :])
    top = torch.cat(((a - b)[..., :, None], _skew(a + b), zero.mT, zero.mT.expand(*a.shape, 3)), -1)
    bottom = torch.cat(((a_ - b_)[..., :, None], _skew(a_ + b_), (a - b)[..., :, None], _skew(a + b)), -1)
    S = torch.cat((top, bottom), -2).flatten(-3, -2)  # (31) of Daniilidis, (6K, 8)
    V = torch.linalg.svd(S, full_matrices=False)[2].mT
    v7, v8 = V[..., :, 6], V[..., :, 7]
    u1, w1, u2, w2 = v7[..., :4], v7[..., 4:], v8[..., :4], v8[..., 4:]
    ca = (u1 * w1).sum(-1)
    cb = (u1 * w2).sum(-1) + (u2 * w1).sum(-1)
    cc = (u2 * w2).sum(-1)
    root = torch.sqrt((cb * cb - 4 * ca * cc).clamp_min(0))
    s1, s2 = (-cb + root) / (2 * ca), (-cb - root) / (2 * ca)  # (34)-(35)

    def val(s):
        return s * s * (u1 * u1).sum(-1) + 2 * s * (u1 * u2).sum(-1) + (u2 * u2).sum(-1)

    first = val(s1) > val(s2)
    s = torch.where(first, s1, s2)
    lam2 = torch.rsqrt(torch.where(first, val(s1), val(s2)))
    dq = (s * lam2)[..., None] * v7 + lam2[..., None] * v8
    q, q_ = dq[..., :4], dq[..., 4:]
    t = 2 * _quaternion_multiply(q_, _quaternion_conjugate(q))[..., 1:]
    return _quaternion_to_matrix(q), t


_CLOSED_FORMS = {"tsai": _tsai, "park": _park, "horaud": _horaud, "andreff": _andreff,
                 "daniilidis": _daniilidis}


def _shah(G: Tensor, C: Tensor) -> tuple[Tensor, Tensor]:
    """OpenCV's Shah on base2gripper G (…, N, 4, 4) and world2cam C: (base2world, gripper2cam)."""
    gR, gt, cR, ct = G[..., :3, :3], G[..., :3, 3], C[..., :3, :3], C[..., :3, 3]
    U, _, Vh = torch.linalg.svd(_kron33(gR, cR).sum(-3))
    RX = _normalize_rotation(Vh[..., 0, :].unflatten(-1, (3, 3)).mT)
    RZ = _normalize_rotation(U[..., :, 0].unflatten(-1, (3, 3)).mT)
    I3 = torch.eye(3, dtype=G.dtype, device=G.device).expand_as(cR)
    M = torch.cat((-cR, I3), -1).flatten(-3, -2)
    rhs = (ct - (RZ[..., None, :, :] @ gt[..., None])[..., 0]).flatten(-2)
    t = _lstsq(M, rhs)
    return _make_transform(RX, t[..., :3]), _make_transform(RZ, t[..., 3:])


def _li(G: Tensor, C: Tensor) -> tuple[Tensor, Tensor]:
    """OpenCV's Li et al. on base2gripper G and world2cam C: (base2world, gripper2cam)."""
    dt, dev = G.dtype, G.device
    gR, gt, cR, ct = G[..., :3, :3], G[..., :3, 3], C[..., :3, :3], C[..., :3, 3]
    I3 = torch.eye(3, dtype=dt, device=dev).expand_as(cR)
    z93 = torch.zeros(*cR.shape[:-2], 9, 3, dtype=dt, device=dev)
    z39 = torch.zeros(*cR.shape[:-2], 3, 9, dtype=dt, device=dev)
    top = torch.cat((_kron33(cR, I3), _kron33(-I3, gR.mT), z93, z93), -1)  # (19) of Li et al.
    bottom = torch.cat((z39, _kron33(I3, gt[..., None, :]), -cR, I3), -1)
    M = torch.cat((top, bottom), -2).flatten(-3, -2)
    rhs = torch.cat((torch.zeros(*ct.shape[:-1], 9, dtype=dt, device=dev), ct), -1).flatten(-2)
    x = _lstsq(M, rhs)
    RX = _normalize_rotation(x[..., :9].unflatten(-1, (3, 3)))
    RZ = _normalize_rotation(x[..., 9:18].unflatten(-1, (3, 3)))
    return _make_transform(RX, x[..., 18:21]), _make_transform(RZ, x[..., 21:24])


# ------------------------------------------------------------------------------------- degeneracy
def motion_axis_spread(T_base_gripper: Tensor) -> Tensor:
    """How well the relative rotations of the poses ``(..., N, 4, 4)`` span two axes: √(λ₂/λ₁) of
    Σ a aᵀ over the rotation vectors a of every pair's relative rotation G_j⁻¹ G_i, ``(...)`` in [0, 1].

    0: all relative rotations about one axis (or none: pure translations), where AX = XB leaves the
    translation along that axis (and for one axis the rotation about it) undetermined.
    """
    G = as_measured_transform(T_base_gripper, "T_base_gripper")
    A, _ = _pairs(G, G)
    a = _matrix_to_rotvec(A[..., :3, :3])
    lam = torch.linalg.eigvalsh((a[..., :, None] * a[..., None, :]).sum(-3))
    tiny = torch.finfo(a.dtype).tiny
    return torch.sqrt(lam[..., 1].clamp_min(0) / lam[..., 2].clamp_min(tiny)) * (lam[..., 2] > 1e-12)


def _check_motions(G: Tensor, axis_tol: float, what: str) -> None:
    N = G.shape[-3]
    if N < 3:
        raise DegenerateMotionError(f"{what} needs at least 3 poses (two motions with distinct rotation "
                                    f"axes), got N = {N}")
    spread = motion_axis_spread(G.detach())
    bad = (spread < axis_tol).nonzero().tolist()
    if bad:
        raise DegenerateMotionError(
            f"{what}: the robot's relative rotations span fewer than two distinct axes in problem(s) "
            f"{[tuple(b) for b in bad[:10]]} (axis spread {float(spread.min()):.3g} < axis_tol {axis_tol:g});"
            " AX = XB then leaves part of X undetermined: add poses rotating about other axes",
            [tuple(b) for b in bad])


def _inputs(T_base_gripper, T_cam_target) -> tuple[Tensor, Tensor]:
    G = as_measured_transform(T_base_gripper, "T_base_gripper")
    C = as_measured_transform(T_cam_target, "T_cam_target")
    if G.ndim < 3 or C.ndim < 3 or G.shape[-3] != C.shape[-3]:
        raise ShapeError(f"expected T_base_gripper and T_cam_target of shape (..., N, 4, 4) with the same N, "
                         f"got {shape_str(G.shape)} and {shape_str(C.shape)}")
    if G.dtype != C.dtype:
        raise ShapeError(f"T_base_gripper is {G.dtype}, T_cam_target {C.dtype}; pass one dtype")
    batch = broadcast_shapes(G.shape[:-3], C.shape[:-3])
    N = G.shape[-3]
    return G.expand(*batch, N, 4, 4), C.expand(*batch, N, 4, 4)


# ------------------------------------------------------------------------------------------ public
def hand_eye(T_base_gripper: Tensor, T_cam_target: Tensor, *, method: str = "park",
             setup: str = "eye_in_hand", refine: bool = True, axis_tol: float = 1e-2,
             iterations: int = 10) -> Tensor:
    """Hand-eye calibration AX = XB with OpenCV's conventions: ``(..., N, 4, 4)`` x 2 -> ``(..., 4, 4)``.

    Args:
        T_base_gripper: the gripper (flange) poses in the robot's base frame, from forward kinematics
            (OpenCV's ``R_gripper2base``, ``t_gripper2base``).
        T_cam_target: the calibration target's poses in the camera frame (``solvePnP``; OpenCV's
            ``R_target2cam``, ``t_target2cam``).
        method: OpenCV's closed form: ``"park"`` (default), ``"tsai"``, ``"horaud"``, ``"andreff"``,
            ``"daniilidis"``; with ``refine=False`` the result equals ``cv2.calibrateHandEye`` to rounding.
        setup: ``"eye_in_hand"``: the camera rides on the gripper and the target is fixed; returns
            T_gripper_cam (OpenCV's ``cam2gripper``). ``"eye_to_hand"``: the camera is fixed and the target
            rides on the gripper; returns T_base_cam (OpenCV's result for the inverted gripper poses).
        refine: follow with Gauss-Newton on SE(3) over X and the fixed transform Y of the loop
            G_i X C_i = Y, minimising the camera-frame pose residuals of the target, rotation and translation
            each weighted by its RMS at the closed form (:mod:`.handeye_refine`).
        axis_tol: the smallest accepted :func:`motion_axis_spread`.
        iterations: Gauss-Newton iterations of the refinement.

    Batched over the leading dims (independent problems); differentiable where the closed form is (distinct
    eigen/singular values), float32 or float64, on the inputs' device.

    Raises:
        DegenerateMotionError: N < 3, or relative rotations about fewer than two distinct axes.
        ConventionError: unknown ``method`` or ``setup``.
    """
    if method not in HAND_EYE_METHODS:
        raise ConventionError(f"unknown hand-eye method {method!r}; valid: {', '.join(HAND_EYE_METHODS)}")
    if setup not in SETUPS:
        raise ConventionError(f"unknown setup {setup!r}; valid: {', '.join(SETUPS)}")
    check_number(axis_tol, "axis_tol")
    G, C = _inputs(T_base_gripper, T_cam_target)
    _check_motions(G, axis_tol, "hand_eye")
    if setup == "eye_to_hand":
        G = _transform_inverse(G)
    A, B = _pairs(G, C)
    R, t = _CLOSED_FORMS[method](A, B)
    X = _make_transform(R, t)
    if refine:
        from .handeye_refine import refine_loop, start_y

        X, _ = refine_loop(G, C, X, start_y(G, C, X), iterations)
    return X


def robot_world_hand_eye(T_base_gripper: Tensor, T_cam_target: Tensor, *, method: str = "shah",
                         refine: bool = True, axis_tol: float = 1e-2,
                         iterations: int = 10) -> tuple[Tensor, Tensor]:
    """Robot-world/hand-eye calibration AX = ZB (OpenCV's ``calibrateRobotWorldHandEye``), batched.

    A camera on the gripper views a fixed target (the "world"). ``T_base_gripper``, ``T_cam_target``
    ``(..., N, 4, 4)`` as in :func:`hand_eye`. Returns ``(T_base_world, T_gripper_cam)``, each
    ``(..., 4, 4)``: the target in the base frame and the camera in the gripper frame, so that
    T_base_world = T_base_gripper_i · T_gripper_cam · T_cam_target_i. OpenCV returns their inverses
    (``base2world`` = T_base_world⁻¹ maps base coordinates to world ones; ``gripper2cam`` = T_gripper_cam⁻¹);
    with ``refine=False`` they equal OpenCV's to rounding. ``method``: ``"shah"`` (default) or ``"li"``;
    ``refine``, ``axis_tol``, ``iterations`` and errors as :func:`hand_eye`.
    """
    if method not in ROBOT_WORLD_METHODS:
        raise ConventionError(f"unknown robot-world method {method!r}; "
                              f"valid: {', '.join(ROBOT_WORLD_METHODS)}")
    check_number(axis_tol, "axis_tol")
    G, C = _inputs(T_base_gripper, T_cam_target)
    _check_motions(G, axis_tol, "robot_world_hand_eye")
    base2world, gripper2cam = (_shah if method == "shah" else _li)(_transform_inverse(G), C)
    X, Y = _transform_inverse(gripper2cam), _transform_inverse(base2world)
    if refine:
        from .handeye_refine import refine_loop

        X, Y = refine_loop(G, C, X, Y, iterations)
    return Y, X
