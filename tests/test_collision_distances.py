"""Signed distances of the collision primitives against coal (thousands of random pairs, penetration
included), against dense sampling where a primitive has no coal counterpart, gradcheck in float64 and
finite values and gradients on degenerate geometry."""

from __future__ import annotations

import collision_reference as ref
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from diffkin.collision import (
    box,
    box_box,
    box_halfspace,
    capsule_box,
    capsule_capsule,
    capsule_halfspace,
    point_box,
    sphere_box,
    sphere_capsule,
    sphere_sphere,
)

N = 2000
F64 = torch.float64


def _random(seed: int, n: int = N):
    """Random capsules (a, b, r) and boxes (c, R, h) in a 0.6 m cube: ~10-20 % of pairs penetrate."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    c = (u(n, 3) - 0.5) * 0.6
    d = (u(n, 3) - 0.5) * u(n, 1) * 0.6
    R = torch.from_numpy(Rotation.random(n, random_state=seed).as_matrix())
    return c - d, c + d, u(n) * 0.15, (u(n, 3) - 0.5) * 0.6, R, u(n, 3) * 0.25


def _coal_capsule(a, b, r, i):
    return ref.capsule(a[i].numpy(), b[i].numpy(), r[i].item())


def _coal_box(c, R, h, i):
    return ref.box(c[i].numpy(), R[i].numpy(), h[i].numpy())


def _check(ours: torch.Tensor, theirs: list[float], tol: float = 1e-9) -> None:
    theirs = np.asarray(theirs)
    assert (theirs < 0).mean() > 0.05 and (theirs > 0).mean() > 0.3  # both regimes are exercised
    np.testing.assert_allclose(ours.detach().numpy(), theirs, atol=tol, rtol=0)


def test_capsule_capsule_against_coal():
    a, b, r, *_ = _random(0)
    a2, b2, r2, *_ = _random(1)
    d = capsule_capsule(a, b, r, a2, b2, r2)
    _check(d, [ref.distance(*_coal_capsule(a, b, r, i), *_coal_capsule(a2, b2, r2, i)) for i in range(N)])


def test_sphere_sphere_and_sphere_capsule_against_coal():
    a, b, r, *_ = _random(2)
    c, _, rs, *_ = _random(3)
    d = sphere_capsule(c, rs, a, b, r)
    _check(d, [ref.distance(*_coal_capsule(c, c, rs, i), *_coal_capsule(a, b, r, i)) for i in range(N)])
    d = sphere_sphere(c, rs, a, r)
    _check(d, [ref.distance(*_coal_capsule(c, c, rs, i), *_coal_capsule(a, a, r, i)) for i in range(N)])


def test_capsule_and_sphere_box_against_coal():
    a, b, r, c, R, h = _random(4)
    d = capsule_box(a, b, r, c, R, h)
    _check(d, [ref.distance(*_coal_capsule(a, b, r, i), *_coal_box(c, R, h, i)) for i in range(N)])
    d = sphere_box(a, r, c, R, h)
    _check(d, [ref.distance(*_coal_capsule(a, a, r, i), *_coal_box(c, R, h, i)) for i in range(N)])


def test_box_box_against_coal():
    _, _, _, c, R, h = _random(5)
    _, _, _, c2, R2, h2 = _random(6)
    d = box_box(c, R, h, c2, R2, h2)
    _check(d, [ref.distance(*_coal_box(c, R, h, i), *_coal_box(c2, R2, h2, i)) for i in range(N)], 1e-8)


def test_halfspaces_against_coal():
    a, b, r, c, R, h = _random(7)
    g = torch.Generator().manual_seed(7)
    n = torch.nn.functional.normalize(torch.randn(N, 3, dtype=F64, generator=g), dim=-1)
    off = torch.rand(N, dtype=F64) * 0.3 - 0.4
    hs = [ref.halfspace(n[i].numpy(), off[i].item()) for i in range(N)]
    want = [ref.distance(*_coal_capsule(a, b, r, i), *hs[i]) for i in range(N)]
    _check(capsule_halfspace(a, b, r, n, off), want)
    _check(box_halfspace(c, R, h, n, off), [ref.distance(*_coal_box(c, R, h, i), *hs[i]) for i in range(N)])


def _dense_segment(a, b, k=4001):
    t = torch.linspace(0, 1, k, dtype=F64)
    return a + t[:, None] * (b - a)


def test_point_box_and_degenerate_capsule_box_against_sampling():
    """Points (no coal primitive) against the box's exact distance field sampled on a dense segment."""
    a, b, _, c, R, h = _random(8, 50)
    for i in range(50):
        pts = _dense_segment(a[i], b[i])
        brute = point_box(pts, c[i], R[i], h[i]).min()
        seg = capsule_box(a[i], b[i], torch.zeros((), dtype=F64), c[i], R[i], h[i])
        if brute > 0:  # apart: the minimum over the segment (sampling is accurate to the grid's spacing)
            assert abs(seg.item() - brute.item()) < 1e-6
        else:  # in contact: at least as deep as the deepest sampled point
            assert seg.item() <= brute.item() + 1e-12


