"""Calibration error models beyond the DH table (issue 14): Hayati's β for parallel axes, the general
per-joint origin model of URDF chains, identifiability with few poses, honest convergence, the noise check,
measured poses rounded to 6 decimals.

The simulated truths lie outside the DH family: every joint origin of the manufacturer URDF is perturbed by
±1 mm and ±0.1° (uniform, all six coordinates) and the encoder zeros by ±0.1°; the measurements are the
perturbed URDF's FK at q + offset (the diffkin URDF model, itself checked against an independent reference
in tests/test_urdf_models.py). Robots: UR5 (axes 2-3-4 parallel; nominal: its DH table, or its URDF), ABB IRB
2400 (axes 2-3 parallel; nominal: the URDF) and Franka Panda (URDF).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import pytest
import torch

from diffkin import DHChain, models
from diffkin.calibration import calibrate, calibrate_batch, identifiability
from diffkin.errors import DiffkinError, ModelError
from diffkin.kernels.joints import pose_correction
from diffkin.models import from_urdf
from diffkin.rotations import rotvec_to_matrix

F64 = torch.float64
ROOT = Path(__file__).resolve().parents[1]
URDF = {
    "ur5": (ROOT / "diffkin/models/data/ur5.urdf", "tool0"),
    "irb2400": (ROOT / "tests/data/urdf/irb2400.urdf", "tool0"),
    "panda": (ROOT / "diffkin/models/data/panda.urdf", "panda_link8"),
}
NOISE = (2e-5, math.radians(0.005))  # 0.02 mm, 0.005° per coordinate


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def nominal_urdf(robot: str):
    path, end = URDF[robot]
    return from_urdf(path, end, dtype=F64)


def ur5_dh() -> DHChain:
    """The UR5 DH table with the URDF's base_link as base (T_base_link_tool0 = Rz(π) · T_dh)."""
    chain = models.load("ur5", dtype=F64)
    chain.base = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=F64))
    return chain


def truth(robot: str, seed: int):
    """(perturbed URDF chain, encoder offsets (n,))."""
    chain = nominal_urdf(robot)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        chain.origin_xyz += 1e-3 * (2 * torch.rand(chain.origin_xyz.shape, generator=g, dtype=F64) - 1)
        chain.origin_rpy += math.radians(0.1) * (2 * torch.rand(chain.origin_rpy.shape, generator=g,
                                                                dtype=F64) - 1)
    offsets = math.radians(0.1) * (2 * torch.rand(chain.n_joints, generator=g, dtype=F64) - 1)
    return chain, offsets


def measure(true, offsets, q, noise=None, seed=0):
    with torch.no_grad():
        T = true.forward_kinematics(q + offsets).clone()
    if noise is not None:
        g = torch.Generator().manual_seed(seed)
        T[:, :3, 3] += noise[0] * torch.randn(q.shape[0], 3, generator=g, dtype=F64)
        T[:, :3, :3] = rotvec_to_matrix(noise[1] * torch.randn(q.shape[0], 3, generator=g, dtype=F64)) @ \
            T[:, :3, :3]
    return T


def configs(chain, n, seed):
    return chain.random_configuration((n,), generator=torch.Generator().manual_seed(seed))


def held_out(chain, true, offsets, seed=99, n=300):
    q = configs(true, n, seed)
    with torch.no_grad():
        err = (chain.forward_kinematics(q) - true.forward_kinematics(q + offsets))[:, :3, 3].norm(dim=-1)
    return float(err.square().mean().sqrt()), float(err.max())


# ------------------------------------------------------------------------------- exact error models
@pytest.mark.parametrize("robot", ["ur5", "irb2400", "panda"])
def test_general_model_recovers_a_perturbed_urdf_exactly(robot, tmp_path):
    nominal = nominal_urdf(robot)
    true, off = truth(robot, seed=1)
    q = configs(nominal, 60, seed=2)
    res = calibrate(nominal, q, measure(true, off, q), base=True, tool=True, progress=False,
                    cross_validation=0)
    assert res.error_model == "general" and type(res.chain) is type(nominal) and res.converged
    before, _ = held_out(nominal, true, off)
    rms, mx = held_out(res.chain, true, off)
    assert before > 1e-3 and mx <= 1e-9  # ≤ 1e-6 mm
    # minimal model: 4 per revolute joint + 6 (base and tool); the rest is reported as redundant
    assert res.report.rank == 4 * nominal.n_joints + 6 and not res.report.undetermined
    assert all("at every configuration" in res.report.reasons[nm] for nm in res.report.unidentifiable)
    # the result is a URDF that loads back with the same kinematics
    path = tmp_path / f"{robot}_calibrated.urdf"
    res.chain.to_urdf(path)
    again = from_urdf(path, URDF[robot][1], dtype=F64)
    qt = configs(nominal, 20, seed=3)
    with torch.no_grad():
        assert (again.forward_kinematics(qt) - res.chain.forward_kinematics(qt)).abs().max() < 1e-12
    assert nominal.origin_delta is None  # nominal untouched


