"""Calibration accuracy on robots whose true geometry lies outside the DH family (issue 14).

    python -m benchmarks.bench_calibration_models [--poses 20 50 100] [--held-out 500] [--json out.json]
        [--pybotics-path DIR]

Truth: the manufacturer URDF with every joint origin perturbed by ±1 mm and ±0.1° (uniform, all six
coordinates), encoder zeros by ±0.1°, an unknown measurement (tracker) frame — the base, a few cm and degrees
off — and the tool (a point 5 cm off the flange, ±1 mm). Measurements with 0.02 mm / 0.005° noise per
coordinate (full pose) or 0.02 mm (position only); calibration estimates base and tool too. Held-out: RMS and
max position error on ``--held-out`` noise-free poses before and after calibration.

Noise floor: the held-out position RMS that the measurement noise alone leaves with the *exact* error model
(general URDF model / Hayati for the UR5 DH table) — √(mean over held-out poses of trace(Φ_p C Φ_pᵀ)) with
C = (Φᵀ Σ⁻¹ Φ)⁻¹ over the identifiable parameters (the Cramér–Rao bound of an unbiased fit, linearised at
the nominal). "ratio" = held-out RMS after / floor (target ≤ 1.5).

Robots: UR5 (axes 2-3-4 parallel) from its DH table with the plain "dh" model and with "auto" (= Hayati's
β), and from its URDF ("general"); ABB IRB 2400 (axes 2-3 parallel) and Franka Panda from their URDFs.

pybotics (``pip install pybotics``, 3.1.2; rows ``impl = "pybotics (MDH + scipy)"``, skipped with a note on
stderr when it does not import; ``--pybotics-path`` / ``$PYBOTICS_PATH`` names a ``pip install --target``
folder, appended to ``sys.path`` *after* the venv's site-packages so that torch and the venv's numpy/scipy are
the ones loaded, not the numpy 1.26 pybotics brings along). One row set per robot: UR5 from the same DH
nominal as the "dh" rows, IRB 2400 and Panda from their URDF nominals. Conversion: the nominal chain's joint
axes at q = 0 (world frame, nominal base and tool included) are turned into a Craig modified-DH table
(:func:`mdh_from_axes`: common normals; for parallel axes the normal through the current origin), pybotics'
``world_frame`` = MDH frame 1 at q = 0 (link 1 all zeros) and its ``Tool`` = frame n⁻¹ · nominal end pose;
the pybotics FK is checked against diffkin's to 1e-9 on 200 random configurations before use (it agrees to
~1e-15). Calibration: pybotics' ``OptimizationHandler`` with all MDH parameters free except the ones the
world frame and tool already carry (link 1's four, θ_n and d_n of the last link), the tool and world frame
free (6 each, ZYX Euler — pybotics' vector form), and ``scipy.optimize.least_squares`` (trf, finite
differences, ``x_scale="jac"``) on the same measurements. The residual is our own, built on the handler and
``Robot.fk``: pybotics' ``optimize_accuracy`` returns one position-error *norm* per pose, which drops the
orientation data and leaves fewer residuals than parameters at 20 position-only poses, so the residual is
the 3 position components plus, for full-pose data, the rotation error ½·vee(R_measᵀR − RᵀR_meas) weighted
σ_p/σ_r (the whitening diffkin uses). Encoder zeros go into θ. Held-out: positions of pybotics'
``fk`` (world frame · chain · tool) against the truth on the same 500 poses, same floor. pybotics' FK is pure
Python (~40 µs a pose) and the parallel axes make the MDH fit crawl (~250 iterations, ending with the
parallel pair's d at ∓250 m, where the common normal of two axes 0.1° apart lies), so a UR5/IRB fit takes
20–50 s: pybotics runs at 50 and 100 poses, full pose only (``PYBOTICS_POSES``); the whole
benchmark then takes about 3½ min on 2 shared cores (about 30 s without pybotics).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from diffkin import models
from diffkin.calibration import calibrate
from diffkin.calibration.error_models import build_model
from diffkin.calibration.identifiability import model_reports
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
SIGMA = (2e-5, math.radians(0.005))
SMR = [0.02, 0.01, 0.05, 0.0, 0.0, 0.0]  # the measured point / tool frame on the flange (nominal)


def _urdf(robot):
    path, end = URDF[robot]
    return from_urdf(path, end, dtype=F64)


def _truth(robot: str, seed: int):
    true = _urdf(robot)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        true.origin_xyz += 1e-3 * (2 * torch.rand(true.origin_xyz.shape, generator=g, dtype=F64) - 1)
        true.origin_rpy += math.radians(0.1) * (2 * torch.rand(true.origin_rpy.shape, generator=g,
                                                               dtype=F64) - 1)
    off = math.radians(0.1) * (2 * torch.rand(true.n_joints, generator=g, dtype=F64) - 1)
    true.base = pose_correction(torch.tensor([0.03, -0.02, 0.01, 0.01, 0.02, -0.015], dtype=F64))
    tool = torch.tensor(SMR, dtype=F64) + torch.tensor([1e-3, -1e-3, 1e-3, 1.5e-3, -1e-3, 1e-3], dtype=F64)
    true.tool = pose_correction(tool)
    return true, off


def _nominal(robot: str, kind: str):
    if kind == "urdf":
        chain = _urdf(robot)
    else:
        chain = models.load(robot, dtype=F64)
        chain.base = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=F64))  # URDF base_link
    chain.tool = pose_correction(torch.tensor(SMR, dtype=F64))
    return chain


def _measure(true, off, q, position_only, seed):
    with torch.no_grad():
        T = true.forward_kinematics(q + off).clone()
    g = torch.Generator().manual_seed(seed)
    T[:, :3, 3] += SIGMA[0] * torch.randn(q.shape[0], 3, generator=g, dtype=F64)
    if position_only:
        return T[:, :3, 3].contiguous()
    R_noise = rotvec_to_matrix(SIGMA[1] * torch.randn(q.shape[0], 3, generator=g, dtype=F64))
    T[:, :3, :3] = R_noise @ T[:, :3, :3]
    return T


def _held_out(chain, true, off, qv):
    with torch.no_grad():
        e = (chain.forward_kinematics(qv) - true.forward_kinematics(qv + off))[:, :3, 3].norm(dim=-1)
    return float(e.square().mean().sqrt()), float(e.max())


def _floor(nominal, error_model, q, qv, position_only):
    """Held-out position RMS left by the measurement noise with the exact error model (Cramér–Rao)."""
    model, _ = build_model(nominal, error_model, base=True, tool=True)
    w = SIGMA[0] / SIGMA[1]  # orientation rows in metres: equal whitened weight
    z = model.nominal[None]
    with torch.no_grad():
        reports, free = model_reports(model, z, q[None], position_only, w)
        Phi, _ = model.calibration_matrix(z, q[None], position_only, w, columns=model.candidate)
        Pv, _ = model.calibration_matrix(z, qv[None], True, w, columns=model.candidate)
    A = Phi.reshape(-1, Phi.shape[-1])[:, free[0]] / SIGMA[0]
    C = torch.linalg.pinv(A.T @ A, hermitian=True)
    B = Pv.reshape(qv.shape[0], 3, -1)[..., free[0]]
    return float(torch.einsum("nij,jk,nik->n", B, C, B).mean().sqrt())


# ----------------------------------------------------------------------------------- pybotics (MDH + scipy)
PYBOTICS_IMPL = "pybotics (MDH + scipy)"
PYBOTICS_POSES = (50, 100)  # full pose only: pybotics' pure-Python FK under finite differences is slow
PYBOTICS_CASES = {("ur5", "dh", "dh"), ("irb2400", "urdf", "auto"), ("panda", "urdf", "auto")}


def _import_pybotics(path: str | None):
    """pybotics' modules, or None. ``path`` (a ``pip install --target`` folder) goes *after* the venv's
    site-packages, so torch and the venv's numpy/scipy win over any numpy that pybotics brought along."""
    if path and path not in sys.path:
        sys.path.append(path)
    try:
        from pybotics.kinematic_chain import MDHKinematicChain
        from pybotics.optimization import OptimizationHandler
        from pybotics.robot import Robot
        from pybotics.tool import Tool
    except ImportError:
        return None
    return MDHKinematicChain, OptimizationHandler, Robot, Tool


