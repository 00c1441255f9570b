"""benchmarks/native_profile.py on a tiny batch: the dumped call runs in the C driver outside Python, the
flop count is the kernel's arithmetic, and (with valgrind) the instruction count is read back."""

from __future__ import annotations

import argparse
import shutil

import pytest
import torch

from benchmarks import native_profile as prof
from diffkin import models
from diffkin.kernels import native

pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler: the native kernel isn't built")


def test_profile_rows_on_a_tiny_batch():
    args = argparse.Namespace(batch=64, reps=1, trials=1, callgrind=shutil.which("valgrind") is not None)
    rows = prof.run(args)
    assert [(r["call"], r["dtype"]) for r in rows] == [("FK", "float32"), ("FK + J", "float32"),
                                                      ("FK", "float64"), ("FK + J", "float64")]
    for r in rows:
        assert r["ns/pose (native)"] > 0 and r["ns/pose (avx2)"] > 0 and r["M/s 1 thread"] > 0
        if args.callgrind:  # more than the FMA bound: an AVX2 FMA of 8 floats is 16 flops
            assert r["instr/pose (AVX2)"] > r["flops/pose"] / 16


def test_pose_flops_counts_the_kernels_arithmetic():
    """A serial chain of revolute joints with identity fixed transforms: per joint m q + b (2), sin/cos (36)
    and the turn of x, y (18); the Jacobian adds 24 per joint; a pure translation Pre adds 9 + 6 per
    non-zero offset (P . A with A's rotation the identity: one product per column and row)."""
    chain = models.load("panda", dtype=torch.float64)
    with torch.no_grad():
        model = chain._native_model(torch.zeros(1, 7, dtype=torch.float64))
    fk, fkj = prof.pose_flops(model, False), prof.pose_flops(model, True)
    assert fkj - fk == 7 * 24
    pre = model.reals[torch.float64]["pre"].view(7, 3, 4)
    offsets = int((pre[:, :, 3] != 0).sum())
    assert fk == 7 * (2 + 36 + 18) + 7 * 9 + 6 * offsets
