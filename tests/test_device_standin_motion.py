"""The newer modules on a device: each case of :mod:`benchmarks.cuda_smoke` (motion.plan's torch search with
the optimisation stage and its gradients, time_optimal, cylinders and convex meshes, World.stack,
read_world / MoveIt scenes, a convex robot, retarget.clip and metrics, solve_velocity with tasks and limits,
hand-eye and camera calibration, the vector envs) twice:

* ``test_as_on_cuda``: the CPU stand-in of :func:`test_device_standin.as_on_cuda` (native kernels off, the
  default device ``meta``: a tensor made without ``device=`` raises or lands off the inputs' device), the
  outputs on the CPU in the reference's dtypes and equal to the ordinary CPU call's within the case's
  tolerance;
* ``test_cuda_matches_cpu``: the same call on ``cuda`` against the CPU call (skipped without CUDA; what
  ``python -m benchmarks.cuda_smoke --device cuda`` prints line by line).

The cases, inputs and tolerances live in ``benchmarks/cuda_smoke.py`` (one encoding for the tests and the
script). A case needing an optional package (cv2, gymnasium, mujoco) is skipped without it.
"""

from __future__ import annotations

import pytest
import torch
from test_device_standin import check_as_on_cuda

from benchmarks import cuda_smoke as smoke

PARAMS = [pytest.param(c, dt, id=f"{c.name}-{str(dt).removeprefix('torch.')}")
          for c in smoke.CASES for dt in c.dtypes]


def _needs(case):
    for m in case.needs:
        pytest.importorskip(m)


@pytest.mark.parametrize("case,dtype", PARAMS)
def test_as_on_cuda(case, dtype):
    _needs(case)
    check_as_on_cuda(case.make("cpu", dtype), atol=case.atol[dtype])


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("case,dtype", PARAMS)
def test_cuda_matches_cpu(case, dtype):
    _needs(case)
    smoke.run_case(case, "cuda", dtype)

