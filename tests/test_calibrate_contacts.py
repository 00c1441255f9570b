"""calibrate_contacts (issue 38 item 4): a probe tip on fixed spheres or planes, distance residuals, the
robot's geometry with the fixtures' unknown geometry, against the known truth of synthetic contacts.

Truth: the nominal robot with every identifiable parameter perturbed by up to ±1 mm / ±0.1° (uniform). The
contacts are postures of the true robot moved onto the true fixture (or off it by Gaussian noise σ, the
probe's trigger noise), checked here with numpy. The fitted robot is compared with the truth by its tip
positions at held-out postures after the best rigid (or, where the scale is reported unidentifiable, similar)
alignment of the two point sets (Kabsch / Umeyama, numpy): contacts cannot tell where the base is relative to
the fixtures, and the report says so.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from diffkin.calibration import CalibrationResult, calibrate_contacts
from diffkin.calibration.contact_model import on_fixtures
from diffkin.calibration.error_models import build_model
from diffkin.errors import ConventionError, DiffkinError, NonFiniteError, OptionError, ShapeError
from diffkin.models import from_urdf
from tests.helpers import panda

F64 = torch.float64
ROOT = Path(__file__).resolve().parents[1]
TIP = (0.0, 0.0, 0.1)


def perturbed(nominal, seed=1):
    """The true robot: every candidate of the error model moved by up to ±1 mm / ±0.1°."""
    model, _ = build_model(nominal)
    g = torch.Generator().manual_seed(seed)
    zeta = model.nominal.clone()
    length = model.is_length()
    for j in model.candidate.nonzero().flatten().tolist():
        u = 2 * float(torch.rand((), generator=g, dtype=F64)) - 1
        zeta[j] += u * (1e-3 if length[j] else math.radians(0.1))
    return model.to_chains(zeta[None])[0]


def contacts(true, surface, fixtures, n, sigma, seed=2):
    """``(q (n, dof), fixture (n,))``: postures of ``true`` whose tip is off its fixture (``fixtures (F, 4)``,
    spheres [c, r] / planes [n, d]) by N(0, σ²), checked with numpy."""
    F = fixtures.shape[0]
    g = torch.Generator().manual_seed(seed)
    q = true.random_configuration(3 * n, generator=g)
    fixture = torch.arange(3 * n) % F
    noise = sigma * torch.randn(3 * n, generator=g, dtype=F64)
    target = fixtures[fixture].clone()
    target[:, 3] += noise  # a sphere of radius r + ε, a plane shifted by ε
    tip = torch.tensor(TIP, dtype=F64)
    q, on = on_fixtures(true, tip, surface, target, q, torch.arange(3 * n))
    q, fixture, noise = q[on][:n], fixture[on][:n], noise[on][:n]
    assert q.shape[0] == n
    p = tips(true, q)
    f = fixtures[fixture].numpy()
    if surface == "sphere":
        d = np.linalg.norm(p - f[:, :3], axis=1) - f[:, 3]
    else:
        d = (p * f[:, :3]).sum(1) - f[:, 3]
    np.testing.assert_allclose(d, noise.numpy(), atol=1e-9)
    return q, fixture


def tips(chain, q) -> np.ndarray:
    with torch.no_grad():
        T = chain.forward_kinematics(q)
    return (T[:, :3, :3] @ torch.tensor(TIP, dtype=F64) + T[:, :3, 3]).numpy()


def aligned_rms(a: np.ndarray, b: np.ndarray, scale: bool = False) -> float:
    """RMS of a − (s R b + t) after the best rigid (``scale``: similarity) fit (Umeyama 1991)."""
    ma, mb = a.mean(0), b.mean(0)
    A, B = a - ma, b - mb
    U, S, Vt = np.linalg.svd(A.T @ B)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = (S * np.diag(D)).sum() / (B**2).sum() if scale else 1.0
    return float(np.sqrt(((A - s * B @ R.T) ** 2).sum(1).mean()))


def test_sphere_of_known_radius_recovers_the_panda_at_the_noise_floor():
    """DH Panda, one sphere of known radius (16 cm) touched in 60 postures with 10 µm of probe noise: χ ≈ 1,
    the tip at held-out postures as the truth's to a few σ (after the rigid motion no contact can see), the
    base's pose about the sphere's centre reported unidentifiable with the sphere's columns."""
    nominal = panda()
    true = perturbed(nominal)
    sphere = torch.tensor([[0.45, 0.2, 0.3, 0.16]], dtype=F64)
    sigma = 1e-5
    q, _ = contacts(true, "sphere", sphere, 60, sigma)
    res = calibrate_contacts(nominal, q, "sphere", radius=0.16, tip=TIP, measurement_noise=sigma,
                             cross_validation=0, progress=False)
    assert isinstance(res, CalibrationResult) and res.success and res.converged
    assert res.error_model == "dh" and res.surface == "sphere"
    assert 0.65 < res.noise_ratio < 1.35
    assert res.residuals[0] > 50 * res.residuals[-1]
    assert float(res.fixtures[0, 3]) == 0.16  # known: kept
    rep = res.report
    assert {"a1", "d1", "alpha1", "theta1"} <= set(rep.unidentifiable) and not rep.undetermined
    assert "sphere0_x" in rep.reasons["a1"] and "sphere0_z" in rep.reasons["d1"]
    q_out = true.random_configuration(200, generator=torch.Generator().manual_seed(5))
    ours = aligned_rms(tips(true, q_out), tips(res.chain, q_out))
    before = aligned_rms(tips(true, q_out), tips(nominal, q_out))
    assert ours < 3 * sigma and before > 30 * ours
    # held-out contacts (noise-free) against the fitted sphere
    q2, _ = contacts(true, "sphere", sphere, 20, 0.0, seed=7)
    assert res.validation_error(q2)["distance_rms"] < 3 * sigma
    assert "sphere 0: centre" in res.summary() and "radius 160.0000 mm" in res.summary()


