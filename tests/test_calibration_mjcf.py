"""calibration.calibrate (the least-squares path) on an MJCF chain: a MuJoCo Panda whose body frames and joint
axes are perturbed generates the measurements (poses by MuJoCo's own mj_kinematics, never by the code under
test); the calibrated chain reaches the noise floor, predicts held-out poses of the perturbed robot, and its
``to_mjcf`` file, compiled by MuJoCo, has the calibrated chain's kinematics."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin import calibration
from diffkin.errors import ModelError
from diffkin.models import from_mjcf

mujoco = pytest.importorskip("mujoco")
from mjcf_util import compile_with_stand_in_assets  # noqa: E402

PANDA = Path(__file__).parent / "data" / "mjcf" / "franka_emika_panda" / "panda.xml"
F64 = torch.float64


def _mujoco_poses(model, chain, q: torch.Tensor, body: str = "hand") -> torch.Tensor:
    """``(N, 4, 4)`` world poses of ``body`` by MuJoCo's FK at the chain's ``to_qpos(q)``."""
    data = mujoco.MjData(model)
    qpos = chain.to_qpos(q).detach().numpy()
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    out = np.tile(np.eye(4), (len(q), 1, 1))
    for i, row in enumerate(qpos):
        data.qpos[:] = row
        mujoco.mj_kinematics(model, data)
        out[i, :3, :3] = data.xmat[bid].reshape(3, 3)
        out[i, :3, 3] = data.xpos[bid]
    return torch.from_numpy(out)


def _perturbed(tmp_path: Path):
    """The 'real' robot: the Panda with its body frames shifted (±3 mm) and tilted (±5 mrad) and its joint
    axes tilted, written by to_mjcf and compiled by MuJoCo."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        real = from_mjcf(PANDA, "hand", dtype=F64)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        real.body_pos.add_(3e-3 * (2 * torch.rand(real.body_pos.shape, generator=g, dtype=F64) - 1))
        real.body_quat.add_(5e-3 * (2 * torch.rand(real.body_quat.shape, generator=g, dtype=F64) - 1))
        real.joint_axis.add_(5e-3 * (2 * torch.rand(real.joint_axis.shape, generator=g, dtype=F64) - 1))
    path = tmp_path / "panda_real.xml"
    real.to_mjcf(path)
    return real, compile_with_stand_in_assets(path)


def _real_and_nominal(tmp_path: Path):
    """The perturbed robot compiled by MuJoCo, and the nominal MJCF chain."""
    _, real_model = _perturbed(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return real_model, from_mjcf(PANDA, "hand", dtype=F64)


def test_least_squares_calibration_of_an_mjcf_panda(tmp_path):
    real_model, nominal = _real_and_nominal(tmp_path)
    g = torch.Generator().manual_seed(1)
    q = nominal.random_configuration(60, generator=g)
    q_test = nominal.random_configuration(200, generator=g)
    sigma = 2e-5  # m: per-axis position noise; orientation noise 2e-5 rad
    T = _mujoco_poses(real_model, nominal, q)
    T_test = _mujoco_poses(real_model, nominal, q_test)
    noisy = T.clone()
    noisy[:, :3, 3] += sigma * torch.randn(60, 3, generator=g, dtype=F64)
    before = (nominal.forward_kinematics(q_test)[:, :3, 3] - T_test[:, :3, 3]).norm(dim=-1)
    assert before.mean() > 3e-3  # the perturbation is far above the noise

    result = calibration.calibrate(nominal, q, noisy[:, :3, 3], method="least_squares",
                                   measurement_noise=(sigma,))  # positions (N, 3): position-only
    assert result.error_model == "general" and result.converged
    rank = result.report.rank
    assert rank == result.report.structural_rank and not result.report.undetermined
    assert 4 * 7 < rank < 4 * 7 + 6  # fewer than a full pose's 4n + 6 (the tool orientation is not seen)
    # the fit residual is the noise's: RMS |e| ≈ σ √3 · √(1 − rank / (3N)) (degrees of freedom)
    floor = sigma * np.sqrt(3 * (1 - rank / 180))
    assert 0.8 * floor < result.residuals[-1] < 1.2 * floor
    assert 0.8 < result.noise_ratio < 1.25
    with torch.no_grad():
        after = (result.chain.forward_kinematics(q_test)[:, :3, 3] - T_test[:, :3, 3]).norm(dim=-1)
    assert after.max() < 10 * sigma and after.mean() < 3 * sigma
    # the calibrated file, compiled by MuJoCo, has the calibrated chain's kinematics
    out = tmp_path / "panda_calibrated.xml"
    result.chain.to_mjcf(out)
    T_file = _mujoco_poses(compile_with_stand_in_assets(out), result.chain, q_test)
    with torch.no_grad():
        torch.testing.assert_close(result.chain.forward_kinematics(q_test), T_file, atol=1e-10, rtol=0)


def test_full_pose_calibration_and_error_model_choices(tmp_path):
    real_model, nominal = _real_and_nominal(tmp_path)
    g = torch.Generator().manual_seed(2)
    q = nominal.random_configuration(40, generator=g)
    T = _mujoco_poses(real_model, nominal, q)
    result = calibration.calibrate(nominal, q, T)  # noise-free full poses: an exact fit
    assert result.report.rank == 4 * 7 + 6  # 4n + 6 identifiable parameters of a 7R arm (full pose)
    assert result.residuals[-1] < 1e-9 and result.orientation_residuals[-1] < 1e-9
    q_test = nominal.random_configuration(50, generator=g)
    with torch.no_grad():
        torch.testing.assert_close(result.chain.forward_kinematics(q_test),
                                   _mujoco_poses(real_model, nominal, q_test), atol=1e-8, rtol=0)
    assert type(result.chain) is type(nominal)
    with pytest.raises(ModelError, match="an MJCF chain uses 'general'"):
        calibration.calibrate(nominal, q, T, error_model="dh")


def test_calibrate_from_files_writes_the_mjcf(tmp_path):
    """An MJCF path through the one loader: calibrated.xml, compiled by MuJoCo, has the real robot's poses."""
    real_model, nominal = _real_and_nominal(tmp_path)
    g = torch.Generator().manual_seed(3)
    q = nominal.random_configuration(40, generator=g)
    np.savez(tmp_path / "meas.npz", q=q.numpy(), T=_mujoco_poses(real_model, nominal, q).numpy())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = calibration.calibrate_from_files(PANDA, tmp_path / "meas.npz", end_link="hand",
                                                  out_dir=tmp_path / "out", progress=False)
    assert type(result.chain).__name__ == "MJCFChain"
    written = compile_with_stand_in_assets(tmp_path / "out" / "calibrated.xml")
    q_test = nominal.random_configuration(30, generator=g)
    want = _mujoco_poses(real_model, nominal, q_test)
    torch.testing.assert_close(_mujoco_poses(written, nominal, q_test), want, atol=1e-8, rtol=0)
