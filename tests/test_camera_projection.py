"""calibration.project_points against cv2.projectPoints (OpenCV's pinhole + k1, k2, p1, p2, k3 model)."""

import numpy as np
import pytest
import torch

from diffkin.calibration import project_points
from diffkin.rotations import rotvec_to_matrix
from diffkin.transforms import make_transform

cv2 = pytest.importorskip("cv2")


def _case(seed, M=30):
    g = np.random.default_rng(seed)
    pts = np.c_[g.uniform(-0.2, 0.2, (M, 2)), g.uniform(-0.05, 0.05, (M, 1))]
    rvec, tvec = g.normal(size=3) * 0.3, np.array([0.05, -0.03, 0.9]) + g.normal(size=3) * 0.05
    K = np.array([[610.0, 0.0, 322.0], [0.0, 605.0, 241.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.28, 0.11, 1.2e-3, -8e-4, -0.02])
    return pts, rvec, tvec, K, dist


@pytest.mark.parametrize("distorted", [False, True])
def test_equals_cv2_project_points(distorted):
    for seed in range(3):
        pts, rvec, tvec, K, dist = _case(seed)
        ref = cv2.projectPoints(pts, rvec, tvec, K, dist if distorted else None)[0][:, 0]
        T = make_transform(rotvec_to_matrix(torch.tensor(rvec)), torch.tensor(tvec))
        d = torch.tensor(dist) if distorted else None
        ours = project_points(torch.tensor(pts), T, torch.tensor(K), d)
        assert np.abs(ours.numpy() - ref).max() < 1e-9


def test_batched_float32_and_gradcheck():
    cases = [_case(s, 12) for s in range(4)]
    pts = torch.tensor(np.stack([c[0] for c in cases]))
    T = make_transform(rotvec_to_matrix(torch.tensor(np.stack([c[1] for c in cases]))),
                       torch.tensor(np.stack([c[2] for c in cases])))
    K, dist = torch.tensor(cases[0][3]), torch.tensor(cases[0][4])
    out = project_points(pts, T, K, dist)
    assert out.shape == (4, 12, 2)
    for k in range(4):
        assert (out[k] - project_points(pts[k], T[k], K, dist)).abs().max() < 1e-12
    f32 = project_points(pts.float(), T.float(), K.float(), dist.float())
    assert f32.dtype == torch.float32 and (f32.double() - out).abs().max() < 1e-2
    args = (pts[0, :5].clone().requires_grad_(), T[0].clone().requires_grad_(), K.clone().requires_grad_(),
            dist.clone().requires_grad_())
    assert torch.autograd.gradcheck(project_points, args)


def test_bad_shapes():
    pts, rvec, tvec, K, dist = _case(0)
    T = make_transform(rotvec_to_matrix(torch.tensor(rvec)), torch.tensor(tvec))
    with pytest.raises(ValueError, match="dist_coeffs"):
        project_points(torch.tensor(pts), T, torch.tensor(K), torch.tensor(dist[:4]))
    with pytest.raises(ValueError):
        project_points(torch.tensor(pts[:, :2]), T, torch.tensor(K))
