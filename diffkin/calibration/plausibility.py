"""Whether a calibration result is credible: the checks behind ``CalibrationResult.success``.

A calibration corrects a robot's geometry by millimetres and tenths of a degree. A fit that needs more —
or one that explains the calibration poses but not held-out ones — usually means other data than the user
thinks: another robot of the same joint count, another end link, joint readings in other units. Three
checks, all of one robot's result:

* **held-out error** (k-fold cross-validation): a held-out position RMS above :data:`CV_RATIO` times the fit's
  (and above :data:`CV_FLOOR_M`, or the noise's expected norm when given) fails; likewise orientation
  (:data:`CV_FLOOR_RAD`).
* **noise ratio** (with ``measurement_noise``): a fit residual above :data:`NOISE_RATIO` times what the noise
  explains fails (2x already warns).
* **size of the corrections**: every link's pose relative to its parent frame, nominal against calibrated,
  at the calibration poses: frames 1..n of ``forward_kinematics(q, all_frames=True)``, X_k = F_{k−1}⁻¹ F_k.
  A change beyond the bound ``max_correction`` (default 5 cm / 10°) of a link before the last fails (the
  data are of another robot); of the last one (the last joint's link, the fixed joints to the end link and
  the tool) it warns and, for a URDF robot, names the link rigidly attached to the last moving link whose
  nominal frame the calibrated end frame matches (``--end-link`` names the wrong frame). The base frame
  is not bounded: a tracker's frame may be anywhere.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..kernels.pose_error import rotation_angle

__all__ = ["CV_RATIO", "CV_FLOOR_M", "CV_FLOOR_RAD", "NOISE_RATIO", "MAX_CORRECTION", "fit_failures",
           "frame_changes", "end_link_fit", "correction_findings"]

#: a held-out (cross-validated) error this many times the fit's fails the result
CV_RATIO = 5.0
#: ... unless it is below this (metres; noise-free data fit to 1e-9 m and hold out to 1e-8 m)
CV_FLOOR_M = 1e-5
#: ... or, for orientation, below this (radians)
CV_FLOOR_RAD = 1e-4
#: a fit residual this many times what ``measurement_noise`` explains fails the result (2x warns)
NOISE_RATIO = 5.0
#: the default plausibility bound of one link's correction: 5 cm, 10 degrees
MAX_CORRECTION = (0.05, math.radians(10.0))


def fit_failures(fit_position: float, fit_orientation: float | None, cv: dict | None,
                 noise_ratio: float | None, noise=None) -> list[str]:
    """The reasons (sentences) a fit of RMS ``fit_position`` (m) / ``fit_orientation`` (rad) fails the
    held-out and noise checks (module doc); ``cv``: ``CalibrationResult.cross_validation`` or None."""
    out = []
    if cv is not None:
        floor = CV_FLOOR_M if noise is None else max(CV_FLOOR_M, math.sqrt(3) * float(noise[0]))
        held = cv["position_rms"]
        if held > CV_RATIO * max(fit_position, floor):
            out.append(f"the {cv['folds']}-fold cross-validated held-out position RMS is "
                       f"{held * 1e3:.4g} mm against {fit_position * 1e3:.4g} mm of the fit "
                       f"({held / max(fit_position, 1e-300):.3g}x; more than {CV_RATIO:g}x fails): the "
                       "parameters fit these poses only")
        held_o = cv.get("orientation_rms")
        if held_o is not None and fit_orientation is not None:
            floor_o = CV_FLOOR_RAD if noise is None or len(noise) < 2 else max(
                CV_FLOOR_RAD, math.sqrt(3) * float(noise[1]))
            if held_o > CV_RATIO * max(fit_orientation, floor_o):
                out.append(f"the cross-validated held-out orientation RMS is {math.degrees(held_o):.4g} deg "
                           f"against {math.degrees(fit_orientation):.4g} deg of the fit")
    if noise_ratio is not None and noise_ratio > NOISE_RATIO:
        out.append(f"the fit residual is {noise_ratio:.3g}x what the measurement noise explains (more than "
                   f"{NOISE_RATIO:g}x fails)")
    return out


def _relative(chain, q: Tensor) -> Tensor:
    """X_k = F_{k−1}⁻¹ F_k ``(N, n, 4, 4)``: each frame of ``forward_kinematics(q, all_frames=True)``
    relative to the one before (frame 0: the base)."""
    with torch.no_grad():
        F = chain.forward_kinematics(q, all_frames=True)
    if F.ndim == q.ndim + 3:  # several end links: not a serial list of frames
        raise ValueError("several end links")
    return torch.linalg.solve(F[..., :-1, :, :], F[..., 1:, :, :])


def frame_changes(nominal, calibrated, q: Tensor, *, other=None) -> tuple[Tensor, Tensor]:
    """``(translation (n,), angle (n,))``: the largest change over the poses ``q (N, n)`` of each link's
    pose relative to its parent frame (X_k above), calibrated against nominal (metres, radians).
    ``other``: compare against this chain's X instead of ``nominal``'s (same joint count)."""
    Xn = _relative(nominal if other is None else other, q)
    Xc = _relative(calibrated, q.to(calibrated.dtype))
    Xn = Xn.to(Xc.dtype)
    dt = (Xc[..., :3, 3] - Xn[..., :3, 3]).norm(dim=-1).amax(0)
    da = rotation_angle(Xc[..., :3, :3], Xn[..., :3, :3]).amax(0)
    return dt, da


def _size(t: float, a: float) -> str:
    return f"{t * 1e3:.2f} mm / {math.degrees(a):.2f} deg"


def _frame_label(chain, k: int) -> str:
    """Frame ``k`` (1..n) in words: the link a URDF joint moves, else the joint's number."""
    links = getattr(chain, "link_names", None)
    if links is not None and len(links) == chain.n_joints and 1 <= k <= len(links):
        return f"link '{links[k - 1]}' (joint {k})"
    return f"joint {k}"


