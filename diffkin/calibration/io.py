"""File entry of calibration (for ``diffkin calibrate``): read measurements, calibrate, write outputs."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import Tensor

from ..chain import DHChain
from ..io.data import read_measurements
from .api import CalibrationResult, calibrate

__all__ = ["load_measurements", "calibrate_from_files", "write_robot"]


def load_measurements(
    joints: str | Path,
    poses: str | Path | None = None,
    n_joints: int | None = None,
    dtype: torch.dtype = torch.float64,
) -> tuple[Tensor, Tensor]:
    """``(q (N, n), T (N, 4, 4) or positions (N, 3))`` from files, read by
    :func:`diffkin.io.data.read_measurements` (the reader ``diffkin calibrate`` uses).

    With ``poses=None`` both come from ``joints``: an ``.npz`` holding ``q`` and ``T`` (or ``position`` and
    optionally ``quaternion``), or a ``.csv`` read by its header (``q1..qn,x,y,z[,qw,qx,qy,qz]``, e.g.
    ``diffkin fk``'s output); otherwise the joints and poses come from two files (``.npy``, ``.npz``,
    ``.csv``). ``n_joints``: the robot's joint count, checked (None: the file's own, by header or shape).
    """
    q, T, _ = read_measurements(joints, poses, n_joints, dtype=dtype)
    return q, T


def write_robot(chain, out_dir: str | Path) -> Path:
    """Write a calibrated chain into ``out_dir`` in its own format: ``calibrated.xml`` (MJCF),
    ``calibrated.yaml`` (DH) or ``calibrated.urdf`` (URDF); returns the path."""
    out = Path(out_dir)
    if hasattr(chain, "to_mjcf"):
        path = out / "calibrated.xml"
        chain.to_mjcf(path)
    elif hasattr(chain, "to_yaml"):
        path = out / "calibrated.yaml"
        path.write_text(chain.to_yaml())
    else:
        path = out / "calibrated.urdf"
        chain.to_urdf(path)
    return path


def calibrate_from_files(
    robot: DHChain | str | Path,
    joints: str | Path,
    poses: str | Path | None = None,
    *,
    end_link: str | None = None,
    out_dir: str | Path | None = None,
    method: str = "least_squares",
    validation: tuple | None = None,
    force: bool = False,
    **options,
) -> CalibrationResult:
    """Calibrate ``robot`` (a chain, a built-in model name, a robot YAML file, or a URDF or MJCF file with
    ``end_link``: :func:`diffkin.models.load_chain`, float64) from measurement files.

    Writes, when ``out_dir`` is given: ``calibrated.yaml``, ``calibrated.urdf`` or ``calibrated.xml`` (the
    calibrated chain: ``to_yaml``, ``to_urdf``, ``to_mjcf``),
    ``parameters.md`` (the identified table), ``report.json`` (residuals, identifiability, noise check,
    cross-validation, validation) and ``residuals.png``.
    ``validation``: optional ``(joints, poses)`` files of held-out measurements scored before and after.
    A result that fails its plausibility checks (``result.success`` False, :mod:`.plausibility`) gets its
    report but not the calibrated robot, unless ``force``.
    ``options`` go to :func:`calibrate` (parameters, base, tool, joint_offsets, progress, ...).
    """
    from ..chain import KinematicChain
    from ..models import load_chain

    chain = load_chain(robot, end_link, dtype=None if isinstance(robot, KinematicChain) else torch.float64)
    q, T = load_measurements(joints, poses, chain.n_joints, chain.dtype)
    result = calibrate(chain, q, T, method=method, **options)
    if out_dir is None:
        return result
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if result.success or force:  # a failed result: the report says why, the robot is not written
        write_robot(result.chain, out)
    (out / "parameters.md").write_text(result.to_markdown() + "\n")
    info = {
        "method": method,
        "error_model": result.error_model,
        "iterations": result.iterations,
        "converged": result.converged,
        "success": result.success,
        "failure": result.failure,
        "noise_ratio": result.noise_ratio,
        "cross_validation": result.cross_validation,
        "notes": result.notes,
        "loss": result.loss,
        "outliers": result.outliers,
        "outlier_threshold_m": result.outlier_threshold,
        "pose_position_errors_m": result.pose_position_errors.tolist(),
        "residuals_m": result.residuals,
        "orientation_residuals_rad": result.orientation_residuals,
        "identifiability": result.report.as_dict(),
        "parameters": result.parameter_table(),
    }
    if validation is not None:
        qv, Tv = load_measurements(*validation, chain.n_joints, chain.dtype)
        from .api import validation_error

        info["validation"] = {
            "nominal": validation_error(chain, qv, Tv),
            "calibrated": result.validation_error(qv, Tv),
        }
    (out / "report.json").write_text(json.dumps(info, indent=2))
    result.plot_residuals(out / "residuals.png")
    return result
