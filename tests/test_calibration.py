"""Kinematic calibration (§2.11): measurement model, iterated least squares (2.85)–(2.89), gradient descent,
identifiability, pose selection, batch calibration, input checks.

References: forward kinematics of :class:`DHChain` (the simulated "true" robot), torch.func.jacfwd and
central finite differences for Φ, numpy's SVD for the condition number, torch.autograd.gradcheck.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from diffkin import DHChain
from diffkin.calibration import (
    CalibrationModel,
    calibrate,
    calibrate_batch,
    calibrate_from_files,
    calibration_loss,
    identifiability,
    robust_loss,
    select_poses,
    validation_error,
)
from diffkin.calibration.model import _dh_frames, _frames_to_matrix, pose_residual
from diffkin.errors import DiffkinError, DTypeError, ModelError, NonFiniteError, ShapeError
from diffkin.rotations import rotvec_to_matrix

PI = math.pi
F64 = torch.float64


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """The calibration problems are many small ops: intra-op threads only add overhead (10x on a busy
    2-core machine). Restored after the module."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def panda() -> DHChain:  # Franka's modified-DH table to the flange
    lower = [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]
    upper = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]
    return DHChain(
        [0, 0, 0, 0.0825, -0.0825, 0, 0.088],
        [0, -PI / 2, PI / 2, PI / 2, -PI / 2, PI / 2, PI / 2],
        [0.333, 0, 0.316, 0, 0.384, 0, 0.107],
        [0] * 7,
        convention="modified",
        q_limits=list(zip(lower, upper)),
        name="panda",
        dtype=F64,
    )


def ur5() -> DHChain:  # standard DH
    return DHChain(
        [0, -0.425, -0.39225, 0, 0, 0],
        [PI / 2, 0, 0, PI / 2, -PI / 2, 0],
        [0.089159, 0, 0, 0.10915, 0.09465, 0.0823],
        [0] * 6,
        name="ur5",
        dtype=F64,
    )


def stanford() -> DHChain:  # textbook Table 2.? style, prismatic joint 3, with base and tool transforms
    base = torch.eye(4, dtype=F64)
    base[:3, 3] = torch.tensor([0.1, -0.2, 0.05], dtype=F64)
    tool = torch.eye(4, dtype=F64)
    tool[:3, 3] = torch.tensor([0.0, 0.01, 0.12], dtype=F64)
    return DHChain(
        [0, 0, 0, 0, 0, 0],
        [-PI / 2, PI / 2, 0, -PI / 2, PI / 2, 0],
        [0.4, 0.15, 0.3, 0, 0, 0.1],
        [0] * 6,
        joint_types="RRPRRR",
        base=base,
        tool=tool,
        name="stanford",
        dtype=F64,
    )


def perturbed(chain, seed, free_names=None, mm=2.0, deg=0.2, **sel):
    """The 'true' robot: nominal ± mm / ± deg (uniform) on the given (default: identifiable) parameters."""
    model = CalibrationModel.from_chains(chain, **sel)
    g = torch.Generator().manual_seed(seed)
    u = 2 * torch.rand(model.n_params, generator=g, dtype=F64) - 1
    delta = torch.where(model.is_length(), mm * 1e-3 * u, math.radians(deg) * u)
    mask = (
        torch.tensor([nm in free_names for nm in model.names]) if free_names is not None else model.candidate
    )
    return model.to_chain(model.nominal + delta * mask)


def measure(chain, q, seed=0, pos_noise=0.0, rot_noise=0.0):
    with torch.no_grad():
        T = chain.forward_kinematics(q).clone()
    g = torch.Generator().manual_seed(seed)  # CPU noise, moved to T's device (the same draws on any device)
    T[:, :3, 3] += pos_noise * torch.randn(q.shape[0], 3, generator=g, dtype=F64).to(T.device)
    R_noise = rotvec_to_matrix(rot_noise * torch.randn(q.shape[0], 3, generator=g, dtype=F64)).to(T.device)
    T[:, :3, :3] = R_noise @ T[:, :3, :3]
    return T


