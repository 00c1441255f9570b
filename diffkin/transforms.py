"""Homogeneous transformations (textbook §2.7) and the pose error of CLIK (§3.7.3).

A transform ``T`` is a (..., 4, 4) tensor [[R, p], [0, 1]] (2.42); leading batch dims are free and
broadcast where two transforms meet. Public functions check their input by the rule of
:mod:`diffkin.validation`; the private kernels (``_name``) skip the checks for hot loops.
"""

from __future__ import annotations

from functools import reduce

import torch
from torch import Tensor

from ._numerics import eps_for
from .errors import ConventionError, DiffkinError, DTypeError, ModelError, NonFiniteError, ShapeError
from .kernels.rigid import _make_transform, _pose_error, _transform_inverse, _transform_points
from .validation import as_tensor, broadcast_batch, check_trailing, shape_str, tensors

__all__ = [
    "make_transform",
    "split_transform",
    "identity_transform",
    "transform_inverse",
    "compose",
    "transform_points",
    "pose_error",
    "check_transform",
    "as_rigid_transform",
    "as_measured_transform",
    "MEASURED_TRANSFORM_ATOL",
    "RIGIDITY_TOLERANCE",
    "POSE_ERROR_ORIENTATIONS",
]

#: The one rigidity rule for transforms that come from outside — measured or target poses (calibration data,
#: IK targets, pose files), a model's fixed base / tool, :func:`check_transform`'s input: the largest of
#: max |RᵀR − I|, |det R − 1| and the bottom row's deviation from [0, 0, 0, 1] must be at most this, the same
#: limit in float32 and float64 (tracker exports rounded to a few decimals, float32 casts and
#: quaternion-to-matrix round-off all stay well below it). Within it a transform is accepted and, where a
#: function returns one (:func:`as_measured_transform`, :func:`as_rigid_transform`, the readers of
#: :mod:`diffkin.io.data`), re-orthonormalised: the rotation replaced by the nearest one, the bottom row set
#: to [0, 0, 0, 1]; beyond it refused with an error naming the first offending index (or file and row), the
#: deviation and this limit.
RIGIDITY_TOLERANCE = 1e-3
#: the former name of :data:`RIGIDITY_TOLERANCE` (kept for one release)
MEASURED_TRANSFORM_ATOL = RIGIDITY_TOLERANCE

POSE_ERROR_ORIENTATIONS = ("axis_angle", "quaternion", "rotvec")  # the kernel's forms


class RigidTransformShapeError(ModelError, ShapeError):
    """A fixed transform of a model (base, tool, URDF origin) is not (4, 4)."""


class RigidTransformDTypeError(ModelError, DTypeError):
    """A fixed transform of a model holds no float numbers."""


class RigidTransformNonFiniteError(ModelError, NonFiniteError):
    """A fixed transform of a model holds NaN or inf."""


def make_transform(R: Tensor, p: Tensor) -> Tensor:
    """Homogeneous transform [[R, p], [0^T, 1]] (2.42): (..., 3, 3), (..., 3) -> (..., 4, 4).

    Batch dims of R and p broadcast. R is not checked for orthonormality (see :func:`check_transform`).
    """
    R, p = tensors(("R", R, (3, 3)), ("p", p, (3,)))
    broadcast_batch(("R", R, 2), ("p", p, 1))
    return _make_transform(R, p)


