"""Issue 30's calibration seams: one measurement reader by header (data_io), the joint count checked against
the robot, one rigidity rule for measured poses, gradient calibration with joint readings that require grad,
calibrate_batch's honesty on degenerate data, the robust loss with its outlier report.

References: the chains' own forward kinematics (the simulated "true" robot), the CLI's error convention.
"""

from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest
import torch

from diffkin import models
from diffkin.calibration import calibrate_from_files, load_measurements
from diffkin.cli import main
from diffkin.errors import DiffkinError, ModelError, ShapeError

F64 = torch.float64


def _cli(*args) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in args])
    return rc, out.getvalue(), err.getvalue()


def _fk_csv(tmp_path, robot: str, n: int = 12):
    """``diffkin fk``'s CSV (header q1..qn,x,y,z,qw,qx,qy,qz) of ``n`` random configurations."""
    path = tmp_path / f"{robot}_measurements.csv"
    rc, _, err = _cli("fk", "--robot", robot, "--random", n, "--seed", 3, "--output", path)
    assert rc == 0, err
    return path


# ------------------------------------------------------------------------------------------ item 1
def test_cli_calibrate_refuses_data_of_another_joint_count(tmp_path):
    data = _fk_csv(tmp_path, "panda")  # 7 joint columns, a 6-joint robot
    rc, out, err = _cli("calibrate", "--robot", "ur5", "--data", data, "--output", tmp_path / "cal.yaml")
    assert rc == 2, out + err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "7" in lines[0] and "6" in lines[0] and "joint" in lines[0], err
    assert not (tmp_path / "cal.yaml").exists()
    with pytest.raises(ShapeError, match=r"7 joint.*6 joints"):
        calibrate_from_files("ur5", data, progress=False)
    np.savez(tmp_path / "m.npz", q=np.zeros((5, 7)), T=np.tile(np.eye(4), (5, 1, 1)))
    with pytest.raises(ShapeError, match=r"7 joint.*6 joints"):
        calibrate_from_files("ur5", tmp_path / "m.npz", progress=False)


# ------------------------------------------------------------------------------------------ item 2
def test_load_measurements_reads_fk_csv_by_header(tmp_path):
    data = _fk_csv(tmp_path, "panda", 9)
    q, T = load_measurements(data)
    assert q.shape == (9, 7) and T.shape == (9, 4, 4)
    chain = models.load("panda", dtype=F64)
    torch.testing.assert_close(chain.forward_kinematics(q).detach(), T, atol=1e-7, rtol=0)
    # the same reader as the CLI's calibrate (calibrate_from_files): the same arrays
    from diffkin.io.data import read_measurements

    q2, T2, position_only = read_measurements(data, n_joints=7)
    assert not position_only
    torch.testing.assert_close(q2, q)
    torch.testing.assert_close(T2, T)
    # positions only: x,y,z without a quaternion
    (tmp_path / "p.csv").write_text("q1,q2,x,y,z\n0.1,0.2,1,2,3\n0.3,0.4,4,5,6\n")
    q, p = load_measurements(tmp_path / "p.csv")
    assert q.shape == (2, 2) and p.shape == (2, 3)
    np.testing.assert_array_equal(p.numpy(), [[1, 2, 3], [4, 5, 6]])
    # a header that names q1..q3 read as a 2-joint robot's data: refused with both counts
    (tmp_path / "q3.csv").write_text("q1,q2,q3,x,y,z\n0,0,0,1,2,3\n")
    with pytest.raises(ShapeError, match=r"3 joint.*2 joints"):
        read_measurements(tmp_path / "q3.csv", n_joints=2)


# ------------------------------------------------------------------------------------------ item 3
def _off_orthonormal(T: torch.Tensor, eps: float, row: int) -> torch.Tensor:
    """``T`` with row ``row``'s rotation scaled by 1 + eps/2: max |RᵀR − I| ≈ eps."""
    T = T.clone()
    T[row, :3, :3] *= 1.0 + eps / 2
    return T


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_rigidity_rule_in_both_dtypes(dtype):
    from diffkin import transforms as tf

    chain = models.load("ur5", dtype=dtype)
    q = chain.random_configuration(8, generator=torch.Generator().manual_seed(4))
    T = chain.forward_kinematics(q).detach()
    assert tf.RIGIDITY_TOLERANCE == 1e-3
    ok = _off_orthonormal(T, 2e-4, 5)  # 2e-4: accepted by every entry point, and re-orthonormalised
    fixed = tf.as_measured_transform(ok)
    R = fixed[..., :3, :3]
    eye = torch.eye(3, dtype=dtype)
    assert float((R.transpose(-1, -2) @ R - eye).abs().max()) < 1e-5
    assert tf.check_transform(ok) is ok
    base = tf.as_rigid_transform(ok[5], "base", dtype)
    assert float((base[:3, :3].T @ base[:3, :3] - eye).abs().max()) < 1e-5
    bad = _off_orthonormal(T, 3e-3, 5)  # beyond the one limit: refused by each, naming the index
    for fn in (tf.as_measured_transform, tf.check_transform):
        with pytest.raises(DiffkinError, match=r"T\[5\] is not a rigid transform.*1e-03|T\[5\].*0\.001"):
            fn(bad, "T")
    with pytest.raises(ModelError, match="base is not a rigid transform"):
        tf.as_rigid_transform(bad[5], "base", dtype)