def poses(chain, n, seed):
    return chain.random_configuration((n,), generator=torch.Generator().manual_seed(seed))


# ------------------------------------------------------------------------------------------ model
@pytest.mark.parametrize("make", [panda, ur5, stanford])
def test_batched_parameter_fk_matches_chain(make):
    chain = make()
    model = CalibrationModel.from_chains(chain, base=True, tool=True)
    g = torch.Generator().manual_seed(1)
    zeta = model.nominal + 0.05 * torch.randn(3, model.n_params, generator=g, dtype=F64)  # K = 3 tables
    q = chain.random_configuration((3, 5), generator=g)
    T = model.forward_kinematics(zeta, q)
    assert T.shape == (3, 5, 4, 4)
    for k in range(3):
        ref = model.to_chain(zeta[k]).forward_kinematics(q[k]).detach()
        torch.testing.assert_close(T[k], ref, atol=1e-14, rtol=0)
    # the private kernel on its own, against chain FK with all frames
    base = torch.eye(4, dtype=F64) if chain.base is None else chain.base
    frames = _dh_frames(
        chain.a, chain.alpha, chain.d, chain.theta, q[0], chain.revolute_mask, chain.convention, base
    )
    ref_all = chain.forward_kinematics(q[0], all_frames=True).detach()
    for i, f in enumerate(frames[:-1]):
        f = [c.expand(5, 3) for c in f]
        torch.testing.assert_close(_frames_to_matrix(*f).detach(), ref_all[:, i], atol=1e-14, rtol=0)


def _twist_jacobian(model, zeta, q):
    """Reference Φ from torch.func.jacfwd of the FK: [dp; vee(dR Rᵀ)] per parameter."""
    T0 = model.forward_kinematics(zeta, q)
    J = torch.func.jacfwd(lambda z: model.forward_kinematics(z, q))(zeta)  # (N, 4, 4, P)
    W = torch.einsum("nijp,nkj->nikp", J[:, :3, :3], T0[:, :3, :3])
    return torch.cat((J[:, :3, 3], torch.stack((W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]), dim=1)), dim=1)


@pytest.mark.parametrize("make", [panda, ur5, stanford])
def test_calibration_matrix_matches_autograd_and_finite_differences(make):
    chain = make()
    model = CalibrationModel.from_chains(chain, base=True, tool=True)
    g = torch.Generator().manual_seed(2)
    q = chain.random_configuration((6,), generator=g)
    zeta = model.nominal + 0.02 * torch.randn(model.n_params, generator=g, dtype=F64)
    Phi, _ = model.calibration_matrix(zeta, q, position_only=False, orientation_weight=1.0)
    torch.testing.assert_close(Phi, _twist_jacobian(model, zeta, q), atol=1e-13, rtol=0)
    # central finite differences of the position rows
    Phi, _ = model.calibration_matrix(zeta, q, position_only=True, orientation_weight=1.0)
    h = 1e-6
    for j in range(0, model.n_params, 3):
        e = torch.zeros_like(zeta)
        e[j] = h
        fd = (model.forward_kinematics(zeta + e, q) - model.forward_kinematics(zeta - e, q))[:, :3, 3] / (
            2 * h
        )
        torch.testing.assert_close(Phi[..., j], fd, atol=1e-8, rtol=0)