DEGENERATE = {
    "coincident centres": ([0.1, 0.2, 0.3], [0.1, 0.2, 0.3], [0.1, 0.2, 0.3], [0.1, 0.2, 0.3]),
    "coincident axes": ([0, 0, 0], [0, 0, 1.0], [0, 0, 0], [0, 0, 1.0]),
    "parallel overlapping": ([0, 0, 0], [0, 0, 1.0], [0.1, 0, 0.5], [0.1, 0, 1.5]),
    "parallel disjoint": ([0, 0, 0], [0, 0, 1.0], [0.1, 0, 1.5], [0.1, 0, 2.5]),
    "antiparallel": ([0, 0, 0], [0, 0, 1.0], [0.1, 0, 1.0], [0.1, 0, 0.0]),
    "crossing": ([-1.0, 0, 0], [1.0, 0, 0], [0, -1.0, 0], [0, 1.0, 0]),
    "point on axis": ([0, 0, 0], [0, 0, 1.0], [0, 0, 0.5], [0, 0, 0.5]),
    "both degenerate apart": ([0, 0, 0], [0, 0, 0], [0.3, 0, 0], [0.3, 0, 0]),
}


@pytest.mark.parametrize("case", list(DEGENERATE))
@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("radius", [0.0, 0.05])
def test_degenerate_capsules_finite_and_match_coal(case, dtype, radius):
    a0, a1, b0, b1 = (torch.tensor(v, dtype=dtype, requires_grad=True) for v in DEGENERATE[case])
    r = torch.tensor(radius, dtype=dtype, requires_grad=True)
    d = capsule_capsule(a0, a1, r, b0, b1, r)
    grads = torch.autograd.grad(d, (a0, a1, b0, b1, r))
    assert torch.isfinite(d) and all(torch.isfinite(g).all() for g in grads)
    want = ref.distance(*ref.capsule(a0.detach().double(), a1.detach().double(), radius),
                        *ref.capsule(b0.detach().double(), b1.detach().double(), radius))
    assert abs(d.item() - want) < (1e-6 if dtype == torch.float32 else 1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_degenerate_boxes_finite(dtype):
    """Zero half extents, a capsule along a box edge and through the centre, coincident boxes."""
    h = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.2], [0.1, 0.1, 0.1]], dtype=dtype, requires_grad=True)
    c = torch.zeros(3, 3, dtype=dtype, requires_grad=True)
    R = torch.eye(3, dtype=dtype).expand(3, 3, 3)
    a = torch.tensor([[0.1, 0.1, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]], dtype=dtype, requires_grad=True)
    b = torch.tensor([[0.1, 0.1, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]], dtype=dtype, requires_grad=True)
    r = torch.zeros(3, dtype=dtype, requires_grad=True)
    out = torch.stack((capsule_box(a, b, r, c, R, h), box_box(c, R, h, c, R, h), point_box(a, c, R, h)))
    grads = torch.autograd.grad(out.sum(), (a, b, r, c, h))
    assert torch.isfinite(out).all() and all(torch.isfinite(g).all() for g in grads)
    assert out[1, 2].item() == pytest.approx(-0.2, abs=1e-6)  # coincident cubes: one full side deep


