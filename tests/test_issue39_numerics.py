"""Issue 39's numerical and boundary items (6, 7, 9, 10, 17, 22, 24, 31, 34): each reproduced as the fuzz
sweep or a new user met it, then checked as a NaN result, a typed error or a correct result against a
reference (numpy / scipy, the closed form, MuJoCo's MJCF file, finite differences)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

import diffkin.collision as C
from diffkin import errors, ik, models
from diffkin.collision import _checked
from diffkin.ik import qp
from diffkin.manipulability import force_ellipsoid, velocity_ellipsoid

F64 = torch.float64
NAN = float("nan")
DATA = Path(__file__).parent / "data"


# ------------------------------------------------------------------------- item 6: NaN in, NaN out
def _argument(shape, name):
    if name == "n":
        return torch.tensor([0.0, 0.0, 1.0], dtype=F64)  # a unit half-space normal
    if shape == (3, 3):
        return torch.eye(3, dtype=F64)
    if shape == ():
        return torch.tensor(0.2, dtype=F64)
    if shape == (None, 3):  # a convex mesh's vertices: a box of 8 corners, placed by the name
        corners = torch.tensor([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=F64)
        return 0.1 * corners + torch.rand(3, dtype=F64, generator=torch.Generator().manual_seed(len(name)))
    return torch.rand(3, dtype=F64, generator=torch.Generator().manual_seed(len(name)))


@pytest.mark.parametrize("fn", list(_checked._SPECS), ids=lambda f: f.__name__)
def test_item06_nan_distance_is_nan(fn):
    """Every exported distance function, a NaN in any coordinate of any argument: NaN out, never a finite
    (collision-looking) distance: sphere_sphere with a NaN centre gave -(ra + rb) (safe_norm mapped NaN to
    0)."""
    spec = _checked._SPECS[fn]
    public = getattr(C, fn.__name__)
    for arg, shape in spec.items():
        for k in range(max(1, math.prod(8 if d is None else d for d in shape))):
            args = {a: _argument(s, a) for a, s in spec.items()}
            x = args[arg].clone()
            x.view(-1)[k] = NAN
            args[arg] = x
            out = public(**args)
            for o in out if isinstance(out, tuple) else (out,):
                assert bool(torch.isnan(o).all()), f"{fn.__name__}({arg}[{k}] = NaN) gave {o}"


def test_item06_nan_distance_is_nan_in_the_pair_kernel_and_keeps_zero_distance_gradients():
    a = torch.tensor([[0.0, 0, 0], [NAN, 0, 0], [1.0, 0, 0]], dtype=F64)
    b = a + torch.tensor([0.0, 0.0, 0.1], dtype=F64)
    r = torch.full((3,), 0.05, dtype=F64)
    i, j = torch.tensor([0, 0, 1]), torch.tensor([1, 2, 2])
    d = C.capsule_capsule_pairs(a, b, r, i, j)
    assert bool(d[0].isnan()) and bool(d[2].isnan())
    torch.testing.assert_close(d[1], torch.tensor(1.0 - 0.1, dtype=F64))  # parallel axes 1 m apart
    # coincident centres (zero distance): a finite, zero gradient, as before
    ca = torch.zeros(3, dtype=F64, requires_grad=True)
    C.sphere_sphere(ca, 0.1, torch.zeros(3, dtype=F64), 0.2).backward()
    assert torch.equal(ca.grad, torch.zeros(3, dtype=F64))
    # and the exact gradient (ca - cb)/|ca - cb| elsewhere, checked by finite differences
    c = torch.tensor([0.3, -0.2, 0.1], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c: C.sphere_sphere(c, 0.1, torch.zeros(3, dtype=F64), 0.2), (c,))


# ----------------------------------------------------------------- item 7: box_qp never falsely converged
@pytest.mark.parametrize("case", ["zero", "negative_definite", "indefinite", "non_symmetric", "lower_inf",
                                  "upper_minus_inf"])
def test_item07_box_qp_refuses_problems_without_a_minimiser(case):
    n = 3
    H, g, lo, hi = torch.eye(n, dtype=F64), torch.ones(n, dtype=F64), None, None
    if case == "zero":
        H = torch.zeros(n, n, dtype=F64)  # x = [nan, nan, inf], "converged"
    elif case == "negative_definite":
        H = -torch.eye(n, dtype=F64)
    elif case == "indefinite":
        H = torch.diag(torch.tensor([1.0, -1.0, 1.0], dtype=F64))
    elif case == "non_symmetric":
        H = torch.tensor([[1.0, 5.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    elif case == "lower_inf":
        lo = torch.tensor([0.0, math.inf, 0.0], dtype=F64)
        hi = torch.full((n,), math.inf, dtype=F64)
    else:
        hi = torch.tensor([1.0, -math.inf, 1.0], dtype=F64)
    match = {"lower_inf": "lower < \\+inf", "upper_minus_inf": "upper > -inf",
             "non_symmetric": "not symmetric"}.get(case, "not positive definite")
    for solver in (qp.box_qp, qp.solve_qp):
        with pytest.raises(errors.DiffkinError, match=match):
            solver(H, g, lower=lo, upper=hi)


def test_item07_box_qp_names_the_offending_row_and_keeps_valid_problems():
    H = torch.eye(2, dtype=F64).repeat(4, 1, 1)
    H[2] = torch.zeros(2, 2, dtype=F64)
    with pytest.raises(errors.DiffkinError, match=r"H\[2\] is not positive definite"):
        qp.box_qp(H, torch.ones(4, 2, dtype=F64))
    # symmetric up to rounding (AᵀA + λI computed in float32) passes; the solution is the bounded minimiser
    A = torch.randn(5, 3, generator=torch.Generator().manual_seed(1))
    Hs, g = A.T @ A + 1e-3 * torch.eye(3), torch.tensor([1.0, -2.0, 0.5])
    res = qp.box_qp(Hs, g, lower=-torch.ones(3), upper=torch.ones(3))
    scipy_optimize = pytest.importorskip("scipy.optimize")
    ref = scipy_optimize.minimize(lambda x: 0.5 * x @ Hs.double().numpy() @ x - g.double().numpy() @ x,
                                  np.zeros(3), bounds=[(-1, 1)] * 3, method="L-BFGS-B",
                                  options={"ftol": 1e-15, "gtol": 1e-12}).x
    assert bool(res.converged)
    np.testing.assert_allclose(res.x.numpy(), ref, atol=1e-4)
    # the solver core (trusted library callers, no checks): a non-finite x is never reported converged
    inf = torch.full((1, 3), math.inf, dtype=F64)
    out = qp._BoxQP.apply(torch.zeros(1, 3, 3, dtype=F64), torch.ones(1, 3, dtype=F64), -inf, inf, 20)
    assert not bool(torch.isfinite(out[0]).all()) and not bool(out[3].any())


# ---------------------------------------------------------------------- item 9: World checks a Box
def _box(center=(0.0, 0.0, 0.0), R=None, h=(0.1, 0.2, 0.3)):
    R = torch.eye(3, dtype=F64) if R is None else R
    return C.Box(torch.tensor([center], dtype=F64), R.reshape(-1, 3, 3), torch.tensor([h], dtype=F64))


@pytest.mark.parametrize("case,error,match", [
    ("nan_centre", errors.NonFiniteError, "boxes.center"),
    ("scaled_rotation", errors.DiffkinError, "boxes.rotation.*not orthonormal"),
    ("reflection", errors.DiffkinError, "boxes.rotation.*det"),
    ("negative_half_extents", errors.DiffkinError, "half_extents >= 0"),
    ("mismatched_shapes", errors.ShapeError, "boxes.center \\(2, 3\\).*boxes.half_extents \\(3, 3\\)"),
    ("rotation_shape", errors.ShapeError, "boxes.rotation"),
    ("batch_dims", errors.ShapeError, "spheres \\(2, 1, 4\\), capsules \\(3, 1, 7\\)"),
])
def test_item09_world_refuses_bad_boxes_and_batches(case, error, match):
    kwargs = {}
    if case == "nan_centre":
        kwargs["boxes"] = _box(center=(NAN, 0.0, 0.0))
    elif case == "scaled_rotation":
        kwargs["boxes"] = _box(R=2.0 * torch.eye(3, dtype=F64))
    elif case == "reflection":
        kwargs["boxes"] = _box(R=torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=F64)))
    elif case == "negative_half_extents":
        kwargs["boxes"] = _box(h=(0.1, -0.2, 0.3))
    elif case == "mismatched_shapes":
        kwargs["boxes"] = C.Box(torch.zeros(2, 3, dtype=F64), torch.eye(3, dtype=F64)[None],
                                torch.ones(3, 3, dtype=F64))
    elif case == "rotation_shape":
        kwargs["boxes"] = C.Box(torch.zeros(1, 3, dtype=F64), torch.eye(3, dtype=F64)[None, :2],
                                torch.ones(1, 3, dtype=F64))
    else:
        kwargs = dict(spheres=torch.zeros(2, 1, 4, dtype=F64), capsules=torch.zeros(3, 1, 7, dtype=F64))
    with pytest.raises(error, match=match):
        C.World(**kwargs)


def test_item09_world_takes_a_valid_direct_box_as_box_builds_it():
    rpy = torch.tensor([0.3, -0.2, 0.9], dtype=F64)
    built = C.box(torch.tensor([0.4, 0.1, 0.2], dtype=F64), torch.tensor([0.1, 0.2, 0.05], dtype=F64), rpy)
    R = built.rotation + 1e-5  # within the rigidity tolerance: accepted, re-orthonormalised
    direct = C.Box(built.center, R, built.half_extents)
    w_direct, w_built = C.World(boxes=direct), C.World(boxes=built)
    torch.testing.assert_close(w_direct.boxes.rotation, w_built.boxes.rotation, atol=2e-5, rtol=0)
    # same distances of a test sphere's centre to the box, and the box's own closed form (scipy's rotation)
    from scipy.spatial.transform import Rotation

    p = torch.tensor([[1.0, 0.5, 0.3]], dtype=F64)
    Rs = torch.from_numpy(Rotation.from_euler("xyz", rpy.numpy()).as_matrix())
    u = (p - built.center) @ Rs
    ref = torch.linalg.norm((u.abs() - built.half_extents).clamp_min(0), dim=-1)
    for w in (w_direct, w_built):
        d = w.distances(p, p, torch.zeros(1, dtype=F64), torch.zeros(0, 3, dtype=F64),
                        torch.zeros(0, 3, 3, dtype=F64), torch.zeros(0, 3, dtype=F64))
        torch.testing.assert_close(d[0], ref, atol=1e-4, rtol=0)
    # batch dims that broadcast are fine: (2, W, 4) spheres with (1, W, 7) capsules
    w = C.World(spheres=torch.zeros(2, 1, 4, dtype=F64), capsules=torch.zeros(1, 1, 7, dtype=F64))
    assert w.counts == (1, 1, 0, 0, 0, 0)


# --------------------------------------------------------------------- item 10: interpolate checks s
@pytest.fixture(scope="module")
def kinds():
    return models.from_mjcf(DATA / "mjcf_extra" / "joint_kinds.xml", "palm", dtype=F64)


@pytest.mark.parametrize("s,error", [
    (NAN, errors.NonFiniteError), (math.inf, errors.NonFiniteError), (1j, errors.DTypeError),
    ("0.5", errors.DTypeError), (None, errors.DTypeError), (True, errors.DTypeError),
    (torch.tensor(0.5, dtype=torch.complex64), errors.DTypeError),
    (torch.tensor(0.5, dtype=torch.float32), errors.DTypeError),  # not the chain's dtype
    (torch.zeros(3, 2, dtype=F64), errors.ShapeError),  # batch (3, 2) vs q0's (4,)
])
def test_item10_interpolate_checks_s(kinds, s, error):
    q0 = kinds.neutral_configuration().expand(4, -1)
    q1 = kinds.random_configuration(generator=torch.Generator().manual_seed(0))
    with pytest.raises(error):
        kinds.interpolate(q0, q1, s)


def test_item10_interpolate_values(kinds):
    q0 = kinds.neutral_configuration()
    q1 = kinds.random_configuration(generator=torch.Generator().manual_seed(0))
    out = kinds.interpolate(q0, q1, [0.0, 0.5, 1.0])  # a list: converted to the chain's dtype
    assert out.shape == (3, kinds.n_joints) and out.dtype == F64
    torch.testing.assert_close(out[0], q0)
    torch.testing.assert_close(kinds.difference(out[2], q1), torch.zeros(kinds.nv, dtype=F64), atol=1e-12,
                               rtol=0)
    # the midpoint is halfway along the geodesic: q0 ⊕ ½(q1 ⊖ q0), both halves the same tangent
    torch.testing.assert_close(kinds.difference(q0, out[1]), kinds.difference(out[1], q1), atol=1e-12, rtol=0)


# ----------------------------------------------------------- item 17: rigid paths, tall force ellipsoid
@pytest.fixture(scope="module")
def panda():
    return models.load("panda", dtype=F64)


_PATH_FNS = [lambda T: ik.finite_difference_twists(T, 0.1), lambda T: ik.refine_path(T, 2)]


@pytest.mark.parametrize("fn", _PATH_FNS,
                         ids=["finite_difference_twists", "refine_path"])
@pytest.mark.parametrize("defect", ["scaled", "sheared", "bottom_row"])
def test_item17_paths_refuse_non_rigid_poses(panda, fn, defect):
    T = panda.forward_kinematics(torch.zeros(3, 7, dtype=F64)).clone()
    if defect == "scaled":
        T[1, :3, :3] *= 2.0
    elif defect == "sheared":
        T[1, 0, 1] += 0.1
    else:
        T[1, 3, 0] = 0.5
    with pytest.raises(errors.DiffkinError, match=r"T_traj\[1\] is not a rigid transform"):
        fn(T)
    T[1] = panda.forward_kinematics(torch.zeros(7, dtype=F64))
    T[1, :3, 3] += 1e-4 * torch.ones(3, dtype=F64)  # rigid again: accepted
    assert torch.isfinite(fn(T)).all()


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("scale", [1e-20, 1e-8, 1.0, 1e8, 1e18])
def test_item17_force_ellipsoid_of_a_7x1_jacobian(dtype, scale):
    J = (torch.randn(7, 1, generator=torch.Generator().manual_seed(3), dtype=F64) * scale).to(dtype)
    force, vel = force_ellipsoid(J), velocity_ellipsoid(J)
    assert not bool(force.axes.isnan().any() | force.lengths.isnan().any())
    U, S, _ = np.linalg.svd(J.double().numpy())  # numpy's full SVD: σ₁ = |J|, u₁ = ±J/|J|
    np.testing.assert_allclose(vel.lengths[0].double().numpy(), S[0], rtol=1e-5)
    np.testing.assert_allclose(force.lengths[0].double().numpy(), 1.0 / S[0], rtol=1e-5)
    assert bool(torch.isinf(force.lengths[1:]).all()) and bool((vel.lengths[1:] == 0).all())
    np.testing.assert_allclose(abs(force.axes[:, 0].double().numpy() @ U[:, 0]), 1.0, rtol=1e-5)
    eye = torch.eye(7, dtype=dtype)
    torch.testing.assert_close(force.axes.mT @ force.axes, eye, atol=1e-5, rtol=0)  # an orthonormal basis


def test_item17_tall_ellipsoid_gradients_match_finite_differences():
    J = torch.randn(7, 2, generator=torch.Generator().manual_seed(4), dtype=F64, requires_grad=True)

    def f(J):
        e = velocity_ellipsoid(J)
        axes = e.axes[:, :2] * e.axes[:1, :2].sign()  # the signs of the axes are arbitrary: fix them
        return axes.sum() + e.lengths.sum()

    assert torch.autograd.gradcheck(f, (J,))


# ---------------------------------------------------------------- item 22: base with the wrong batch
def test_item22_base_batch_mismatch_is_a_shape_error(panda):
    base = torch.eye(4, dtype=F64).expand(3, 4, 4)
    with pytest.raises(errors.ShapeError, match=r"expected T_target of shape \(\.\.\., 4, 4\), got \(5, 4\)"):
        ik.solve(panda, torch.zeros(5, 4, dtype=F64), base=torch.eye(4, dtype=F64))
    T = panda.forward_kinematics(torch.zeros(5, 7, dtype=F64))
    with pytest.raises(errors.ShapeError, match=r"base.*broadcast with those of T_target \(5\).*\(3, 4, 4\)"):
        ik.solve(panda, T, base=base)
    with pytest.raises(errors.ShapeError, match=r"with those of q \(5\), got base \(3, 4, 4\)"):
        panda.forward_kinematics(torch.zeros(5, 7, dtype=F64), base=base)
    with pytest.raises(errors.ShapeError, match=r"broadcast with those of q \(5\)"):
        panda.forward_kinematics(torch.zeros(5, 7, dtype=F64), all_frames=True, base=base)
    with pytest.raises(errors.ShapeError, match=r"broadcast with those of q \(5\)"):
        panda.forward_kinematics_and_jacobian(torch.zeros(5, 7, dtype=F64), base=base)


def test_item22_base_that_broadcasts_still_places_the_robot(panda):
    from scipy.spatial.transform import Rotation

    q = panda.random_configuration((2, 5), generator=torch.Generator().manual_seed(5))
    B = torch.eye(4, dtype=F64).repeat(2, 1, 1, 1)  # (2, 1, 4, 4) against q's (2, 5)
    B[:, 0, :3, :3] = torch.from_numpy(Rotation.from_rotvec([[0, 0, 0.7], [0.3, 0, 0]]).as_matrix())
    B[:, 0, :3, 3] = torch.tensor([[0.5, 0.0, 0.1], [-1.0, 2.0, 0.0]], dtype=F64)
    Tw = panda.forward_kinematics(q, base=B)
    torch.testing.assert_close(Tw, B @ panda.forward_kinematics(q))
    res = ik.solve(panda, Tw, base=B, seed=0)
    assert bool(res.success.all())
    torch.testing.assert_close(panda.forward_kinematics(res.q, base=B), Tw, atol=1e-3, rtol=0)


# ------------------------------------------------------ item 24: RobotCollision takes q as the chain
@pytest.fixture(scope="module")
def fr3_collision():
    import warnings

    chain = models.from_urdf(DATA / "urdf" / "fr3.urdf", "fr3_link8", dtype=torch.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the FR3's meshes are not shipped
        return chain, C.RobotCollision.from_urdf(DATA / "urdf" / "fr3.urdf", chain)


def test_item24_robot_collision_converts_q_like_the_chain(fr3_collision):
    chain, rc = fr3_collision
    q = chain.random_configuration((2,), generator=torch.Generator().manual_seed(6))
    world = C.World(spheres=[[0.4, 0.0, 0.5, 0.1]], dtype=torch.float32)
    as_list, as_np64 = q.tolist(), q.double().numpy()  # a float64 array: converted to the chain's float32
    for method in (rc.self_distances, rc.min_distance, lambda q: rc.placed(q)[0],
                   lambda q: rc.world_distances(q, world), lambda q: rc.min_distance(q, world)):
        ref = method(q)
        for given in (as_list, as_np64):
            out = method(given)
            assert out.dtype == torch.float32
            torch.testing.assert_close(out, ref)
        with pytest.raises(errors.ShapeError, match=r"expected q of shape \(\.\.\., 7\)"):
            method([0.0] * 6)
    with pytest.raises(errors.DTypeError, match="q is torch.float64"):  # a tensor keeps the agreement check
        rc.self_distances(q.double())


def test_item24_from_urdf_refuses_a_missing_srdf_and_a_missing_chain(fr3_collision):
    chain, _ = fr3_collision
    urdf = DATA / "urdf" / "fr3.urdf"
    with pytest.raises(errors.ModelError, match="SRDF file 'missing.srdf' not found"):
        C.RobotCollision.from_urdf(urdf, chain, srdf="missing.srdf")
    with pytest.raises(errors.ModelError, match="expected srdf as a path or the XML text, got int"):
        C.RobotCollision.from_urdf(urdf, chain, srdf=3)
    for bad, what in ((None, "NoneType"), (models.load("panda"), "DHChain")):
        with pytest.raises(errors.ModelError, match=f"expected chain as the chain built from .*{what}"):
            C.RobotCollision.from_urdf(urdf, bad)


# ------------------------------------------------------------------ item 31: the trajectory CLI
def _cli(*args):
    import contextlib
    import io

    from diffkin.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in args])
    return rc, out.getvalue(), err.getvalue()


def test_item31_cartesian_via_points_from_a_txt_file(tmp_path):
    from scipy.interpolate import CubicSpline

    pts = np.array([[0.3, 0.0, 0.5], [0.4, 0.1, 0.5], [0.45, 0.0, 0.45], [0.5, 0.1, 0.4]])
    np.savetxt(tmp_path / "via.txt", pts, header="x y z")  # numpy's plain text: spaces, a # header
    rc, out, err = _cli("trajectory", "cartesian", "--points", tmp_path / "via.txt", "--duration", "3",
                        "--samples", "31", "--output", tmp_path / "c.npz")
    assert rc == 0, err
    with np.load(tmp_path / "c.npz") as data:
        t, p, v, a = data["t"], data["position"], data["velocity"], data["acceleration"]
    # the clamped cubic spline through the points at equally spaced times (zero end velocities), scipy's
    ref = CubicSpline(np.linspace(0, 3, 4), pts, bc_type="clamped")
    np.testing.assert_allclose(p, ref(t), atol=1e-12)
    np.testing.assert_allclose(v, ref(t, 1), atol=1e-10)
    np.testing.assert_allclose(a, ref(t, 2), atol=1e-9)
    # joint space from a comma-separated .txt, the same spline
    np.savetxt(tmp_path / "j.txt", pts[:, :2], delimiter=",")
    rc, _, err = _cli("trajectory", "joint", "--points", tmp_path / "j.txt", "--duration", "3", "--samples",
                      "31", "--output", tmp_path / "j.npz")
    assert rc == 0, err
    with np.load(tmp_path / "j.npz") as data:
        np.testing.assert_allclose(data["position"], ref(t)[:, :2], atol=1e-12)


@pytest.mark.parametrize("extra,flag", [(("--profile", "cubic"), "--profile"),
                                        (("--start", "0", "0"), "--start"), (("--end", "1", "1"), "--end")])
def test_item31_points_with_profile_start_or_end_is_an_error(tmp_path, extra, flag):
    np.savetxt(tmp_path / "j.csv", [[0.0, 0.0], [1.0, -1.0], [0.5, 0.5]], delimiter=",")
    rc, _, err = _cli("trajectory", "joint", "--points", tmp_path / "j.csv", *extra, "--output",
                      tmp_path / "x.npz")
    assert rc == 2 and err.startswith("error: ") and f"{flag} cannot be combined with --points" in err, err
    assert not (tmp_path / "x.npz").exists()


def test_item31_cartesian_points_need_three_columns_and_numbers(tmp_path):
    np.savetxt(tmp_path / "two.txt", [[0.0, 0.0], [1.0, -1.0]])
    out = tmp_path / "x.npz"
    rc, _, err = _cli("trajectory", "cartesian", "--points", tmp_path / "two.txt", "--output", out)
    assert rc == 2 and "expected Cartesian via points of shape (N >= 2, 3 (x, y, z)), got (2, 2)" in err, err
    (tmp_path / "bad.txt").write_text("0 0 0\n1 x 1\n")
    rc, _, err = _cli("trajectory", "cartesian", "--points", tmp_path / "bad.txt", "--output", out)
    assert rc == 2 and "line 2: not a number: 'x'" in err, err
    (tmp_path / "ragged.txt").write_text("0 0 0\n1 1\n")
    rc, _, err = _cli("trajectory", "cartesian", "--points", tmp_path / "ragged.txt", "--output", out)
    assert rc == 2 and "line 2: 2 columns, but the first row has 3" in err, err


# ------------------------------------------------------------- item 34: the env's public joint state
def test_item34_env_exposes_its_joint_configuration():
    gym = pytest.importorskip("gymnasium")
    import diffkin.envs  # noqa: F401

    env = gym.make("diffkin/Reach-v0", observation=("joint_positions",))
    with pytest.raises(gym.error.ResetNeeded):
        _ = env.unwrapped.q
    obs, _ = env.reset(seed=3)
    chain = env.unwrapped.robot.chain
    lo, hi = (x.double().numpy() for x in chain.lower_upper())
    for _ in range(3):
        q = env.unwrapped.q
        assert q.shape == (chain.n_joints,) and q.dtype == np.float64
        # the observation is q mapped to [-1, 1] by the limits: the property is the env's own q
        np.testing.assert_allclose(obs["observation"], 2.0 * (q - lo) / (hi - lo) - 1.0, atol=1e-6)
        q[:] = 0.0  # a copy: writing it leaves the env alone
        assert not np.array_equal(env.unwrapped.q, q)
        np.testing.assert_array_equal(env.get_wrapper_attr("q"), env.unwrapped.q)
        obs, *_ = env.step(env.action_space.sample())