def mdh_from_axes(z, p, T_end, tol=1e-9):
    """Modified DH (Craig) table ``(n, 4)`` = (α_{i-1}, a_{i-1}, θ_i, d_i), world frame and tool of a revolute
    chain, from its joint axes (unit ``z[i]`` through ``p[i]``, world frame) and end pose at q = 0.

    Frame i: z along axis i, x along the common normal to axis i+1 (through the current origin for parallel
    axes, z_i × z_{i+1} for intersecting ones), origin where that normal leaves axis i; frame 1 = world
    frame (so link 1 is all zeros) and x_n is the flange x projected off z_n (so θ_n = d_n = 0 there)."""
    n = len(z)
    z = [v / np.linalg.norm(v) for v in z]
    o, x = [None] * n, [None] * n
    start = np.asarray(p[0], dtype=float)
    for i in range(n):
        o[i] = start
        if i == n - 1:
            xi = T_end[:3, 0] - (T_end[:3, 0] @ z[i]) * z[i]
            if np.linalg.norm(xi) < 1e-6:
                xi = T_end[:3, 1] - (T_end[:3, 1] @ z[i]) * z[i]
            x[i] = xi / np.linalg.norm(xi)
            break
        zi, zj = z[i], z[i + 1]
        c = np.cross(zi, zj)
        if np.linalg.norm(c) < tol:  # parallel: the normal through the current origin
            w = (p[i + 1] - start) - ((p[i + 1] - start) @ zi) * zi
            x[i] = w / np.linalg.norm(w)
            start = start + w
        else:  # skew or intersecting: the closest points of the two lines
            r = p[i + 1] - p[i]
            s, t = np.linalg.solve(np.array([[zi @ zi, -zi @ zj], [zi @ zj, -zj @ zj]]),
                                   np.array([r @ zi, r @ zj]))
            o[i] = p[i] + s * zi
            d = p[i + 1] + t * zj - o[i]
            x[i] = d / np.linalg.norm(d) if np.linalg.norm(d) > tol else c / np.linalg.norm(c)
            start = o[i] + d
    table = np.zeros((n, 4))
    for i in range(1, n):
        table[i] = (np.arctan2(np.cross(z[i - 1], z[i]) @ x[i - 1], z[i - 1] @ z[i]),
                    (o[i] - o[i - 1]) @ x[i - 1],
                    np.arctan2(np.cross(x[i - 1], x[i]) @ z[i], x[i - 1] @ x[i]),
                    (o[i] - o[i - 1]) @ z[i])
    frames = [np.eye(4) for _ in range(n)]
    for F, zi, xi, oi in zip(frames, z, x, o):
        F[:3, 0], F[:3, 1], F[:3, 2], F[:3, 3] = xi, np.cross(zi, xi), zi, oi
    return table, frames[0], np.linalg.inv(frames[-1]) @ T_end