def _gradcheck(fn, *args):
    args = [x.detach().clone().requires_grad_(True) for x in args]
    assert torch.autograd.gradcheck(fn, args, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradcheck_float64():
    a, b, r, c, R, h = _random(9, 6)
    a2, b2, r2, c2, R2, h2 = _random(10, 6)
    _gradcheck(capsule_capsule, a, b, r, a2, b2, r2)
    _gradcheck(sphere_capsule, a, r, a2, b2, r2)
    _gradcheck(lambda a, b, r, c, h: capsule_box(a, b, r, c, R, h), a, b, r, c, h)
    _gradcheck(lambda c, h, c2, h2: box_box(c, R, h, c2, R2, h2), c, h, c2, h2)
    n = torch.nn.functional.normalize(torch.randn(6, 3, dtype=F64), dim=-1)
    _gradcheck(lambda a, b, r: capsule_halfspace(a, b, r, n, torch.zeros(6, dtype=F64)), a, b, r)
    _gradcheck(lambda c, h: box_halfspace(c, R, h, n, torch.zeros(6, dtype=F64)), c, h)


def test_box_rotation_gradient_against_finite_differences():
    """d/d rpy of capsule–box through collision.box (rotations are not free parameters of gradcheck)."""
    a, b, r, c, _, h = _random(11, 8)
    rpy = torch.rand(8, 3, dtype=F64, requires_grad=True)
    f = lambda rpy: capsule_box(a, b, r, *_box_tensors(c, h, rpy)).sum()  # noqa: E731
    g = torch.autograd.grad(f(rpy), rpy)[0]
    eps = 1e-6
    fd = torch.stack([(f(rpy + eps * e) - f(rpy - eps * e)) / (2 * eps) for e in torch.eye(3, dtype=F64)], -1)
    torch.testing.assert_close(g.sum(0), fd.detach(), atol=1e-6, rtol=1e-5)


def _box_tensors(c, h, rpy):
    B = box(c, h, rpy)
    return B.center, B.rotation, B.half_extents


def test_float32_matches_float64_and_broadcasts():
    a, b, r, c, R, h = _random(12, 64)
    d64 = capsule_box(a[:, None], b[:, None], r[:, None], c[None, :8], R[None, :8], h[None, :8])
    d32 = capsule_box(*(x.float() for x in (a[:, None], b[:, None], r[:, None], c[None, :8], R[None, :8],
                                            h[None, :8])))
    assert d64.shape == (64, 8) and d32.dtype == torch.float32
    torch.testing.assert_close(d32.double(), d64, atol=2e-6, rtol=0)
    dc = capsule_capsule(a[:, None], b[:, None], r[:, None], a[None, :5], b[None, :5], r[None, :5])
    assert dc.shape == (64, 5)


def test_box_constructor():
    B = box([[0, 0, 0], [1, 0, 0]], [0.1, 0.2, 0.3], rpy=[0, 0, np.pi / 2], dtype=F64)
    assert B.center.shape == (2, 3) and B.rotation.shape == (2, 3, 3) and B.center.dtype == F64
    want = Rotation.from_euler("xyz", [0, 0, np.pi / 2]).as_matrix()
    np.testing.assert_allclose(B.rotation[0].numpy(), want, atol=1e-15)
    with pytest.raises(ValueError, match="half_extents"):
        box([0, 0, 0], [-0.1, 0.1, 0.1])


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    a, b, r, c, R, h = _random(13, 256)
    cpu = torch.stack((capsule_capsule(a, b, r, c, c + 0.1, r), capsule_box(a, b, r, c, R, h),
                       box_box(c, R, h, a, R.flip(0), h.flip(0))))
    gpu = torch.stack((capsule_capsule(*(x.cuda() for x in (a, b, r, c, c + 0.1, r))),
                       capsule_box(*(x.cuda() for x in (a, b, r, c, R, h))),
                       box_box(*(x.cuda() for x in (c, R, h, a, R.flip(0), h.flip(0))))))
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-10, rtol=0)