def test_hayati_on_the_ur5_dh_table_is_exact_and_keeps_its_kind(tmp_path):
    nominal = ur5_dh()
    true, off = truth("ur5", seed=4)
    q = configs(true, 60, seed=5)
    res = calibrate(nominal, q, measure(true, off, q), base=True, tool=True, progress=False,
                    cross_validation=0)
    assert res.error_model == "hayati" and isinstance(res.chain, DHChain) and res.converged
    assert {"beta2", "beta3"} <= set(res.names) and "d2" not in res.names and "d3" not in res.names
    assert held_out(res.chain, true, off)[1] <= 1e-9
    text = res.chain.to_yaml(tmp_path / "ur5_cal.yaml")
    assert "beta" in text
    again = DHChain.from_yaml(tmp_path / "ur5_cal.yaml", dtype=F64)
    qt = configs(true, 20, seed=6)
    with torch.no_grad():
        assert (again.forward_kinematics(qt) - res.chain.forward_kinematics(qt)).abs().max() < 1e-12
    # the plain DH table cannot represent the tilted parallel axes
    res_dh = calibrate(nominal, q, measure(true, off, q), base=True, tool=True, progress=False,
                       error_model="dh", cross_validation=0)
    assert held_out(res_dh.chain, true, off)[0] > 1e-4


@pytest.mark.parametrize("method", ["least_squares", "gradient"])
def test_position_only_with_unknown_tracker_frame(method):
    """A tracker (laser tracker / SMR) sees one point on the tool; its frame relative to the robot base is
    unknown (a few cm and degrees). The nominal point is off the flange axis: a point on a joint axis cannot
    show rotations about it (identifiability at the nominal would freeze them)."""
    nominal = nominal_urdf("panda")
    nominal.tool = pose_correction(torch.tensor([0.01, 0.02, 0.1, 0.0, 0.0, 0.0], dtype=F64))
    true, off = truth("panda", seed=7)
    with torch.no_grad():
        true.base = pose_correction(torch.tensor([0.04, -0.03, 0.02, 0.02, 0.03, 0.05], dtype=F64))
        true.tool = pose_correction(torch.tensor([0.011, 0.021, 0.101, 0.0, 0.0, 0.0], dtype=F64))
    q = configs(nominal, 80, seed=8)
    P = measure(true, off, q)[:, :3, 3]
    res = calibrate(nominal, q, P, method=method, base=True, tool=True, progress=False, cross_validation=0)
    assert res.position_only and res.converged
    qt = configs(nominal, 200, seed=9)
    with torch.no_grad():
        err = (res.chain.forward_kinematics(qt) - true.forward_kinematics(qt + off))[:, :3, 3].norm(dim=-1)
    assert float(err.max()) <= (1e-9 if method == "least_squares" else 1e-7)
    assert any(nm.startswith("tool_r") for nm in res.report.unidentifiable)  # a point has no orientation


# ------------------------------------------------------------------------------- the noise check
def test_noise_warning_fires_for_dh_on_the_ur5_and_not_for_auto():
    nominal = ur5_dh()
    true, off = truth("ur5", seed=10)
    q = configs(true, 100, seed=11)
    T = measure(true, off, q, NOISE, seed=12)
    with pytest.warns(UserWarning, match="cannot represent the robot"):
        bad = calibrate(nominal, q, T, base=True, tool=True, error_model="dh", measurement_noise=NOISE,
                        progress=False)
    assert bad.noise_ratio > 2.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        good = calibrate(nominal, q, T, base=True, tool=True, measurement_noise=NOISE, progress=False)
    assert good.error_model == "hayati" and 0.7 < good.noise_ratio < 1.3
    cv = good.cross_validation
    assert cv["folds"] == 5 and cv["position_rms"] < 3 * math.sqrt(3) * NOISE[0]
    assert held_out(good.chain, true, off)[0] < 0.5 * held_out(bad.chain, true, off)[0]
    assert "cross-validated" in good.summary()


def test_calibrate_batch_general_equals_single():
    nominal = nominal_urdf("irb2400")
    qs, Ts = [], []
    for k in range(2):
        true, off = truth("irb2400", seed=20 + k)
        q = configs(nominal, 40, seed=30 + k)
        qs.append(q)
        Ts.append(measure(true, off, q))
    batch = calibrate_batch(nominal, torch.stack(qs), torch.stack(Ts), method="least_squares", base=True,
                            tool=True, progress=False)
    for k in range(2):
        one = calibrate(nominal, qs[k], Ts[k], base=True, tool=True, progress=False, cross_validation=0)
        assert torch.allclose(batch[k].identified, one.identified, atol=1e-12)
        assert isinstance(batch[k].chain, type(nominal))