def test_pose_residual_is_base_frame_rotvec():
    from scipy.spatial.transform import Rotation

    g = torch.Generator().manual_seed(3)
    R1 = rotvec_to_matrix(torch.randn(4, 3, generator=g, dtype=F64))
    R2 = rotvec_to_matrix(0.1 * torch.randn(4, 3, generator=g, dtype=F64)) @ R1
    T1, T2 = torch.eye(4, dtype=F64).repeat(4, 1, 1), torch.eye(4, dtype=F64).repeat(4, 1, 1)
    T1[:, :3, :3], T2[:, :3, :3] = R1, R2
    T2[:, :3, 3] = 1.0
    r = pose_residual(T1, T2, orientation_weight=0.5)
    ref = Rotation.from_matrix((R2 @ R1.transpose(-1, -2)).numpy()).as_rotvec()
    np.testing.assert_allclose(r[:, 3:].numpy(), 0.5 * ref, atol=1e-12)
    np.testing.assert_allclose(r[:, :3].numpy(), 1.0, atol=0)


# ------------------------------------------------------------------------------ least squares
@pytest.mark.parametrize(
    "make, options",
    [
        (panda, {}),
        (ur5, {}),
        (stanford, {}),
        (ur5, {"base": True, "tool": True}),
        (panda, {"base": True}),
        (panda, {"position_only": True}),
        (ur5, {"position_only": True, "tool": True}),
    ],
)
def test_exact_recovery_noise_free(make, options):
    chain = make()
    position_only = options.pop("position_only", False)
    q = poses(chain, 60, seed=4)
    report = identifiability(chain, q, position_only=position_only, error_model="dh", **options)
    true = perturbed(chain, seed=5, free_names=report.identifiable, **options)
    T = measure(true, q)
    if position_only:
        T = T[:, :3, 3]
    res = calibrate(chain, q, T, progress=False, error_model="dh", **options)
    assert res.converged
    assert res.report.identifiable == report.identifiable
    model = CalibrationModel.from_chains(true, **options)
    truth = dict(zip(model.names, model.nominal.tolist()))
    truth_bt = {}
    if "base" in options or "tool" in options:  # base/tool corrections relative to the nominal transforms
        for part, ref, est in (("base", chain.base, true.base), ("tool", chain.tool, true.tool)):
            if est is None:
                continue
            D = (torch.eye(4, dtype=F64) if ref is None else ref).inverse() @ est
            from diffkin.rotations import matrix_to_rotvec

            v = torch.cat((D[:3, 3], matrix_to_rotvec(D[:3, :3])))
            truth_bt.update({f"{part}_{s}": float(x) for s, x in zip(("x", "y", "z", "rx", "ry", "rz"), v)})
    truth.update(truth_bt)
    for row in res.parameter_table():
        assert abs(row["identified"] - truth[row["name"]]) < 1e-9, row
    assert res.residuals[0] > 1e-3 and res.residuals[-1] < 1e-12
    v = validation_error(res.chain, poses(chain, 20, 6), measure(true, poses(chain, 20, 6)))
    assert v["position_max"] < 1e-11


@pytest.mark.parametrize("make", [ur5, panda], ids=["ur5-standard", "panda-modified"])
def test_noisy_validation_below_0p2_mm(make):
    chain = make()
    q, qv = poses(chain, 80, seed=7), poses(chain, 100, seed=8)
    report = identifiability(chain, q)
    true = perturbed(chain, seed=9, free_names=report.identifiable)
    T = measure(true, q, seed=10, pos_noise=5e-5, rot_noise=math.radians(0.005))
    Tv = measure(true, qv)
    before = validation_error(chain, qv, Tv)
    res = calibrate(chain, q, T, progress=False)
    after = res.validation_error(qv, Tv)
    assert before["position_rms"] > 2e-3  # several millimetres
    assert after["position_rms"] < 0.2e-3 and after["position_max"] < 0.2e-3
    assert after["orientation_rms"] < before["orientation_rms"] / 20


