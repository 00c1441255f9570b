"""``diffkin calibrate``: a robot's geometry from measured poses or positions, or from pictures of a board
(``--images``), written back as YAML / URDF / MJCF with a report."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from ..errors import DiffkinError
from ._common import _check_output_dir, _console, _load_chain, _print_whole, _table


# ------------------------------------------------------------------------------------- calibrate
def cmd_calibrate(args) -> int:
    import warnings

    from ..calibration import calibrate_from_files
    from ..errors import ModelError
    from ..io.data import check_output_path

    if args.images is not None or args.joints is not None:
        return _cmd_calibrate_images(args)
    if args.data is None:
        raise DiffkinError("calibrate needs --data FILE (measured poses) or --images DIR with --joints FILE")
    out = Path(args.output)
    suffixes = (".yaml", ".yml", ".urdf", ".xml")
    as_dir = out.suffix not in suffixes
    if as_dir:
        if out.suffix:
            raise ModelError(f"--output {out}: give a .yaml (DH robot), a .urdf (URDF robot), an .xml (MJCF "
                             "robot) or a directory")
        _check_output_dir(out)
    else:
        check_output_path(out, suffixes)
    args.device, args.dtype = "cpu", "float64"  # calibration corrects by micrometres: float64 on the CPU
    chain = _load_chain(args)  # --robot NAME|FILE, --urdf / --mjcf FILE --end-link: as fk, ik and view
    kind = _written_kind(chain)
    if not as_dir and (".yaml" if out.suffix == ".yml" else out.suffix) != kind:
        raise ModelError(f"--output {out}: a DH robot (--robot NAME or YAML) is written as .yaml, a URDF "
                         f"robot as .urdf, an MJCF robot as .xml; this one as {kind} (or give a directory)")
    noise = None if args.noise is None else (args.noise[0] * 1e-3, math.radians(args.noise[1]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = calibrate_from_files(
            chain, args.data, method=args.method, progress=not args.no_progress,
            out_dir=out if as_dir else None, force=args.force, error_model=args.error_model,
            base=args.base, tool=args.tool, measurement_noise=noise, cross_validation=args.cv, loss=args.loss,
        )
    written = None
    if res.success or args.force:
        if as_dir:
            written = out / f"calibrated{kind}"  # calibrate_from_files wrote it
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
            if kind == ".urdf":
                res.chain.to_urdf(out)
            elif kind == ".xml":
                res.chain.to_mjcf(out)
            else:
                out.write_text(res.chain.to_yaml())
            written = out
    con = _console()
    title = f"calibration of '{res.nominal_chain.name}' ({args.method}; lengths mm, angles deg)"
    rows = res.display_rows()
    # the whole parameter names, whatever the terminal's width (URDF joints: "shoulder_pan_joint.dx")
    _print_whole(con, _table(title, ["parameter", "nominal", "identified", "delta", "unit", ""], rows,
                             whole=(0, 1, 2, 3, 4)))
    rows = [["position RMS [mm]", f"{res.residuals[0] * 1e3:.4f}", f"{res.residuals[-1] * 1e3:.4f}"]]
    if res.orientation_residuals is not None:
        rows.append(["orientation RMS [deg]", f"{math.degrees(res.orientation_residuals[0]):.5f}",
                     f"{math.degrees(res.orientation_residuals[-1]):.5f}"])
    cv = res.cross_validation
    if cv is not None:
        rows.append([f"held-out position RMS [mm] ({cv['folds']}-fold CV)", "",
                     f"{cv['position_rms'] * 1e3:.4f}"])
    con.print(_table(f"before / after ({res.error_model} model, "
                     f"{'converged' if res.converged else 'NOT converged'})",
                     ["", "before", "after"], rows))
    if res.noise_ratio is not None:
        con.print(f"noise check: fit residual / measurement noise = {res.noise_ratio:.2f} (about 1 expected)")
    if res.outliers or res.loss != "l2":
        con.print(res.outlier_summary())
    for w in caught:
        con.print(f"[bold yellow]warning:[/] {w.message}")
    for note in res.notes:
        if not any(note in str(w.message) for w in caught):  # said once, as the warning
            con.print(f"note: {note}")
    if written is not None:
        con.print(f"wrote {written}" + (f" and the report in {out}" if as_dir else ""))
    elif as_dir:
        con.print(f"wrote the report in {out} (not the calibrated robot)")
    if res.report.unidentifiable:
        con.print(
            "not identifiable from these poses (kept at nominal): " + ", ".join(res.report.unidentifiable)
        )
    if not res.success:
        if not args.force:
            raise DiffkinError(f"calibration of '{res.nominal_chain.name}' failed: {res.failure}; the "
                               "calibrated robot was not written (--force writes it and exits 0)")
        con.print("[bold yellow]warning:[/] the calibration failed its plausibility checks; written anyway "
                  "(--force)")
    return 0


def _cmd_calibrate_images(args) -> int:
    """``calibrate --images DIR --joints FILE``: board pictures -> detect_board -> calibrate_camera."""
    import warnings

    from ..calibration.camera_io import calibrate_camera_from_files, write_camera_report

    need = {"--images": args.images, "--joints": args.joints, "--board": args.board, "--square": args.square,
            "--camera": args.camera}
    missing = [k for k, v in need.items() if v is None]
    if missing:
        raise DiffkinError(f"calibrate --images needs {', '.join(missing)} as well (see --help)")
    if args.data is not None:
        raise DiffkinError("give --data (measured poses) or --images with --joints (board pictures), "
                           "not both")
    if args.base or args.tool or args.noise is not None:
        raise DiffkinError("--base, --tool and --noise are for --data; with --images the camera's and the "
                           "board's poses are always estimated (--pixel-noise PX for the noise check)")
    out = Path(args.output)
    if out.suffix:
        raise DiffkinError(f"--output {out}: with --images give a directory (the calibrated robot, "
                           "camera.yaml, camera_joint.urdf, report.md, residuals.png, residuals/)")
    _check_output_dir(out)
    args.device, args.dtype = "cpu", "float64"  # calibration corrects by micrometres: float64 on the CPU
    chain = _load_chain(args)
    fx, fy, cx, cy = args.camera
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    if args.dist is not None and len(args.dist) not in (4, 5):
        raise DiffkinError(f"--dist: expected 4 or 5 numbers (k1 k2 p1 p2 [k3]), got {len(args.dist)}")
    dist = None if args.dist is None else torch.tensor(args.dist, dtype=torch.float64)
    estimate = ("robot", "camera", "board") + (("intrinsics",) if args.intrinsics else ())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res, det = calibrate_camera_from_files(
            chain, args.images, args.joints, board=tuple(args.board), square=args.square, camera_matrix=K,
            detector=args.detector, marker=args.charuco_marker, dictionary=args.charuco_dictionary,
            dist_coeffs=dist, setup=args.setup, estimate=estimate, method=args.method,
            error_model=args.error_model, measurement_noise=args.pixel_noise, loss=args.loss,
            cross_validation=args.cv, progress=not args.no_progress,
        )
    written = write_camera_report(res, det, out, images=args.images)
    con = _console()
    con.print(f"board found in {int(det.found.sum())} of {len(det.names)} pictures"
              + ("" if bool(det.found.all()) else " (not in: "
                 + ", ".join(n for n, f in zip(det.names, det.found.tolist()) if not f) + ")"))
    title = f"camera calibration of '{res.nominal_chain.name}' ({args.method}; lengths mm, angles deg)"
    unit = {"m": (1e3, "mm"), "rad": (180.0 / math.pi, "deg"), "px": (1.0, "px")}
    rows = []
    for r in res.parameter_table():
        f, u = unit.get(r["unit"], (1.0, r["unit"]))
        rows.append([r["name"], f"{r['nominal'] * f:.4f}", f"{r['identified'] * f:.4f}",
                     f"{r['delta'] * f:+.4f}", u if r["identifiable"] else f"{u} (fixed: unidentifiable)"])
    if rows:
        _print_whole(con, _table(title, ["parameter", "nominal", "identified", "delta", "unit"], rows,
                                 whole=(0, 1, 2, 3, 4)))
    con.print(res.summary())
    for w in caught:
        con.print(f"[bold yellow]warning:[/] {w.message}")
    con.print("wrote " + ", ".join(str(p) for p in written))
    return 0


def _written_kind(chain) -> str:
    """The file a calibrated ``chain`` is written as: ``.xml`` (MJCF), ``.yaml`` (DH) or ``.urdf``."""
    if hasattr(chain, "to_mjcf"):
        return ".xml"
    return ".yaml" if hasattr(chain, "to_yaml") else ".urdf"
