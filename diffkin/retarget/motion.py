"""A human clip: joint positions (and optionally orientations) over time, in metres with z up."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ..errors import ModelError, NonFiniteError, ShapeError
from ..validation import as_tensor, check_number, shape_str

__all__ = ["Motion"]


def _nonfinite_frames(x: Tensor, name: str) -> None:
    """NonFiniteError naming the (clip, frame) entries of ``x`` (B, T, ...) that hold NaN or inf."""
    bad = ~torch.isfinite(x.reshape(x.shape[0], x.shape[1], -1)).all(-1)  # (B, T)
    if bool(bad.any()):
        where = bad.nonzero().tolist()
        shown = ", ".join(f"(clip {b}, frame {t})" for b, t in where[:6])
        more = f" and {len(where) - 6} more" if len(where) > 6 else ""
        raise NonFiniteError(f"{name} holds NaN or inf in {len(where)} frame(s): {shown}{more}; expected "
                             "finite numbers in every frame (drop or fill the frames first)")


class Motion:
    """B clips of T frames of J named joints, sampled at ``fps`` frames per second.

    Args:
        positions: joint positions ``(B, T, J, 3)`` in metres, z up (a ``(T, J, 3)`` array is one clip).
        names: the J joint names (unique strings).
        fps: frames per second, a finite number > 0.
        orientations: optional joint frames ``(B, T, J, 3, 3)`` (rotation matrices, world from joint).

    Raises :class:`~diffkin.errors.ShapeError` for wrong shapes or a name count that is not J,
    :class:`~diffkin.errors.NonFiniteError` naming the frames that hold NaN or inf,
    :class:`~diffkin.errors.OptionError` for ``fps <= 0`` and :class:`~diffkin.errors.ModelError` for
    repeated joint names. Tensors keep their dtype and device; numpy arrays and lists are converted.
    """

    def __init__(self, positions, names: Sequence[str], fps, orientations=None):
        p = as_tensor(positions, "positions")
        if p.ndim == 3:
            p = p.unsqueeze(0)
        if p.ndim != 4 or p.shape[-1] != 3 or p.shape[1] < 1:
            raise ShapeError(f"expected positions of shape (B, T, J, 3) or (T, J, 3) with T >= 1, got "
                             f"{shape_str(p.shape)}")
        names = list(names) if not isinstance(names, str) else [names]
        if len(names) != p.shape[2] or not all(isinstance(n, str) for n in names):
            raise ShapeError(f"expected {p.shape[2]} joint names (strings), one per joint of positions "
                             f"{shape_str(p.shape)}, got {len(names)}")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ModelError(f"joint names must be unique, got repeated {dup}")
        self.fps = check_number(fps, "fps", unit=" frames per second")
        _nonfinite_frames(p, "positions")
        R = None
        if orientations is not None:
            R = as_tensor(orientations, "orientations", dtype=p.dtype, device=p.device)
            if R.ndim == 4:  # (T, J, 3, 3): one clip, as positions (T, J, 3)
                R = R.unsqueeze(0)
            if tuple(R.shape) != (*p.shape[:3], 3, 3):
                raise ShapeError(f"expected orientations of shape {shape_str((*p.shape[:3], 3, 3))} "
                                 f"(B, T, J, 3, 3) to match positions, got {shape_str(R.shape)}")
            _nonfinite_frames(R, "orientations")
        self.positions, self.orientations, self.names = p, R, names

    # ------------------------------------------------------------------------------------- sizes
    @property
    def batch(self) -> int:
        """B, the number of clips."""
        return int(self.positions.shape[0])

    @property
    def frames(self) -> int:
        """T, the number of frames."""
        return int(self.positions.shape[1])

    @property
    def duration(self) -> float:
        """The clip length in seconds, (T - 1) / fps."""
        return (self.frames - 1) / self.fps

    def __len__(self) -> int:
        return self.frames

    def __repr__(self) -> str:
        return (f"Motion(B={self.batch}, T={self.frames}, J={len(self.names)}, fps={self.fps:g}, "
                f"orientations={'yes' if self.orientations is not None else 'no'})")

    # ------------------------------------------------------------------------------------ access
    def index(self, names: str | Sequence[str]) -> list[int]:
        """Indices of joint names; :class:`~diffkin.errors.ModelError` names the unknown ones."""
        names = [names] if isinstance(names, str) else list(names)
        unknown = [n for n in names if n not in self.names]
        if unknown:
            raise ModelError(f"unknown joint name(s) {unknown}; this clip's joints are {self.names}")
        return [self.names.index(n) for n in names]

    def joint(self, name: str) -> Tensor:
        """Positions ``(B, T, 3)`` of one joint."""
        return self.positions[:, :, self.index(name)[0]]

    def frames_slice(self, start: int = 0, stop: int | None = None) -> Motion:
        """The frames ``start:stop`` as a new Motion (same fps; the skeleton's ``parents`` kept if known)."""
        R = None if self.orientations is None else self.orientations[:, start:stop]
        out = Motion(self.positions[:, start:stop], self.names, self.fps, R)
        if getattr(self, "parents", None) is not None:
            out.parents = list(self.parents)
        return out