def test_unidentifiable_parameters_reported_and_left_at_nominal():
    chain = ur5()
    q = poses(chain, 50, seed=11)
    rep = identifiability(chain, q, base=True, error_model="dh")
    # parallel axes 2-3-4: d3 and d4 move the wrist along the same direction as d2; base z / yaw = d1 / theta1
    assert set(rep.unidentifiable) == {"d3", "d4", "base_z", "base_rz"}
    assert rep.dependencies["d3"] == pytest.approx({"d2": 1.0}, abs=1e-9)
    assert rep.dependencies["base_rz"] == pytest.approx({"theta1": 1.0}, abs=1e-9)
    assert "d2" in rep.reasons["d4"] and rep.rank == len(rep.candidates) - 4
    # the truth changes d3 and d4 too: the fit absorbs them into d2 instead of diverging
    true = chain.copy()
    with torch.no_grad():
        true.d[1:4] += torch.tensor([1e-3, 2e-3, -1.5e-3], dtype=F64)
        true.a[1] += 1e-3
    res = calibrate(chain, q, measure(true, q), base=True, progress=False, error_model="dh")
    table = {r["name"]: r for r in res.parameter_table()}
    for name in ("d3", "d4", "base_z", "base_rz"):
        assert table[name]["identified"] == table[name]["nominal"] and not table[name]["identifiable"]
    assert table["d2"]["delta"] == pytest.approx(1.5e-3, abs=1e-10)
    assert res.residuals[-1] < 1e-12
    # position-only data: the flange roll theta6 and twist alpha6 do not move the flange point
    rep_p = identifiability(chain, q, position_only=True, error_model="dh")
    assert {"theta6", "alpha6"} <= set(rep_p.unidentifiable)
    assert "no effect" in rep_p.reasons["theta6"]


def test_observability_indices_and_condition_number():
    chain = panda()
    q = poses(chain, 40, seed=12)
    rep = identifiability(chain, q)
    model = CalibrationModel.from_chains(chain)
    Phi = _twist_jacobian(model, model.nominal, q)
    Phi = torch.cat((Phi[:, :3], 0.1 * Phi[:, 3:]), dim=1).reshape(-1, model.n_params)[:, :28].numpy()
    s = np.linalg.svd(Phi, compute_uv=False)
    assert rep.o1 == pytest.approx(np.exp(np.log(s).mean()) / math.sqrt(40), rel=1e-10)
    assert rep.o3 == pytest.approx(s[-1], rel=1e-10)
    assert rep.condition_number == pytest.approx(np.linalg.cond(Phi / np.linalg.norm(Phi, axis=0)), rel=1e-8)


def test_select_poses_beats_random_subsets():
    chain = ur5()
    cands = poses(chain, 300, seed=13)
    idx = select_poses(chain, cands, 12)
    assert idx.shape == (12,) and len(set(idx.tolist())) == 12
    o1_sel = identifiability(chain, cands[idx]).o1
    g = torch.Generator().manual_seed(14)
    o1_rand = [identifiability(chain, cands[torch.randperm(300, generator=g)[:12]]).o1 for _ in range(10)]
    assert o1_sel > max(o1_rand)


# ----------------------------------------------------------------------------------- gradient
def test_gradient_and_least_squares_agree():
    """Both minimise the same weighted sum of squares: the Huber loss (scale 1 mm) is exactly quadratic for
    the ~0.05 mm residuals at the optimum. They differ only by second-order terms (least squares uses the
    small-angle Φ for the orientation rows, the gradient the exact derivative of the rotation vector, a
    relative difference ~|φ|/2 ≈ 1e-4 on a noise-induced parameter shift ~1e-5) and by the L-BFGS stopping
    rule, so 1e-7 (m or rad) is a safe bound; the validation errors agree to 1 nm."""
    chain = panda()
    q, qv = poses(chain, 60, seed=15), poses(chain, 50, seed=16)
    true = perturbed(chain, seed=17, free_names=identifiability(chain, q).identifiable)
    T = measure(true, q, seed=18, pos_noise=5e-5, rot_noise=math.radians(0.01))
    ls = calibrate(chain, q, T, method="least_squares", progress=False)
    gd = calibrate(chain, q, T, method="gradient", progress=False)
    assert gd.converged
    torch.testing.assert_close(gd.identified, ls.identified, atol=1e-7, rtol=0)
    Tv = measure(true, qv)
    assert (
        abs(gd.validation_error(qv, Tv)["position_rms"] - ls.validation_error(qv, Tv)["position_rms"]) < 1e-9
    )