def test_measurement_files_follow_the_rule_and_name_file_and_row(tmp_path):
    chain = models.load("ur5", dtype=F64)
    q = chain.random_configuration(10, generator=torch.Generator().manual_seed(5))
    T = chain.forward_kinematics(q).detach()
    np.savez(tmp_path / "ok.npz", q=q.numpy(), T=_off_orthonormal(T, 2e-4, 3).numpy())
    res = calibrate_from_files(chain, tmp_path / "ok.npz", progress=False, cross_validation=0)
    assert res.residuals[-1] < 1e-4  # accepted and re-orthonormalised, not refused
    rc, out, err = _cli("calibrate", "--robot", "ur5", "--data", tmp_path / "ok.npz", "--cv", "0",
                        "--output", tmp_path / "cal.yaml")
    assert rc == 0, err
    np.savez(tmp_path / "bad.npz", q=q.numpy(), T=_off_orthonormal(T, 3e-3, 7).numpy())
    rc, out, err = _cli("calibrate", "--robot", "ur5", "--data", tmp_path / "bad.npz",
                        "--output", tmp_path / "cal2.yaml")
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "bad.npz" in err and "row 8" in err and "rigid" in err, err
    # the same rule for IK targets read from a file
    np.save(tmp_path / "T.npy", _off_orthonormal(T, 2e-4, 3).numpy())
    rc, out, err = _cli("ik", "--robot", "ur5", "--input", tmp_path / "T.npy", "--num-seeds", "2")
    assert rc == 0, err
    np.save(tmp_path / "T_bad.npy", _off_orthonormal(T, 3e-3, 4).numpy())
    rc, out, err = _cli("ik", "--robot", "ur5", "--input", tmp_path / "T_bad.npy")
    assert rc == 2 and "T_bad.npy: row 5 is not a rigid transform" in err, err


# ------------------------------------------------------------------------------------------ item 4
@pytest.mark.parametrize("robot", ["ur5", "urdf"])
def test_hayati_and_general_calibrations_print_only_diffkin_output(tmp_path, robot):
    from pathlib import Path

    if robot == "urdf":
        urdf = Path(__file__).parent / "data" / "urdf" / "irb2400.urdf"
        chain = models.from_urdf(urdf, "tool0", dtype=F64)
        args = ["--urdf", urdf, "--end-link", "tool0", "--output", tmp_path / "cal.urdf"]
    else:
        chain = models.load(robot, dtype=F64)
        args = ["--robot", robot, "--output", tmp_path / "cal.yaml"]
    q = chain.random_configuration(24, generator=torch.Generator().manual_seed(6))
    np.savez(tmp_path / "m.npz", q=q.numpy(), T=chain.forward_kinematics(q).detach().numpy())
    rc, out, err = _cli("calibrate", "--data", tmp_path / "m.npz", "--cv", "0", *args)
    assert rc == 0, err
    assert ("hayati" if robot == "ur5" else "general") in out
    assert "jit" not in out + err and "deprecated" not in out + err, out + err


# ------------------------------------------------------------------------------------------ item 8
def _perturbed_panda(seed: int):
    chain = models.load("panda", dtype=F64)
    true = chain.copy()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        true.a.add_(1e-3 * (2 * torch.rand(true.a.shape, generator=g, dtype=F64) - 1))
        true.d.add_(1e-3 * (2 * torch.rand(true.d.shape, generator=g, dtype=F64) - 1))
    return chain, true


@pytest.mark.parametrize("method", ["gradient", "least_squares"])
def test_calibrate_with_joint_readings_that_require_grad(method):
    from diffkin.calibration import calibrate, calibrate_batch

    chain, true = _perturbed_panda(7)
    q0 = chain.random_configuration(30, generator=torch.Generator().manual_seed(8))
    T = true.forward_kinematics(q0).detach()
    net = torch.nn.Linear(7, 7, dtype=F64)  # joint readings from a network: they carry a graph
    with torch.no_grad():
        net.weight.copy_(torch.eye(7, dtype=F64))
        net.bias.zero_()
    q = net(q0)
    assert q.requires_grad
    res = calibrate(chain, q, T, method=method, progress=False, cross_validation=0)
    assert res.residuals[-1] < 1e-6, res.residuals[-1]
    assert not res.q.requires_grad and net.weight.grad is None
    out = calibrate_batch(chain, q[None], T[None], method=method, progress=False)
    assert out[0].residuals[-1] < 1e-6


