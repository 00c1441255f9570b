"""The fused C pass of the collision decisions (``native.capsules_clear``, ``_native_collide.c``) against
the closed-form torch distances of ``diffkin.collision.distances`` entry by entry: random capsules with
degenerate ones among them (points, parallel and crossing segments, zero radius), round world objects and
half-spaces, float32 and float64, margins and slacks of both signs, left-out entries."""

from __future__ import annotations

import pytest
import torch

from diffkin.collision.distances import capsule_capsule, capsule_halfspace
from diffkin.kernels import native

pytestmark = pytest.mark.skipif(not native.available(), reason="the native library is not built here")


def _capsules(G: int, N: int, dtype, g):
    A = torch.rand(G, 3, N, dtype=dtype, generator=g) - 0.5
    B = A + 0.3 * (torch.rand(G, 3, N, dtype=dtype, generator=g) - 0.5)
    B[0] = A[0]  # a point (a sphere)
    B[1] = A[1] + (B[2] - A[2])  # parallel to capsule 2
    r = 0.1 * torch.rand(G, dtype=dtype, generator=g)
    r[3] = 0.0
    return A, B, r


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_every_entry_decides_as_the_torch_distance(dtype):
    g = torch.Generator().manual_seed(3)
    G, N = 6, 700
    A, B, r = _capsules(G, N, dtype, g)
    wa = torch.rand(4, 3, dtype=dtype, generator=g) - 0.5
    wb = wa.clone()
    wb[1:3] += 0.2  # spheres/points (0, 3) and capsules (1, 2)
    wr = torch.tensor([0.05, 0.02, 0.0, 0.0], dtype=dtype)
    hs = torch.tensor([[0.0, 0.0, 1.0, 0.1], [0.6, 0.0, 0.8, -0.2]], dtype=dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    none3, none0 = (A.new_zeros(0, 3),) * 2, A.new_zeros(0)
    checked = 0
    for margin, slack in ((0.0, 0.0), (0.02, 1e-4), (-0.03, 0.0)):
        for i in range(G):
            for j in range(i + 1, G):
                d = capsule_capsule(A[i].T, B[i].T, r[i], A[j].T, B[j].T, r[j])  # (N,)
                ok = torch.ones(N, dtype=torch.bool)
                pair = torch.tensor([[i, j]])
                assert native.capsules_clear(A, B, r, pair, (*none3, none0), A.new_zeros(0, 4), None, None,
                                             margin, slack, ok)
                sure = (d - margin - slack).abs() > tol
                assert torch.equal(ok[sure], (d - margin >= slack)[sure]), (i, j)
                checked += int(sure.sum())
        for w in range(4):
            skip = torch.ones(G, 4, dtype=torch.bool)
            for k in range(G):
                skip[k, w] = False
                d = capsule_capsule(A[k].T, B[k].T, r[k], wa[w], wb[w], wr[w])
                ok = torch.ones(N, dtype=torch.bool)
                assert native.capsules_clear(A, B, r, torch.zeros(0, 2, dtype=torch.long), (wa, wb, wr),
                                             A.new_zeros(0, 4), skip, None, margin, slack, ok)
                sure = (d - margin - slack).abs() > tol
                assert torch.equal(ok[sure], (d - margin >= slack)[sure]), (k, w)
                skip[k, w] = True
        for h in range(2):
            d = capsule_halfspace(A.permute(2, 0, 1), B.permute(2, 0, 1), r, hs[h, :3], hs[h, 3]).amin(-1)
            ok = torch.ones(N, dtype=torch.bool)
            skip_h = torch.ones(G, 2, dtype=torch.bool)
            skip_h[:, h] = False
            assert native.capsules_clear(A, B, r, torch.zeros(0, 2, dtype=torch.long), (*none3, none0), hs,
                                         None, skip_h, margin, slack, ok)
            sure = (d - margin - slack).abs() > tol
            assert torch.equal(ok[sure], (d - margin >= slack)[sure]), h
    assert checked > 10 * N


def test_a_skipped_entry_takes_no_part_and_cuda_is_not_served():
    dtype = torch.float64
    A = torch.zeros(1, 3, 5, dtype=dtype)
    B = A.clone()
    r = torch.tensor([0.1], dtype=dtype)
    inside = (A.new_zeros(1, 3), A.new_zeros(1, 3), A.new_full((1,), 0.1))
    ok = torch.ones(5, dtype=torch.bool)
    native.capsules_clear(A, B, r, torch.zeros(0, 2, dtype=torch.long), inside, A.new_zeros(0, 4), None, None,
                          0.0, 0.0, ok)
    assert not ok.any()
    ok = torch.ones(5, dtype=torch.bool)
    native.capsules_clear(A, B, r, torch.zeros(0, 2, dtype=torch.long), inside, A.new_zeros(0, 4),
                          torch.ones(1, 1, dtype=torch.bool), None, 0.0, 0.0, ok)
    assert ok.all()
    half = A.to(torch.float16)
    assert not native.capsules_clear(half, half, r, torch.zeros(0, 2, dtype=torch.long), inside,
                                     A.new_zeros(0, 4), None, None, 0.0, 0.0, ok)