# ---------------------------------------------------------------------------------- few poses
@pytest.mark.parametrize("robot, n_poses, rank", [("panda_dh", 3, 18), ("ur5_dh", 1, 6)])
def test_rank_with_fewer_equations_than_parameters(robot, n_poses, rank):
    chain = models.load(robot.removesuffix("_dh"), dtype=F64)
    q = configs(chain, n_poses, seed=40)
    rep = identifiability(chain, q)
    assert rep.rank == rank  # the pose rows' full rank: every equation counts
    assert rep.undetermined and rep.more_poses_needed >= 1
    assert rep.structural_rank > rank and "more" in rep.summary()
    # the structurally identifiable parameters are estimated (minimum-norm), not frozen at nominal
    true = chain.copy()
    with torch.no_grad():
        true.a += 1e-3
        true.theta += 1e-3
    T = true.forward_kinematics(q)
    with pytest.warns(UserWarning, match=f"determines? only {rank} of {rep.structural_rank}"):
        res = calibrate(chain, q, T, progress=False)
    moved = [r["name"] for r in res.parameter_table() if abs(r["delta"]) > 1e-12]
    assert set(moved) & set(rep.undetermined)
    assert res.residuals[-1] < 1e-10  # the poses themselves are fitted
    qv = configs(chain, 200, seed=41)
    before = res.nominal_chain.forward_kinematics(qv)[:, :3, 3] - true.forward_kinematics(qv)[:, :3, 3]
    after = res.chain.forward_kinematics(qv)[:, :3, 3] - true.forward_kinematics(qv)[:, :3, 3]
    assert float(after.detach().norm(dim=-1).mean()) < float(before.detach().norm(dim=-1).mean())


# ------------------------------------------------------------------------------ honest convergence
def test_converged_only_when_the_stopping_rule_is_met():
    nominal = nominal_urdf("irb2400")
    true, off = truth("irb2400", seed=50)
    q = configs(nominal, 30, seed=51)
    T = measure(true, off, q)
    kw = dict(base=True, tool=True, progress=False, cross_validation=0)
    assert not calibrate(nominal, q, T, max_iterations=1, **kw).converged
    assert not calibrate(nominal, q, T, method="gradient", optimizer="adam", max_iterations=20,
                         **kw).converged
    assert not calibrate(nominal, q, T, method="gradient", max_iterations=1, **kw).converged
    # another robot's data: the fit cannot explain it; whatever the stopping rule says, the noise check warns
    other = nominal_urdf("ur5")
    with torch.no_grad():
        T_other = other.forward_kinematics(q)
    with pytest.warns(UserWarning, match="measurement noise"):
        res = calibrate(nominal, q, T_other, method="gradient", measurement_noise=NOISE, **kw)
    assert res.noise_ratio > 100


# --------------------------------------------------------------------------- measurement files
def test_six_decimal_poses_are_accepted_and_reorthonormalised():
    from diffkin.ik import solve

    nominal = nominal_urdf("irb2400")
    true, off = truth("irb2400", seed=60)
    q = configs(nominal, 40, seed=61)
    T6 = torch.round(measure(true, off, q) * 1e6) / 1e6
    dev = (T6[:, :3, :3].mT @ T6[:, :3, :3] - torch.eye(3, dtype=F64)).abs().max()
    assert 1.5e-7 < dev < 1e-5  # beyond the old 1.5e-7 tolerance
    res = calibrate(nominal, q, T6, base=True, tool=True, progress=False, cross_validation=0)
    assert res.converged and held_out(res.chain, true, off)[0] < 5e-6
    out = solve(true, T6[:3])  # IK accepts the same six-decimal poses and reaches them
    assert bool(out.success.all())
    reached = true.forward_kinematics(out.q).detach()
    assert float((reached[:, :3, 3] - T6[:3, :3, 3]).norm(dim=-1).max()) < 1e-4
    bad = T6.clone()
    bad[0, 0, 0] += 1e-2  # beyond the one rigidity tolerance (1e-3)
    with pytest.raises(DiffkinError, match=r"T\[0\] is not a rigid transform.*deviation"):
        calibrate(nominal, q, bad, progress=False)
    with pytest.raises(DiffkinError, match=r"T_target\[0\] is not a rigid transform.*deviation"):
        solve(true, bad[:3])


def test_error_model_choice_is_checked():
    with pytest.raises(ModelError, match="URDF"):
        calibrate(ur5_dh(), torch.zeros(5, 6, dtype=F64), torch.eye(4, dtype=F64).expand(5, 4, 4),
                  error_model="general")
    with pytest.raises(ModelError, match="general"):
        calibrate(nominal_urdf("ur5"), torch.zeros(5, 6, dtype=F64), torch.eye(4, dtype=F64).expand(5, 4, 4),
                  error_model="hayati")
    with pytest.raises(ModelError, match="unknown error_model"):
        calibrate(ur5_dh(), torch.zeros(5, 6, dtype=F64), torch.eye(4, dtype=F64).expand(5, 4, 4),
                  error_model="best")