def split_transform(T: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation and translation of T: (..., 4, 4) -> (R (..., 3, 3), p (..., 3)) (views of T)."""
    (T,) = tensors(("T", T, (4, 4)))
    return T[..., :3, :3], T[..., :3, 3]


def identity_transform(
    batch_shape: tuple[int, ...] | int = (), dtype: torch.dtype | None = None, device=None
) -> Tensor:
    """Identity transforms of shape (*batch_shape, 4, 4)."""
    if isinstance(batch_shape, int):
        batch_shape = (batch_shape,)
    eye = torch.eye(4, dtype=dtype, device=device)
    return eye.expand(*batch_shape, 4, 4).clone()


def transform_inverse(T: Tensor) -> Tensor:
    """Inverse [[R^T, -R^T p], [0^T, 1]] of a rigid transform (2.45): (..., 4, 4) -> (..., 4, 4)."""
    return _transform_inverse(tensors(("T", T, (4, 4)))[0])


def compose(*Ts: Tensor) -> Tensor:
    """Product T_1 T_2 ... T_k of transforms (2.47), batch dims broadcast: k x (..., 4, 4) -> (..., 4, 4).

    Also works for (..., 3, 3) rotation matrices (composition (2.15)) if all arguments are 3 x 3.
    """
    if not Ts:
        raise DiffkinError("compose() needs at least one transform")
    Ts = tensors(*((f"Ts[{i}]", T, None) for i, T in enumerate(Ts)))
    size = 3 if Ts[0].ndim >= 1 and Ts[0].shape[-1] == 3 else 4
    for i, T in enumerate(Ts):
        check_trailing(T, (size, size), f"Ts[{i}]")
    broadcast_batch(*((f"Ts[{i}]", T, 2) for i, T in enumerate(Ts)))
    return reduce(torch.matmul, Ts)


def transform_points(T: Tensor, points: Tensor) -> Tensor:
    """p^0 = o + R p^1 (2.38) for each point: (..., 4, 4), (..., 3) -> (..., 3), batch dims broadcast.

    For N points per transform, pass ``T[..., None, :, :]`` with points (..., N, 3).
    """
    T, points = tensors(("T", T, (4, 4)), ("points", points, (3,)))
    broadcast_batch(("T", T, 2), ("points", points, 1))
    return _transform_points(T, points)


def pose_error(T_desired: Tensor, T_current: Tensor, orientation: str = "axis_angle") -> Tensor:
    """Pose error [p_d - p_e; e_O] in the base frame: (..., 4, 4), (..., 4, 4) -> (..., 6).

    Position part (3.78). Orientation part from R_d R_e^T (3.84): ``"axis_angle"`` e_O = r sin(theta)
    (3.83)/(3.85); ``"rotvec"`` e_O = theta r; ``"quaternion"`` e_O = Delta eps = r sin(theta/2) (3.91).
    For small errors the first two are ~ theta r and the quaternion form is ~ theta r / 2 (half the size:
    scale its gain by 2 to compare).
    """
    if orientation not in POSE_ERROR_ORIENTATIONS:
        raise ConventionError(
            f"unknown orientation error {orientation!r}; valid: {', '.join(POSE_ERROR_ORIENTATIONS)}"
        )
    T_desired, T_current = tensors(("T_desired", T_desired, (4, 4)), ("T_current", T_current, (4, 4)))
    broadcast_batch(("T_desired", T_desired, 2), ("T_current", T_current, 2))
    return _pose_error(T_desired, T_current, orientation)


def check_transform(T, name: str = "T", atol: float | None = None) -> Tensor:
    """Check that T is a batch of rigid transforms in SE(3) (2.42) and return it unchanged.

    Raises ``ShapeError`` unless T is (..., 4, 4), ``NonFiniteError`` for NaN/inf, and ``DiffkinError``
    when R^T R != I, det R != 1 or the bottom row is not [0, 0, 0, 1] beyond ``atol`` (default
    :data:`RIGIDITY_TOLERANCE`, 1e-3 in either dtype), naming the first offending index. Synchronises with
    the device. A tensor is returned as it is; numbers and numpy arrays are converted
    (:mod:`diffkin.validation`).
    """
    (T,) = tensors((name, T, (4, 4)))
    _transform_deviations(T, name, RIGIDITY_TOLERANCE if atol is None else atol)
    return T


def _transform_deviations(T: Tensor, name: str, atol: float, where=None,
                          error: type[DiffkinError] = DiffkinError) -> tuple[float, float]:
    """Raise ``error`` unless every transform of ``T (..., 4, 4)`` is rigid to ``atol`` (the rule of
    :data:`RIGIDITY_TOLERANCE`); return the largest deviations of the bottom row and of RᵀR from I.

    ``where(index) -> str`` names a transform by its batch index (default ``name[i, j]``; the file readers
    name the file and row). One host sync when all is well.
    """
    if T.numel() == 0:
        return 0.0, 0.0
    R = T[..., :3, :3]
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    dev = torch.stack((
        (T[..., 3, :] - bottom).abs().amax(-1),
        (R.transpose(-1, -2) @ R - eye).abs().amax((-1, -2)),
        (torch.linalg.det(R) - 1.0).abs(),
    ), dim=-1)  # fmt: skip
    worst = dev.reshape(-1, 3).amax(0).tolist()
    if all(w <= atol for w in worst):  # NaN fails too
        return worst[0], worst[1]
    whats = ("bottom row is not [0, 0, 0, 1]", "rotation block is not orthonormal (R^T R != I)",
             "rotation block has det != 1")
    k = next(i for i, w in enumerate(worst) if not w <= atol)
    bad = ~(dev[..., k] <= atol)
    index = tuple(int(i) for i in bad.nonzero()[0].tolist()) if bad.ndim else ()
    label = where(index) if where is not None else (
        f"{name}[{', '.join(map(str, index))}]" if index else name)
    w = float(dev[index][k]) if index else float(dev[k])
    raise error(f"{label} is not a rigid transform: {whats[k]} (deviation {w:.3g} > {atol:g}, the "
                "tolerance of diffkin.transforms.RIGIDITY_TOLERANCE)")


def _nearest_rigid(T: Tensor, bottom_dev: float, orth_dev: float) -> Tensor:
    """``T`` with exactly orthonormal rotations (polar factor U Vᵀ of R = U S Vᵀ) and bottom row [0, 0, 0, 1];
    ``T`` itself when it is exact already (deviations of a few eps)."""
    if T.numel() == 0 or (orth_dev <= 4.0 * eps_for(T) and bottom_dev == 0.0):
        return T
    U, _, Vh = torch.linalg.svd(T[..., :3, :3])
    out = T.clone()
    out[..., :3, :3] = U @ Vh
    out[..., 3, :] = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    return out


def as_measured_transform(T: Tensor, name: str = "T", atol: float | None = None) -> Tensor:
    """Validate measured or target poses ``(..., 4, 4)`` and return them with exactly orthonormal rotations.

    The rule of :data:`RIGIDITY_TOLERANCE` (``atol`` default 1e-3, either dtype): deviations within it are
    accepted, worse ones refused (``DiffkinError`` naming the first offending index and the deviation). The
    rotation blocks are replaced by the nearest rotation (polar factor U Vᵀ of the SVD R = U S Vᵀ) and the
    bottom row by [0, 0, 0, 1]; already exact inputs are returned unchanged (same object).
    """
    (T,) = tensors((name, T, (4, 4)))
    return _nearest_rigid(T, *_transform_deviations(T, name, RIGIDITY_TOLERANCE if atol is None else atol))


def as_rigid_transform(T, name: str, dtype: torch.dtype, device=None) -> Tensor:
    """Validate a fixed ``(4, 4)`` rigid transform (base, tool, URDF origin) and return a tensor copy in
    ``dtype``/``device`` (a float32 or float64 tensor is converted: the caller names the dtype), by the rule
    of :data:`RIGIDITY_TOLERANCE` (re-orthonormalised within it).

    Errors are :class:`~diffkin.errors.ModelError` s, and also the shared validators' ``ShapeError``,
    ``DTypeError`` (integer, bool, complex or half-precision data) or ``NonFiniteError`` where they apply.
    """
    try:
        T = as_tensor(T, name, dtype=dtype, device=device)  # a tensor: checked, not converted
    except DTypeError as exc:
        raise RigidTransformDTypeError(str(exc)) from None
    T = T.to(dtype=dtype, device=device).clone()
    if T.shape != (4, 4):
        raise RigidTransformShapeError(
            f"{name} must be a (4, 4) homogeneous transform, got {shape_str(T.shape)}"
        )
    if not bool(torch.isfinite(T).all()):
        raise RigidTransformNonFiniteError(f"{name} holds NaN or inf; expected a rigid transform")
    return _nearest_rigid(T, *_transform_deviations(T, name, RIGIDITY_TOLERANCE, error=ModelError))