@pytest.mark.extended
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_three_planes_ur5_scale_unidentifiable(dtype):
    """UR5 (URDF, general model), three tilted planes, 150 contacts: contacts have no length standard, so one
    length is reported unidentifiable with the planes' offsets in its dependency; up to that scale the
    geometry is recovered at the noise floor (similarity alignment), not rigidly."""
    nominal = from_urdf(ROOT / "diffkin/models/data/ur5.urdf", "tool0", dtype=F64)
    true = perturbed(nominal)
    n = torch.tensor([[0.1, 0.1, 1.0], [1.0, 0.2, 0.1], [0.2, 1.0, -0.1]], dtype=F64)
    n = n / n.norm(dim=-1, keepdim=True)
    planes = torch.cat((n, torch.tensor([[0.05], [0.45], [0.35]], dtype=F64)), -1)
    sigma = 1e-5
    q, fixture = contacts(true, "plane", planes, 150, sigma)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = calibrate_contacts(nominal.to(dtype), q.to(dtype), "plane", fixture=fixture, tip=TIP,
                                 measurement_noise=sigma, cross_validation=3, progress=False)
    assert res.converged or dtype == torch.float32
    scale = [nm for nm, why in res.report.reasons.items() if "plane0_z" in why and "plane2_z" in why]
    assert scale, res.report.summary()
    q_out = true.random_configuration(200, generator=torch.Generator().manual_seed(5))
    ours = tips(res.chain.to(F64), q_out)
    floor = 3 * sigma if dtype == torch.float64 else 3e-5
    assert aligned_rms(tips(true, q_out), ours, scale=True) < floor
    if dtype == torch.float64:
        assert 0.7 < res.noise_ratio < 1.3 and res.cross_validation["distance_rms"] < 2 * sigma
        np.testing.assert_allclose(res.fixtures[:, :3].norm(dim=-1).numpy(), 1.0, atol=1e-12)