def _fixed_to(tree, link: str) -> list[str]:
    """Links attached to ``link`` by fixed joints only (``link`` included), down the tree."""
    out, todo = [], [link]
    while todo:
        cur = todo.pop()
        out.append(cur)
        todo += [j.child for j in tree.children(cur) if j.type == "fixed"]
    return out


def end_link_fit(nominal, calibrated, q: Tensor, bound: tuple[float, float]
                 ) -> tuple[str, float, float] | None:
    """For a URDF robot: ``(link, translation, angle)`` of the link rigidly attached to the last moving link
    whose nominal frame the calibrated end frame is nearest to (X_n compared at the poses ``q``), when that
    is within ``bound`` and it is not the chain's own end link; else None."""
    tree = getattr(nominal, "tree", None)
    ends = getattr(nominal, "end_links", None)
    links = getattr(nominal, "link_names", None)
    if tree is None or not ends or len(ends) != 1 or not links:
        return None
    from ..models.urdf import from_urdf

    best = None
    for link in _fixed_to(tree, links[-1]):
        if link == ends[0]:
            continue
        try:
            other = from_urdf(tree, link, root_link=nominal.root_link, dtype=nominal.dtype)
        except Exception:  # noqa: BLE001 - a link this robot cannot end at is no candidate
            continue
        if other.joint_names != nominal.joint_names:
            continue
        dt, da = frame_changes(nominal, calibrated, q, other=other)
        score = float(dt[-1]) / bound[0] + float(da[-1]) / bound[1]
        if best is None or score < best[0]:
            best = (score, link, float(dt[-1]), float(da[-1]))
    if best is None or best[2] > bound[0] or best[3] > bound[1]:
        return None
    return best[1], best[2], best[3]


def correction_findings(nominal, calibrated, q: Tensor, bound: tuple[float, float] | None
                        ) -> tuple[list[str], str | None]:
    """``(failures, end_warning)`` of the correction-size check (module doc): a sentence per link before
    the last whose change exceeds ``bound`` (metres, radians; None: no check), and one sentence when the
    last link's (the end link's) does, naming the end link that would fit where one does."""
    if bound is None:
        return [], None
    try:
        dt, da = frame_changes(nominal, calibrated, q)
    except ValueError:  # several end links: the check is per serial chain
        return [], None
    lim_t, lim_a = bound
    over = [(k, float(t), float(a)) for k, (t, a) in enumerate(zip(dt.tolist(), da.tolist()), start=1)
            if t > lim_t or a > lim_a]
    size = f"(bound {lim_t * 1e3:g} mm / {math.degrees(lim_a):g} deg)"
    failures, end = [], None
    inner = [o for o in over if o[0] < nominal.n_joints]
    if inner:
        parts = ", ".join(f"{_frame_label(nominal, k)} by {_size(t, a)}"
                          for k, t, a in inner[:4]) + (", ..." if len(inner) > 4 else "")
        failures.append(f"the identified geometry moves {parts} relative to the nominal robot {size}: more "
                        "than a calibration corrects; the data are probably of another robot (or the joint "
                        "readings are in other units or zeros)")
    last = [o for o in over if o[0] == nominal.n_joints]
    if last:
        _, t, a = last[0]
        ends = getattr(nominal, "end_links", None)
        name = f"end link '{ends[0]}'" if ends and len(ends) == 1 else "end frame (last link and tool)"
        end = (f"the {name} is corrected by {_size(t, a)} {size}: more than a "
               "calibration corrects; the measured frame is probably another one")
        fit = end_link_fit(nominal, calibrated, q, bound)
        if fit is not None:
            end += (f": end link '{fit[0]}' fits (its nominal frame is within {_size(fit[1], fit[2])} of the "
                    f"calibrated one; --end-link {fit[0]})")
        else:
            end += " (check the end link or tool the measurements were taken at)"
    return failures, end