def test_adam_and_soft_l1_reduce_the_error():
    chain = ur5()
    q, qv = poses(chain, 50, seed=19), poses(chain, 50, seed=20)
    true = perturbed(chain, seed=21, free_names=identifiability(chain, q).identifiable)
    T, Tv = measure(true, q, seed=22, pos_noise=5e-5), measure(true, qv)
    for opts in ({"optimizer": "adam", "max_iterations": 300, "lr": 3e-4}, {"loss": "soft_l1"}):
        res = calibrate(chain, q, T, method="gradient", progress=False, **opts)
        assert res.validation_error(qv, Tv)["position_rms"] < 0.2e-3, opts


def test_robust_loss_resists_outliers():
    """Four gross outliers (17 mm) in 60 poses pull least squares off by > 1 mm, but not the Huber fit."""
    chain = ur5()
    q, qv = poses(chain, 60, seed=70), poses(chain, 50, seed=71)
    true = perturbed(chain, seed=72, free_names=identifiability(chain, q).identifiable)
    T, Tv = measure(true, q, seed=73, pos_noise=5e-5), measure(true, qv)
    T[:4, :3, 3] += 0.01
    ls = calibrate(chain, q, T, progress=False).validation_error(qv, Tv)
    huber = calibrate(chain, q, T, method="gradient", scale=2e-4, progress=False).validation_error(qv, Tv)
    assert ls["position_rms"] > 1e-3 and huber["position_rms"] < 0.1e-3


def test_robust_loss_shapes_and_gradients():
    s = torch.tensor([0.0, 0.25e-6, 1e-6, 4e-6], dtype=F64, requires_grad=True)
    h = robust_loss(s, "huber", 1e-3)
    torch.testing.assert_close(h[:3], s[:3])  # quadratic up to the scale
    assert h[3].item() == pytest.approx(2 * 1e-3 * 2e-3 - 1e-6)
    for loss in ("huber", "cauchy", "soft_l1", "l2"):
        (g,) = torch.autograd.grad(robust_loss(s, loss, 1e-3).sum(), s)
        assert torch.isfinite(g).all()
    c = robust_loss(s, "cauchy", 1e-3)  # c² log(1 + s/c²): ~s near 0, logarithmic beyond
    assert c[3].item() == pytest.approx(1e-6 * math.log(5.0))
    with pytest.raises(DiffkinError, match="unknown loss"):
        robust_loss(s, "tukey", 1.0)


def test_calibration_loss_gradcheck_and_batch():
    chain = ur5()
    model = CalibrationModel.from_chains(chain, base=True, tool=True)
    q = poses(chain, 4, seed=23)
    T = measure(perturbed(chain, seed=24), q)  # includes the exact optimum direction: residual ≠ 0
    params = model.nominal.clone().requires_grad_(True)
    f = lambda p: calibration_loss(p, q, T, model, scale=1e-2)  # noqa: E731
    assert torch.autograd.gradcheck(f, (params,))
    # zero residual: finite (zero) gradient, also through the base/tool rotation vectors at 0
    T0 = measure(chain, q)
    (g,) = torch.autograd.grad(calibration_loss(params, q, T0, model), params)
    assert torch.isfinite(g).all() and g.abs().max() < 1e-12
    batch = torch.stack((model.nominal, model.nominal + 1e-3))
    out = calibration_loss(batch, q.expand(2, -1, -1), torch.stack((T0, T)), model)
    assert out.shape == (2,)
    torch.testing.assert_close(out[1], calibration_loss(model.nominal + 1e-3, q, T, model))