def test_bad_inputs_are_refused():
    nominal = panda()
    q = nominal.random_configuration(30, generator=torch.Generator().manual_seed(0))
    kw = dict(progress=False, cross_validation=0)
    with pytest.raises(ConventionError, match="surface"):
        calibrate_contacts(nominal, q, "cylinder", **kw)
    with pytest.raises(OptionError, match="radius"):
        calibrate_contacts(nominal, q, "plane", radius=0.1, **kw)
    with pytest.raises(ShapeError, match=r"\(N, 7\)"):  # joint readings of another robot
        calibrate_contacts(nominal, q[:, :6], **kw)
    with pytest.raises(NonFiniteError):
        calibrate_contacts(nominal, torch.where(q > 2.5, math.nan, q), **kw)
    with pytest.raises(ShapeError, match="fixture"):
        calibrate_contacts(nominal, q, fixture=torch.zeros(29, dtype=torch.long), **kw)
    with pytest.raises(DiffkinError, match="integer"):
        calibrate_contacts(nominal, q, fixture=torch.zeros(30), **kw)
    with pytest.raises(DiffkinError, match="radius > 0"):
        calibrate_contacts(nominal, q, radius=-0.1, **kw)
    with pytest.raises(DiffkinError, match="radius > 0"):
        calibrate_contacts(nominal, q, fixture=torch.arange(30) % 2, radius=[0.1, 0.2, 0.3], **kw)
    with pytest.raises(DiffkinError, match="touched in 2 postures"):
        calibrate_contacts(nominal, q, fixture=(torch.arange(30) > 1).long(), **kw)
    with pytest.raises(DiffkinError, match="degenerate"):  # every posture the same tip: no sphere
        calibrate_contacts(nominal, q[:1].expand(30, 7), **kw)
    with pytest.raises(ShapeError, match="tip"):
        calibrate_contacts(nominal, q, tip=[0.0, 0.1], **kw)


@pytest.mark.extended
def test_two_spheres_gradient_and_unknown_radii():
    """DH Panda, two spheres, 80 contacts, 10 µm: by the gradient method with the radii known, the tip at
    held-out postures as the truth's to 2σ (rigid alignment), cross-validated distance RMS ≈ σ; by least
    squares with the radii unknown, one more length (the scale) fixed with the radii in its dependency, the
    geometry right up to that scale (similarity alignment) and not rigidly."""
    nominal = panda()
    true = perturbed(nominal)
    spheres = torch.tensor([[0.45, 0.2, 0.3, 0.16], [0.3, -0.3, 0.5, 0.12]], dtype=F64)
    sigma = 1e-5
    q, fixture = contacts(true, "sphere", spheres, 80, sigma)
    q_out = true.random_configuration(200, generator=torch.Generator().manual_seed(5))
    kw = dict(fixture=fixture, tip=TIP, measurement_noise=sigma, cross_validation=4, progress=False)
    known = calibrate_contacts(nominal, q, "sphere", radius=[0.16, 0.12], method="gradient", **kw)
    assert known.success and known.converged and 0.7 < known.noise_ratio < 1.4
    assert known.cross_validation["distance_rms"] < 2 * sigma
    assert aligned_rms(tips(true, q_out), tips(known.chain, q_out)) < 2 * sigma
    free = calibrate_contacts(nominal, q, "sphere", **kw)
    extra = set(free.report.unidentifiable) - set(known.report.unidentifiable)
    assert len(extra) == 1
    why = free.report.reasons[extra.pop()]
    assert "sphere0_r" in why and "sphere1_r" in why
    assert aligned_rms(tips(true, q_out), tips(free.chain, q_out), scale=True) < 2 * sigma
    assert aligned_rms(tips(true, q_out), tips(free.chain, q_out)) > 20 * sigma
