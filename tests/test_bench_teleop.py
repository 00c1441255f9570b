"""Smoke test of benchmarks/bench_teleop.py: its peers solve the same problem (results only, never time)."""

from __future__ import annotations

import tempfile

import numpy as np
import pytest
import torch

pytest.importorskip("mink")
pytest.importorskip("daqp")
pytest.importorskip("mujoco")

from benchmarks import bench_teleop as bt  # noqa: E402
from diffkin.ik import _native_velocity as nvel  # noqa: E402
from diffkin.models import from_mjcf, from_urdf  # noqa: E402
from diffkin.models.mjcf import compile_mjcf  # noqa: E402

pytestmark = pytest.mark.skipif(not nvel.available(), reason="no C compiler: the fused kernel is not built")


def test_written_urdf_is_the_mjcf_panda():
    """The URDF handed to PlaCo and pink is the Menagerie Panda's arm (diffkin reads both files)."""
    text = bt.panda_arm_urdf(compile_mjcf(bt.PANDA)[0])
    a = from_mjcf(bt.PANDA, "hand", dtype=torch.float64).requires_grad_(False)
    b = from_urdf(text, "hand", dtype=torch.float64).requires_grad_(False)
    q = a.random_configuration(32, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(b.forward_kinematics(q), a.forward_kinematics(q), rtol=0, atol=1e-12)
    torch.testing.assert_close(b.q_limits, a.q_limits, rtol=0, atol=1e-12)


def test_teleop_loop_follows_mink():
    """The C loop and mink's loop over the same moving targets give the same trajectory, and it tracks."""
    chain = from_mjcf(bt.PANDA, "hand", dtype=torch.float64).requires_grad_(False)
    T0 = chain.forward_kinematics(torch.tensor(bt.Q0, dtype=torch.float64)).numpy()
    targets = bt._targets(T0, 400)
    with torch.no_grad():
        _, traj, err, _, _ = bt._diffkin_side(targets)
    _, traj_m, err_m, _ = bt._mink_side(targets)
    np.testing.assert_allclose(traj, traj_m, rtol=0, atol=1e-9)
    assert err < 2e-3 and abs(err - err_m) < 1e-9


def test_placo_and_pink_run_on_the_written_urdf():
    pytest.importorskip("placo")
    pytest.importorskip("pink")
    chain = from_mjcf(bt.PANDA, "hand", dtype=torch.float64).requires_grad_(False)
    T0 = chain.forward_kinematics(torch.tensor(bt.Q0, dtype=torch.float64)).numpy()
    targets = bt._targets(T0, 250)
    with tempfile.NamedTemporaryFile("w", suffix=".urdf") as f:
        f.write(bt.panda_arm_urdf(compile_mjcf(bt.PANDA)[0]))
        f.flush()
        _, err_placo = bt._placo_side(f.name, targets)
        _, err_pink = bt._pink_side(f.name, targets)
    assert err_placo < 0.02 and err_pink < 2e-3  # both follow the 5 cm circle


def test_teleop_profile_parts_run_the_same_loop():
    """benchmarks/teleop_profile.py: the C loop outside Python, NativeVelocity.step and ik.solve_velocity run
    the same 200 steps to the same q (results only, never time)."""
    import argparse
    import shutil

    if not (shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")):
        pytest.skip("no C compiler for the driver")
    from benchmarks import teleop_profile

    rows = teleop_profile.run(argparse.Namespace(steps=200, quick=False))
    assert len(rows) == 4 and all(r["median_us"] > 0 for r in rows)
    assert rows[2]["max_abs_q_diff_vs_c_loop"] == 0.0  # the same C call on the same inputs
    assert rows[3]["max_abs_q_diff_vs_c_loop"] < 1e-12  # q + q̇ Δt in torch against the C integration
