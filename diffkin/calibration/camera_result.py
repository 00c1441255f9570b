"""The result of :func:`~diffkin.calibration.calibrate_camera`: the calibrated robot, the camera's and the
board's poses, the intrinsics, the reprojection error, the identifiability report; reports and exports."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor

from ..chain import KinematicChain
from ..errors import DiffkinError, OptionError, ShapeError, require
from ..rotations import _matrix_to_rotvec
from .api import save_figure
from .identifiability import IdentifiabilityReport

__all__ = ["CameraCalibrationResult"]

_DEG = 180.0 / math.pi


def _rpy(R: Tensor) -> list[float]:
    """URDF's roll, pitch, yaw (R = Rz(yaw) Ry(pitch) Rx(roll)) of a rotation matrix (3, 3)."""
    r = R.tolist()
    pitch = math.asin(max(-1.0, min(1.0, -r[2][0])))
    if abs(r[2][0]) < 1 - 1e-12:
        return [math.atan2(r[2][1], r[2][2]), pitch, math.atan2(r[1][0], r[0][0])]
    return [0.0, pitch, math.atan2(-r[0][1], r[1][1])]  # gimbal lock: roll folded into yaw


@dataclass
class CameraCalibrationResult:
    """Outcome of :func:`~diffkin.calibration.calibrate_camera`.

    ``chain``: the calibrated copy of the robot (same kind as the nominal; ``to_urdf(path)`` for URDF
    chains); ``camera_pose`` ``(4, 4)``: T_base_cam (eye-to-hand) or T_flange_cam (eye-in-hand);
    ``board_pose`` ``(4, 4)``: T_flange_board (eye-to-hand) or T_base_board (eye-in-hand); ``camera_matrix``
    ``(3, 3)``, ``dist_coeffs`` ``(5,)`` (k1, k2, p1, p2, k3; the given ones unless ``"intrinsics"`` was
    estimated); ``reprojection_rms``: √(mean over the visible points of |measured − projected|²) in pixels
    (OpenCV's definition; √2 σ for noise of σ per coordinate); ``residuals``: that RMS at the start and after
    every iteration; ``initial_reprojection_rms``: at the start (nominal robot, hand-eye poses).
    ``report``: identifiability (:class:`IdentifiabilityReport`; ``report.unidentifiable``: what the images
    cannot separate from the camera's and board's poses, kept at nominal, with ``report.reasons``);
    ``names``, ``units``, ``nominal``, ``identified``: every candidate parameter (camera and board entries
    are corrections Δ on the starting poses ``initial_camera_pose`` / ``initial_board_pose``).
    ``noise_ratio``: χ = √(Σ (r/σ)² / (2·points − rank)) for ``measurement_noise`` σ (≈ 1 for an adequate
    model; None without σ); ``cross_validation``: the k-fold held-out reprojection RMS over images
    (``folds``, ``reprojection_rms``, ``reprojection_max`` in px); ``outliers``: ``(image, point)`` pairs
    whose residual exceeds ``outlier_threshold`` px; ``image_rms`` ``(N,)``: per image, after the fit.
    ``image_points`` ``(N, M, 2)``: the measured pixels, ``visible`` ``(N, M)``, and ``reprojected`` /
    ``initial_reprojected`` ``(N, M, 2)``: the board points projected by the calibrated model / at the start
    (nominal robot, hand-eye poses) — the projections ``image_rms`` / ``initial_image_rms`` are computed
    from (NaN where not visible); drawn per image by :meth:`plot_image_residuals`.
    """

    chain: KinematicChain
    nominal_chain: KinematicChain
    camera_pose: Tensor
    board_pose: Tensor
    camera_matrix: Tensor
    dist_coeffs: Tensor
    reprojection_rms: float
    setup: str
    method: str
    estimate: tuple[str, ...]
    names: list[str]
    units: list[str]
    nominal: Tensor
    identified: Tensor
    report: IdentifiabilityReport
    residuals: list[float]
    iterations: int
    converged: bool
    initial_camera_pose: Tensor = field(repr=False)
    initial_board_pose: Tensor = field(repr=False)
    initial_reprojection_rms: float = math.nan
    error_model: str = "general"
    noise_ratio: float | None = None
    cross_validation: dict | None = None
    outliers: list[tuple[int, int]] = field(default_factory=list)
    outlier_threshold: float | None = None
    image_rms: Tensor | None = field(default=None, repr=False)
    initial_image_rms: Tensor | None = field(default=None, repr=False)
    loss: str = "l2"
    notes: list[str] = field(default_factory=list)
    image_points: Tensor | None = field(default=None, repr=False)
    visible: Tensor | None = field(default=None, repr=False)
    reprojected: Tensor | None = field(default=None, repr=False)
    initial_reprojected: Tensor | None = field(default=None, repr=False)

    @property
    def determined(self) -> bool:
        """The images determine every structurally identifiable parameter (``report.undetermined`` empty)."""
        return not self.report.undetermined

    def parameter_table(self) -> list[dict]:
        """Rows ``{name, nominal, identified, delta, unit, identifiable}`` per candidate (SI units, px)."""
        fixed = set(self.report.unidentifiable)
        return [
            {
                "name": nm,
                "nominal": a,
                "identified": b,
                "delta": b - a,
                "unit": u,
                "identifiable": nm not in fixed,
            }
            for nm, u, a, b in zip(self.names, self.units, self.nominal.tolist(), self.identified.tolist())
        ]

    def to_markdown(self) -> str:
        """The parameter table as Markdown (lengths in mm, angles in degrees, intrinsics in px)."""
        lines = ["| parameter | start | identified | delta | |", "|---|---:|---:|---:|---|"]
        for r in self.parameter_table():
            f, u = {"m": (1e3, "mm"), "rad": (_DEG, "deg"), "px": (1.0, "px")}.get(r["unit"], (1.0, ""))
            note = "" if r["identifiable"] else "fixed (unidentifiable)"
            lines.append(
                f"| {r['name']} | {r['nominal'] * f:.4f} | {r['identified'] * f:.4f} | "
                f"{r['delta'] * f:+.4f} {u} | {note} |"
            )
        return "\n".join(lines)

    def summary(self) -> str:
        cam = "T_base_cam" if self.setup == "eye_to_hand" else "T_flange_cam"
        p = self.camera_pose[:3, 3].tolist()
        lines = [
            f"camera calibration of '{self.chain.name}' ({self.setup}, {self.method}; estimated: "
            f"{', '.join(self.estimate)}): {self.iterations} iterations, "
            f"{'converged' if self.converged else 'NOT converged'}",
            f"reprojection RMS {self.initial_reprojection_rms:.4f} px -> {self.reprojection_rms:.4f} px",
            f"camera pose ({cam}) at [{p[0] * 1e3:.2f}, {p[1] * 1e3:.2f}, {p[2] * 1e3:.2f}] mm",
        ]
        if self.cross_validation is not None:
            cv = self.cross_validation
            lines.append(
                f"{cv['folds']}-fold cross-validated held-out reprojection RMS "
                f"{cv['reprojection_rms']:.4f} px (max {cv['reprojection_max']:.4f} px)"
            )
        if self.noise_ratio is not None:
            lines.append(f"fit residual / measurement noise: {self.noise_ratio:.2f} (about 1 expected)")
        if self.outlier_threshold is not None:
            lines.append(f"outliers: {len(self.outliers)} points beyond {self.outlier_threshold:.3f} px")
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines + [self.report.summary()])

    # ------------------------------------------------------------------------------------ exports
    def camera_joint_urdf(
        self, name: str = "camera_joint", parent: str | None = None, child: str = "camera_optical_frame"
    ) -> str:
        """The camera pose as a URDF ``<joint type="fixed">`` element (xyz in metres, rpy in radians); the
        parent is the chain's base link (eye-to-hand) or its end link (eye-in-hand) unless given."""
        if parent is None:
            links = getattr(self.chain, "link_names", None) or []
            base = getattr(self.chain, "base_link", None) or "base_link"
            end = links[-1] if links else "flange"
            ends = getattr(self.chain, "end_links", None)
            if ends:
                end = ends[0]
            parent = base if self.setup == "eye_to_hand" else end
        xyz = " ".join(f"{v:.9g}" for v in self.camera_pose[:3, 3].tolist())
        rpy = " ".join(f"{v:.9g}" for v in _rpy(self.camera_pose[:3, :3]))
        return (
            f'<joint name="{name}" type="fixed">\n  <parent link="{parent}"/>\n  <child link="{child}"/>\n'
            f'  <origin xyz="{xyz}" rpy="{rpy}"/>\n</joint>'
        )

    def to_yaml(self, path: str | Path | None = None) -> str:
        """The camera (pose, camera matrix, distortion), the board's pose and the fit's figures as YAML
        (written to ``path`` when given). Poses as translation (m), rotation vector (rad), URDF rpy (rad)
        and the 4 x 4 matrix."""

        def pose(T: Tensor, frame: str) -> list[str]:
            rows = [
                f"  frame: {frame}",
                f"  xyz: {T[:3, 3].tolist()}",
                f"  rotvec: {_matrix_to_rotvec(T[:3, :3]).tolist()}",
                f"  rpy: {_rpy(T[:3, :3])}",
                f"  matrix: {T.tolist()}",
            ]
            return rows

        cam_frame, board_frame = ("base", "flange") if self.setup == "eye_to_hand" else ("flange", "base")
        lines = [f"setup: {self.setup}", f"robot: {self.chain.name}", "camera_pose:"]
        lines += pose(self.camera_pose, cam_frame)
        lines += ["board_pose:"] + pose(self.board_pose, board_frame)
        lines += [
            f"camera_matrix: {self.camera_matrix.tolist()}",
            f"dist_coeffs: {self.dist_coeffs.tolist()}  # k1, k2, p1, p2, k3",
            f"reprojection_rms_px: {self.reprojection_rms}",
        ]
        text = "\n".join(lines) + "\n"
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            Path(path).write_text(text)
        return text

    def plot_residuals(self, path: str | Path) -> Path:
        """PNG: per-image reprojection RMS before (nominal robot, hand-eye poses) and after the fit, and the
        RMS per iteration. Needs matplotlib (a Figure, no pyplot: the process's backend is left alone)."""
        Figure = require("matplotlib.figure", "plot", "CameraCalibrationResult.plot_residuals").Figure
        fig = Figure(figsize=(10, 4))
        ax, ax2 = fig.subplots(1, 2)
        i = range(len(self.image_rms))
        ax.semilogy(i, self.initial_image_rms.cpu().numpy(), "o", ms=4, label="start (nominal robot)")
        ax.semilogy(i, self.image_rms.cpu().numpy(), "s", ms=4, label="calibrated")
        ax.set_xlabel("image")
        ax.set_ylabel("reprojection RMS [px]")
        ax.legend()
        ax2.semilogy(self.residuals, marker="o", ms=3)
        ax2.set_xlabel(f"iteration ({self.method})")
        ax2.set_ylabel("reprojection RMS [px]")
        fig.suptitle(f"camera calibration of '{self.chain.name}' ({self.setup})")
        return save_figure(fig, path)

    def plot_image_residuals(
        self,
        i: int,
        path: str | Path | None = None,
        image=None,
        *,
        scale: float | None = None,
        size: tuple[int, int] | None = None,
        title: str | None = None,
    ):
        """One picture's reprojection residuals, OpenCV-style: picture ``i`` (``image``: an array ``(H, W)``
        or ``(H, W, 3)`` in RGB order, e.g. ``cv2.cvtColor(cv2.imread(f), cv2.COLOR_BGR2RGB)``; None: a blank
        canvas of ``size = (W, H)`` px, by default (2⌈cx⌉, 2⌈cy⌉) of the camera matrix) with the detected
        corners (``image_points[i]``), the corners projected at the start (``initial_reprojected[i]``: nominal
        robot, hand-eye poses) and by the calibrated model (``reprojected[i]``), and the residual vectors
        from each detected corner to its two projections, magnified ``scale`` times (default: the longest
        start residual drawn at about 4 % of the picture's diagonal, rounded to 1, 2 or 5 × 10^k; the
        factor is in the legend).
        Writes a PNG to ``path`` and returns the path; without ``path`` returns the matplotlib Figure (no
        pyplot: the process's backend is left alone). Needs matplotlib."""
        import numpy as np

        Figure = require("matplotlib.figure", "plot", "CameraCalibrationResult.plot_image_residuals").Figure
        if self.reprojected is None:
            raise DiffkinError("this result holds no per-point projections (calibrate_camera's results do)")
        n = self.image_points.shape[0]
        if not isinstance(i, int) or not -n <= i < n:
            raise OptionError(f"expected an image index in [0, {n}), got {i!r}")
        vis = self.visible[i].cpu().numpy()
        meas, after, before = (
            t[i].detach().cpu().double().numpy()[vis]
            for t in (self.image_points, self.reprojected, self.initial_reprojected)
        )
        if image is not None:
            image = np.asarray(image.detach().cpu() if isinstance(image, Tensor) else image)
            if image.ndim not in (2, 3):
                raise ShapeError(f"expected image (H, W) or (H, W, 3), got {tuple(image.shape)}")
            H, W = image.shape[:2]
        elif size is not None:
            W, H = int(size[0]), int(size[1])
        else:  # a centred principal point is at (W - 1) / 2 (OpenCV's pixel centres) or W / 2: W even
            K = self.camera_matrix.tolist()
            W, H = 2 * math.ceil(K[0][2]), 2 * math.ceil(K[1][2])
        r0, r1 = meas - before, meas - after
        if scale is None:
            longest = float(np.linalg.norm(r0, axis=-1).max()) if len(r0) else 0.0
            raw = 0.04 * math.hypot(W, H) / max(longest, 1e-12)
            k = 10.0 ** math.floor(math.log10(raw))
            scale = max(m * k for m in (1, 2, 5) if m * k <= raw)
        fig = Figure(figsize=(7, 7 * H / W + 0.6))
        ax = fig.subplots()
        if image is not None:
            top = 255 if image.dtype.kind in "ui" else 1
            grey = dict(cmap="gray", vmin=0, vmax=top) if image.ndim == 2 else {}
            ax.imshow(image, extent=(-0.5, W - 0.5, H - 0.5, -0.5), **grey)  # grey levels as they are
        else:
            ax.set_facecolor("white")
        rms0, rms1 = float(self.initial_image_rms[i]), float(self.image_rms[i])
        ax.plot(meas[:, 0], meas[:, 1], "+", color="lime", ms=6, mew=1.0, label="detected")
        ax.plot(before[:, 0], before[:, 1], "o", mfc="none", color="tab:orange", ms=5,
                label=f"start (nominal robot), RMS {rms0:.3f} px")
        ax.plot(after[:, 0], after[:, 1], "x", color="tab:blue", ms=5,
                label=f"calibrated, RMS {rms1:.3f} px")
        for r, c in ((r0, "tab:orange"), (r1, "tab:blue")):  # residuals from the detected corner, magnified
            ax.quiver(meas[:, 0], meas[:, 1], -r[:, 0] * scale, -r[:, 1] * scale, color=c, angles="xy",
                      scale_units="xy", scale=1.0, width=0.003)
        ax.plot([], [], "-", color="gray", label=f"projected - detected, x{scale:g}")
        ax.set_xlim(-0.5, W - 0.5)
        ax.set_ylim(H - 0.5, -0.5)  # image rows down
        ax.set_aspect("equal")
        ax.set_xlabel("u [px]")
        ax.set_ylabel("v [px]")
        ax.legend(loc="upper right", fontsize=8, framealpha=0.8)
        ax.set_title(title or f"image {i % n}: reprojection before / after calibration")
        fig.subplots_adjust(left=0.11, right=0.98, bottom=0.07, top=0.94)  # fixed: no layout pass
        # one figure per picture in a report: a fast PNG compression (the pictures' noise compresses badly)
        return fig if path is None else save_figure(fig, path, tight=False, pil_kwargs={"compress_level": 3})