# ------------------------------------------------------------------------------------------ item 9
def test_calibrate_batch_is_as_honest_as_calibrate_on_degenerate_data():
    from diffkin.calibration import calibrate, calibrate_batch

    chain, true = _perturbed_panda(9)
    q = chain.random_configuration(1, generator=torch.Generator().manual_seed(10)).expand(30, 7).clone()
    T = true.forward_kinematics(q).detach()  # one robot, 30 identical poses
    q_good = chain.random_configuration(30, generator=torch.Generator().manual_seed(11))
    T_good = true.forward_kinematics(q_good).detach()
    with pytest.warns(UserWarning, match="determine only 6 of 28"):
        single = calibrate(chain, q, T, progress=False)
    with pytest.warns(UserWarning, match="determine only 6 of 28") as caught:
        batch = calibrate_batch(chain, torch.stack([q_good, q]), torch.stack([T_good, T]), progress=False)
    assert len([w for w in caught if "determine only" in str(w.message)]) == 1  # robot 1 only
    for res in (single, batch[1]):
        assert res.report.rank == 6 and len(res.report.undetermined) == 22
        assert not res.determined
        assert any("determine only 6 of 28" in note for note in res.notes), res.notes
        assert "NOT determined" in res.summary()
    assert batch[0].determined and not any("determine only" in note for note in batch[0].notes)
    # what the warning says, measured: away from the poses the identified robot is not better
    held = chain.random_configuration(40, generator=torch.Generator().manual_seed(12))
    T_held = true.forward_kinematics(held).detach()
    assert batch[0].validation_error(held, T_held)["position_rms"] < 1e-6
    assert batch[1].validation_error(held, T_held)["position_rms"] > 1e-4