def _pybotics_robot(pyb, nominal, check: int = 200):
    """The nominal chain (base and tool included) as a pybotics ``Robot``; its FK is checked against
    diffkin's on ``check`` random configurations to 1e-9."""
    MDHKinematicChain, _, Robot, Tool = pyb
    with torch.no_grad():
        z, p, T = nominal.joint_axes_origins(torch.zeros(nominal.n_joints, dtype=F64))
    table, world, tool = mdh_from_axes(z.numpy(), p.numpy(), T.numpy())
    robot = Robot(MDHKinematicChain(table), tool=Tool(tool), world_frame=world)
    q = nominal.random_configuration((check,), generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        T_ref = nominal.forward_kinematics(q).numpy()
    err = np.abs(np.stack([robot.fk(qq) for qq in q.numpy()]) - T_ref).max()
    if err > 1e-9:
        raise RuntimeError(f"MDH conversion off by {err:.2e}")
    return robot


def _pybotics_calibrate(pyb, robot, q, data, position_only):
    """pybotics' OptimizationHandler (MDH chain + tool + world frame, ZYX Euler vectors) with scipy's
    least_squares on the measured positions (and orientations, rows weighted σ_p/σ_r)."""
    import scipy.optimize

    OptimizationHandler = pyb[1]
    n = len(robot)
    mask = np.ones((n, 4), dtype=bool)
    mask[0] = False  # link 1 (α0, a0, θ1, d1) is the world frame's
    mask[-1, 2:] = False  # θ_n, d_n are the tool's
    handler = OptimizationHandler(robot, kinematic_chain_mask=mask.ravel(), tool_mask=True, world_mask=True)
    qs, meas = q.numpy(), data.numpy()
    w = SIGMA[0] / SIGMA[1]

    def residuals(x):
        handler.apply_optimization_vector(x)
        T = np.stack([handler.robot.fk(qq) for qq in qs])
        if position_only:
            return (T[:, :3, 3] - meas).ravel()
        dR = np.einsum("nji,njk->nik", meas[:, :3, :3], T[:, :3, :3])
        rot = 0.5 * np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0],
                              dR[:, 1, 0] - dR[:, 0, 1]], axis=-1)
        return np.concatenate([T[:, :3, 3] - meas[:, :3, 3], w * rot], axis=-1).ravel()

    res = scipy.optimize.least_squares(residuals, handler.generate_optimization_vector(), x_scale="jac")
    handler.apply_optimization_vector(res.x)
    return handler.robot, res


def _pybotics_held_out(robot, true, off, qv):
    with torch.no_grad():
        ref = true.forward_kinematics(qv + off)[:, :3, 3].numpy()
    e = np.linalg.norm(np.stack([robot.fk(qq)[:3, 3] for qq in qv.numpy()]) - ref, axis=-1)
    return float(np.sqrt(np.mean(e ** 2))), float(e.max())


CASES = [  # (robot, nominal kind, error model, exact error model for the floor)
    ("ur5", "dh", "dh", "hayati"),
    ("ur5", "dh", "auto", "hayati"),
    ("ur5", "urdf", "auto", "general"),
    ("irb2400", "urdf", "auto", "general"),
    ("panda", "urdf", "auto", "general"),
]