# -------------------------------------------------------------------------------------- batch
@pytest.mark.parametrize("method, atol", [("least_squares", 1e-12), ("gradient", 1e-8)])
def test_batch_equals_single_calibrations(method, atol):
    nominal = ur5()
    K = 3
    q = torch.stack([poses(nominal, 40, seed=30 + k) for k in range(K)])
    free = identifiability(nominal, q[0]).identifiable
    trues = [perturbed(nominal, seed=40 + k, free_names=free) for k in range(K)]
    T = torch.stack([measure(t, q[k], seed=k, pos_noise=5e-5, rot_noise=1e-4) for k, t in enumerate(trues)])
    batch = calibrate_batch(nominal, q, T, method=method, progress=False)
    assert len(batch) == K
    for k in range(K):
        single = calibrate(nominal, q[k], T[k], method=method, progress=False)
        torch.testing.assert_close(batch[k].identified, single.identified, atol=atol, rtol=0)
        torch.testing.assert_close(batch[k].chain.dh_table(), single.chain.dh_table(), atol=atol, rtol=0)
    # K different nominal tables
    noms = [perturbed(nominal, seed=50 + k, mm=1.0, deg=0.1) for k in range(K)]
    res = calibrate_batch(noms, q, T, method="least_squares", progress=False)
    for k in range(K):
        torch.testing.assert_close(res[k].nominal_chain.dh_table(), noms[k].dh_table())
        assert res[k].residuals[-1] < 1e-4


# ---------------------------------------------------------------------------- bad input, misc
def test_bad_input_gets_clear_errors():
    chain = ur5()
    q = poses(chain, 10, seed=60)
    T = measure(chain, q)
    with pytest.raises(ShapeError, match="10 joint vectors but T holds 9"):
        calibrate(chain, q, T[:9], progress=False)
    with pytest.raises(ShapeError, match=r"q of shape \(N, 6\)"):
        calibrate(chain, q[:, :5], T, progress=False)
    with pytest.raises(ShapeError, match=r"\(N, 4, 4\) or positions"):
        calibrate(chain, q, T[:, :3, :], progress=False)
    bad = T.clone()
    bad[3, :3, :3] *= 1.01
    with pytest.raises(DiffkinError, match="not a rigid transform"):
        calibrate(chain, q, bad, progress=False)
    for x, name in ((q.clone(), "q"), (T.clone(), "T")):
        x.view(-1)[5] = float("nan")
        args = (x, T) if name == "q" else (q, x)
        with pytest.raises(NonFiniteError, match=f"{name} contains NaN"):
            calibrate(chain, *args, progress=False)
    with pytest.raises(DTypeError):
        calibrate(chain, q.float(), T, progress=False)
    with pytest.raises(DiffkinError, match="unknown calibration method"):
        calibrate(chain, q, T, method="newton", progress=False)
    with pytest.raises(ModelError, match="unknown calibration parameter"):
        calibrate(chain, q, T, parameters=["a9"], progress=False)
    with pytest.raises(ShapeError, match="calibrate_batch"):
        calibrate(chain, q[None], T[None], progress=False)


