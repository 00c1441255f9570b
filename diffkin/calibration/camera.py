"""The pinhole camera with OpenCV's distortion model (k1, k2, p1, p2, k3): the projection of
:func:`cv2.projectPoints`, batched and differentiable (the measurement model of camera-based calibration).

A point p = (X, Y, Z) in the camera frame (z forward) has normalised coordinates x = X/Z, y = Y/Z; with
r² = x² + y², the distorted ones are

    x'' = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
    y'' = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y

and the pixel is u = f_x x'' + c_x, v = f_y y'' + c_y (the camera matrix [[f_x, 0, c_x], [0, f_y, c_y],
[0, 0, 1]]; as OpenCV, its skew entry is not used).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import ShapeError
from ..transforms import _transform_points
from ..validation import broadcast_batch, shape_str, tensors

__all__ = ["project_points"]


def _project(p: Tensor, K: Tensor, dist: Tensor | None) -> Tensor:
    """Camera-frame points (..., M, 3) -> pixels (..., M, 2); K (..., 3, 3), dist (..., 5) or None."""
    xy = p[..., :2] / p[..., 2:3]
    if dist is not None:
        k1, k2, p1, p2, k3 = (dist[..., i, None] for i in range(5))
        x, y = xy.unbind(-1)
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy = torch.stack((x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                          y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y), -1)
    f = torch.stack((K[..., 0, 0], K[..., 1, 1]), -1)[..., None, :]
    c = torch.stack((K[..., 0, 2], K[..., 1, 2]), -1)[..., None, :]
    return xy * f + c


def project_points(points: Tensor, T_cam_points: Tensor, camera_matrix: Tensor,
                   dist_coeffs: Tensor | None = None) -> Tensor:
    """Pixels of ``points (..., M, 3)`` given in a frame whose pose in the camera frame is
    ``T_cam_points (..., 4, 4)``: ``(..., M, 2)``, as ``cv2.projectPoints(points, rvec, tvec, camera_matrix,
    dist_coeffs)``. ``camera_matrix (..., 3, 3)``; ``dist_coeffs (..., 5)`` = (k1, k2, p1, p2, k3) or None
    (no distortion). Batch dims broadcast; differentiable in every argument (points behind the camera,
    Z <= 0, give meaningless pixels as in OpenCV)."""
    points, T, K, dist = tensors(("points", points, (3,)), ("T_cam_points", T_cam_points, (4, 4)),
                                 ("camera_matrix", camera_matrix, (3, 3)), ("dist_coeffs", dist_coeffs, None))
    if points.ndim < 2:
        raise ShapeError(f"expected points of shape (..., M, 3), got {shape_str(points.shape)}")
    if dist is not None and (dist.ndim < 1 or dist.shape[-1] != 5):
        raise ShapeError(f"expected dist_coeffs of shape (..., 5) = (k1, k2, p1, p2, k3), got "
                         f"{shape_str(dist.shape)}")
    broadcast_batch(("points", points, 2), ("T_cam_points", T, 2), ("camera_matrix", K, 2),
                    ("dist_coeffs", dist, 1))
    return _project(_transform_points(T[..., None, :, :], points), K, dist)