def run(poses=(20, 50, 100), held_out: int = 500, methods=("least_squares", "gradient"),
        pybotics_path: str | None = None) -> list[dict]:
    rows = []
    pyb = _import_pybotics(pybotics_path)
    if pyb is None:
        print("pybotics not importable: no pybotics rows (pip install pybotics, or --pybotics-path)",
              file=sys.stderr)
    for robot, kind, em, exact in CASES:
        true, off = _truth(robot, seed=1)
        nominal = _nominal(robot, kind)
        qv = true.random_configuration((held_out,), generator=torch.Generator().manual_seed(7))
        before = _held_out(nominal, true, off, qv)
        pyb_robot = _pybotics_robot(pyb, nominal) if pyb and (robot, kind, em) in PYBOTICS_CASES else None
        for position_only in (False, True):
            for N in poses:
                q = true.random_configuration((N,), generator=torch.Generator().manual_seed(100 + N))
                data = _measure(true, off, q, position_only, seed=N)
                floor = _floor(nominal, exact, q, qv, position_only)
                for method in methods:
                    t0 = time.perf_counter()
                    with warnings.catch_warnings(record=True) as caught:
                        warnings.simplefilter("always")
                        res = calibrate(nominal, q, data, method=method, base=True, tool=True, progress=False,
                                        error_model=em, measurement_noise=SIGMA, cross_validation=0)
                    sec = time.perf_counter() - t0
                    after = _held_out(res.chain, true, off, qv)
                    rows.append({
                        "robot": robot, "nominal": kind, "error_model": res.error_model,
                        "data": "position" if position_only else "pose", "poses": N, "method": method,
                        "rms_before_mm": before[0] * 1e3, "max_before_mm": before[1] * 1e3,
                        "rms_after_mm": after[0] * 1e3, "max_after_mm": after[1] * 1e3,
                        "floor_mm": floor * 1e3, "ratio": after[0] / floor, "converged": res.converged,
                        "noise_ratio": res.noise_ratio,
                        "warned": any("measurement noise" in str(w.message) for w in caught),
                        "rank": res.report.rank, "seconds": sec, "impl": "diffkin",
                    })
                if pyb_robot is not None and not position_only and N in PYBOTICS_POSES:
                    t0 = time.perf_counter()
                    fitted, res = _pybotics_calibrate(pyb, pyb_robot, q, data, position_only)
                    sec = time.perf_counter() - t0
                    after = _pybotics_held_out(fitted, true, off, qv)
                    rows.append({
                        "robot": robot, "nominal": kind, "error_model": "mdh",
                        "data": "pose", "poses": N, "method": "least_squares",
                        "rms_before_mm": before[0] * 1e3, "max_before_mm": before[1] * 1e3,
                        "rms_after_mm": after[0] * 1e3, "max_after_mm": after[1] * 1e3,
                        "floor_mm": floor * 1e3, "ratio": after[0] / floor, "converged": bool(res.success),
                        "noise_ratio": float("nan"), "warned": False, "rank": None, "seconds": sec,
                        "nfev": int(res.nfev), "impl": PYBOTICS_IMPL,
                    })
    return rows


def markdown(rows: list[dict]) -> str:
    lines = ["| impl | robot (nominal) | model | data | poses | method | held-out RMS / max before [mm] | "
             "after [mm] | noise floor [mm] | ratio | χ (noise check) | warned | time [s] |",
             "|---|---|---|---|---:|---|---:|---:|---:|---:|---:|---|---:|"]
    for r in rows:
        lines.append(
            f"| {r['impl']} | {r['robot']} ({r['nominal']}) | {r['error_model']} | {r['data']} | "
            f"{r['poses']} | {r['method']} | "
            f"{r['rms_before_mm']:.3f} / {r['max_before_mm']:.3f} | {r['rms_after_mm']:.4f} / "
            f"{r['max_after_mm']:.4f} | {r['floor_mm']:.4f} | {r['ratio']:.2f} | "
            f"{'—' if math.isnan(r['noise_ratio']) else format(r['noise_ratio'], '.2f')} | "
            f"{'yes' if r['warned'] else 'no'} | {r['seconds']:.2f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, nargs="+", default=[20, 50, 100])
    ap.add_argument("--held-out", dest="held_out", type=int, default=500)
    ap.add_argument("--json", help="also write the rows here")
    ap.add_argument("--pybotics-path", dest="pybotics_path", default=os.environ.get("PYBOTICS_PATH"),
                    help="a folder holding pybotics (pip install --target), appended to sys.path after the "
                         "venv's site-packages; default $PYBOTICS_PATH")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = run(tuple(args.poses), args.held_out, pybotics_path=args.pybotics_path)
    print(markdown(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