def test_input_rule_numpy_empty_mixed_and_options():
    """The shared input rule (diffkin.validation) at calibration's boundary: numpy measurements give the
    tensor result, 0 poses are refused naming the minimum, 0 robots give no results, mixed float dtypes and
    non-finite options are typed errors."""
    chain = ur5()
    q = poses(chain, 12, seed=63).detach()
    T = measure(perturbed(chain, seed=64), q)
    kw = dict(progress=False, cross_validation=0, max_iterations=5)
    ref = calibrate(chain, q, T, **kw)
    res = calibrate(chain, q.numpy(), T.numpy(), **kw)
    torch.testing.assert_close(res.identified, ref.identified, rtol=0, atol=0)
    assert res.q.dtype == F64 and isinstance(res.q, torch.Tensor)
    res32 = calibrate(ur5().to(torch.float32), q.numpy(), T.numpy(), **kw)  # numpy follows the chain
    assert res32.identified.dtype == torch.float32 and res32.residuals[-1] < 1e-4
    # positions as nested lists are numbers too
    pos = calibrate(chain, q.tolist(), T[:, :3, 3].tolist(), **kw)
    assert pos.position_only and pos.residuals[-1] < pos.residuals[0] / 10
    with pytest.raises(ShapeError, match=r"at least 1 measured pose"):
        calibrate(chain, q[:0], T[:0], **kw)
    with pytest.raises(ShapeError, match=r"at least 1 measured pose"):
        validation_error(chain, q[:0], T[:0])
    with pytest.raises(ShapeError, match=r"N >= 1"):
        identifiability(chain, q[:0])
    assert calibrate_batch(chain, q[None].expand(0, 12, 6), T[None].expand(0, 12, 4, 4),
                           progress=False) == []
    with pytest.raises(ShapeError, match="K = 0 robots"):
        calibrate_batch(chain, q[None][:0], T[None], progress=False)
    with pytest.raises(DTypeError, match="float64.*float32|float32.*float64"):
        calibrate(chain, q, T.float(), **kw)
    with pytest.raises(DTypeError, match="float64.*float32|float32.*float64"):
        calibrate_batch(chain, q[None], T[None].float(), progress=False)
    with pytest.raises(DTypeError, match="float16"):
        calibrate(chain, q.half(), T, **kw)
    with pytest.raises(NonFiniteError, match="T contains NaN"):
        calibrate(chain, q.numpy(), np.where(np.eye(4, dtype=bool), np.nan, T.numpy()), **kw)
    for bad in (float("nan"), -0.1, float("inf")):
        with pytest.raises(DiffkinError, match="orientation_weight"):
            calibrate(chain, q, T, orientation_weight=bad, **kw)
    with pytest.raises(DiffkinError, match=r"measurement_noise\[0\]"):
        calibrate(chain, q, T, measurement_noise=(0.0, 1e-3), **kw)
    with pytest.raises(DiffkinError, match="unknown calibration method"):
        calibrate_batch(chain, q[None][:0], T[None][:0], method="newton", progress=False)
    # select_poses: indices checked, numpy candidates follow the chain
    idx = select_poses(chain, q.numpy(), 3)
    assert torch.equal(idx, select_poses(chain, q, 3))
    with pytest.raises(ShapeError, match="distinct indices"):
        select_poses(chain, q, 3, initial=[12])
    with pytest.raises(ShapeError, match="integer in 1..12"):
        select_poses(chain, q, 2.0)


def test_loss_functions_validate_their_input():
    chain = ur5()
    model = CalibrationModel.from_chains(chain)
    q = poses(chain, 5, seed=65).detach()
    T = measure(chain, q)
    ref = calibration_loss(model.nominal, q, T, model)
    assert float(ref) < 1e-20
    torch.testing.assert_close(calibration_loss(model.nominal.numpy(), q.numpy(), T.numpy(), model), ref)
    params = model.nominal.expand(0, -1)
    assert calibration_loss(params, q.expand(0, 5, 6), T.expand(0, 5, 4, 4), model).shape == (0,)
    with pytest.raises(ShapeError, match="at least 1 measured pose"):
        calibration_loss(model.nominal, q[:0], T[:0], model)
    with pytest.raises(ShapeError, match="do not broadcast"):
        calibration_loss(model.nominal.expand(2, -1), q.expand(3, 5, 6), T.expand(2, 5, 4, 4), model)
    with pytest.raises(ShapeError, match=r"\(\.\.\., N, 4, 4\)"):
        calibration_loss(model.nominal, q.expand(3, 5, 6), T, model)  # as many batch dims as q
    with pytest.raises(ShapeError, match="5 joint vectors but T holds 4"):
        calibration_loss(model.nominal, q, T[:4], model)
    with pytest.raises(DTypeError, match="float32"):
        calibration_loss(model.nominal.float(), q, T, model)
    with pytest.raises(NonFiniteError, match="params"):
        calibration_loss(model.nominal + float("nan"), q, T, model)
    with pytest.raises(DiffkinError, match="scale"):
        calibration_loss(model.nominal, q, T, model, scale=0.0)
    s = torch.tensor([0.0, 1e-8, 4e-6], dtype=F64)
    torch.testing.assert_close(robust_loss(s.numpy(), "soft_l1", 1e-3), robust_loss(s, "soft_l1", 1e-3))
    with pytest.raises(DiffkinError, match="negative"):
        robust_loss(-s - 1.0, "soft_l1", 1e-3)  # would be NaN
    with pytest.raises(NonFiniteError, match="sq_norm"):
        robust_loss(s / 0.0, "huber", 1e-3)
    with pytest.raises(DiffkinError, match="scale"):
        robust_loss(s, "huber", float("nan"))
    with pytest.raises(DTypeError):
        robust_loss(s.to(torch.bfloat16), "huber", 1e-3)