# ----------------------------------------------------------------------------------------- item 12
def _outlier_data(seed: int, n_poses: int = 100, sigma_p: float = 5e-5, sigma_o: float = 1e-4):
    """Panda measurements with Gaussian noise (σ per coordinate) and 5 % of the poses' positions off by 5 mm
    (a mis-read target, a bumped reflector): ``(nominal, true, q, T_clean, T_bad, outlier rows)``."""
    from diffkin.rotations import rotvec_to_matrix

    chain, true = _perturbed_panda(seed)
    g = torch.Generator().manual_seed(seed + 100)
    q = chain.random_configuration(n_poses, generator=g)
    T = true.forward_kinematics(q).detach().clone()
    T[:, :3, 3] += sigma_p * torch.randn(n_poses, 3, generator=g, dtype=F64)
    T[:, :3, :3] = rotvec_to_matrix(sigma_o * torch.randn(n_poses, 3, generator=g, dtype=F64)) @ T[:, :3, :3]
    bad = torch.randperm(n_poses, generator=g)[: n_poses // 20]
    direction = torch.nn.functional.normalize(torch.randn(len(bad), 3, generator=g, dtype=F64), dim=-1)
    T_bad = T.clone()
    T_bad[bad, :3, 3] += 5e-3 * direction
    return chain, true, q, T, T_bad, sorted(bad.tolist())


@pytest.mark.parametrize("loss,method", [("huber", "least_squares"), ("cauchy", "least_squares"),
                                         ("cauchy", "gradient")])
def test_robust_loss_resists_5_percent_outliers_of_5_mm(loss, method):
    from diffkin.calibration import calibrate

    noise = (5e-5, 1e-4)
    chain, true, q, T, T_bad, bad = _outlier_data(13)
    held = chain.random_configuration(200, generator=torch.Generator().manual_seed(14))
    T_held = true.forward_kinematics(held).detach()  # the true robot, noise-free: the model's own error
    opts = dict(method=method, measurement_noise=noise, progress=False, cross_validation=0)

    def model_error(res):
        return res.validation_error(held, T_held)["position_rms"]

    with pytest.warns(UserWarning):  # the plain fit of the contaminated data: 2x what the noise explains
        plain = calibrate(chain, q, T_bad, loss="l2", **opts)
    floor = model_error(calibrate(chain, q, T, loss="l2", **opts))  # the noise floor: clean data, plain fit
    robust = calibrate(chain, q, T_bad, loss=loss, **opts)
    assert model_error(robust) <= 1.5 * floor, (model_error(robust), floor)
    assert model_error(plain) > 1.5 * floor, (model_error(plain), floor)
    # the per-pose outlier report names exactly the contaminated poses
    assert robust.loss == loss and robust.outliers == bad, (robust.outliers, bad)
    assert robust.pose_position_errors.shape == (100,)
    assert float(robust.pose_position_errors[bad].min()) > 4e-3
    assert f"{len(bad)} of 100 poses" in robust.summary()


def test_cli_calibrate_loss_flag_reports_the_outliers(tmp_path):
    import json

    chain, true, q, T, T_bad, bad = _outlier_data(15)
    np.savez(tmp_path / "m.npz", q=q.numpy(), T=T_bad.numpy())
    rc, out, err = _cli("calibrate", "--robot", "panda", "--data", tmp_path / "m.npz", "--loss", "cauchy",
                        "--noise", "0.05", str(np.degrees(1e-4)), "--cv", "0", "--output", tmp_path / "rep")
    assert rc == 0, err
    assert f"outliers (cauchy loss): {len(bad)} of 100 poses" in out, out
    assert "fit residual is" not in out + err  # the robust fit's noise check is that of its inliers
    report = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert report["loss"] == "cauchy" and report["outliers"] == bad
    rc, out, err = _cli("calibrate", "--robot", "panda", "--data", tmp_path / "m.npz", "--loss", "tukey",
                        "--output", tmp_path / "c.yaml")
    assert rc == 2 and "tukey" in err


# ----------------------------------------------------------------------------------------- item 14
def test_one_parameter_jacobian_for_every_error_model():
    """The DH model's Φ is the forward-mode derivative of the FK kernel, the very code of the Hayati and
    general models (no hand-written analytic Jacobian beside it), and it matches central differences."""
    from diffkin.calibration import model as dh_model
    from diffkin.calibration.error_models import ChainErrorModel
    from diffkin.calibration.model import CalibrationModel

    assert CalibrationModel.calibration_matrix is ChainErrorModel.calibration_matrix
    assert not hasattr(dh_model, "_so3_right_jacobian")
    chain = models.load("panda", dtype=F64)
    model = CalibrationModel.from_chains(chain, base=True, tool=True)
    g = torch.Generator().manual_seed(16)
    zeta = model.nominal + 0.05 * torch.randn(model.n_params, generator=g, dtype=F64)  # off nominal
    q = chain.random_configuration(5, generator=g)
    Phi, T = model.calibration_matrix(zeta, q, False, 1.0)
    assert Phi.shape == (5, 6, model.n_params)
    from diffkin.calibration.model import pose_residual

    h = 1e-6
    for j in (0, 9, 20, 4 * 7 + 2, 4 * 7 + 4, 4 * 7 + 10):  # a1, alpha3, theta7, base_z, base_ry, tool_ry
        e = torch.zeros(model.n_params, dtype=F64)
        e[j] = h
        # the twist of a parameter step, from the residual of the stepped poses against the stepped-back ones
        plus, minus = (model.forward_kinematics(zeta + s * e, q) for s in (1.0, -1.0))
        fd = pose_residual(minus, plus, 1.0) / (2 * h)
        torch.testing.assert_close(Phi[..., j], fd, atol=1e-6, rtol=1e-6)


# ------------------------------------------------------------------------------- docs list: units
def test_reports_share_one_unit_convention(tmp_path):
    """Console table, parameters.md and summary() give lengths in mm and angles in degrees alike."""
    from diffkin.calibration import calibrate

    chain, true = _perturbed_panda(17)
    q = chain.random_configuration(40, generator=torch.Generator().manual_seed(18))
    T = true.forward_kinematics(q).detach()
    res = calibrate(chain, q, T, progress=False)
    text = res.summary()
    assert "mrad" not in text and "deg" in text and "mm" in text
    md = res.to_markdown().splitlines()[2:]
    for line, row in zip(md, res.display_rows()):
        assert line.startswith(f"| {row[0]} | {row[1]} | {row[2]} | {row[3]} {row[4]} |")
    a2 = next(r for r in res.parameter_table() if r["name"] == "a2")
    shown = next(r for r in res.display_rows() if r[0] == "a2")
    assert float(shown[2]) == pytest.approx(a2["identified"] * 1e3, abs=1e-4) and shown[4] == "mm"
    np.savez(tmp_path / "m.npz", q=q.numpy(), T=T.numpy())
    rc, out, err = _cli("calibrate", "--robot", "panda", "--data", tmp_path / "m.npz", "--cv", "0",
                        "--output", tmp_path / "c.yaml")
    assert rc == 0, err
    assert "lengths mm, angles deg" in " ".join(out.split()) and f"{a2['identified'] * 1e3:.4f}" in out, out