def test_nominal_chain_untouched_and_outputs(tmp_path):
    chain = panda()
    before = {k: v.detach().clone() for k, v in chain.state_dict().items() if v is not None}
    q = poses(chain, 30, seed=61)
    T = measure(perturbed(chain, seed=62), q, pos_noise=5e-5)
    res = calibrate(chain, q, T, method="least_squares", progress=False)
    res_g = calibrate(chain, q, T, method="gradient", progress=False, max_iterations=5)
    for k, v in chain.state_dict().items():
        if v is not None:
            assert torch.equal(v, before[k]), k
    assert all(p.grad is None for p in chain.parameters())
    assert res.chain is not chain and res.chain.a.data_ptr() != chain.a.data_ptr()
    assert res_g.iterations <= 5
    png = res.plot_residuals(tmp_path / "res.png")
    held_out = poses(chain, 6, seed=66).detach()
    T_held = measure(perturbed(chain, seed=62), held_out).numpy()  # numpy held-out poses by the input rule
    assert res.plot_residuals(tmp_path / "held.png", held_out.numpy(), T_held).stat().st_size > 1000
    with pytest.raises(ShapeError, match="6 joint vectors but T holds 5"):
        res.plot_residuals(tmp_path / "bad.png", held_out, T_held[:5])
    assert png.stat().st_size > 1000
    md = res.to_markdown()
    assert md.count("\n") == len(res.names) + 1 and "| a4 |" in md
    assert "condition number" in res.summary()
    # file entry point (used by the CLI): npz with q and T, outputs under out_dir
    np.savez(tmp_path / "meas.npz", q=q.numpy(), T=T.numpy())
    res_f = calibrate_from_files(chain, tmp_path / "meas.npz", out_dir=tmp_path / "out", progress=False)
    torch.testing.assert_close(res_f.identified, res.identified)
    assert {p.name for p in (tmp_path / "out").iterdir()} >= {"parameters.md", "report.json", "residuals.png"}


def test_float32_least_squares():
    chain = ur5().float()
    q = poses(chain, 60, seed=63)
    true = perturbed(ur5(), seed=64, free_names=identifiability(ur5(), q.double()).identifiable)
    T = measure(true, q.double()).float()
    res = calibrate(chain, q, T, progress=False)
    assert res.chain.dtype == torch.float32
    assert res.validation_error(q, T)["position_rms"] < 2e-6


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_batch():
    chain = ur5().cuda()
    q = poses(chain, 40, seed=65)
    T = measure(perturbed(ur5(), seed=66).cuda(), q)
    for method in ("least_squares", "gradient"):
        res = calibrate_batch(
            chain, q.expand(2, -1, -1), T.expand(2, -1, -1, -1), method=method, progress=False
        )
        assert res[0].chain.a.device.type == "cuda" and res[0].residuals[-1] < 1e-5
