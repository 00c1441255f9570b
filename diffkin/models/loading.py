"""The one model loader: a chain from a name, a robot YAML, a URDF or an MJCF file, or a chain.

The CLI (``diffkin fk / ik / calibrate``), :func:`diffkin.calibration.calibrate_from_files` and the envs all
load robots here.
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..chain import KinematicChain
from ..chain.kinematic import _check_learnable
from ..errors import ModelError
from ..validation import check_device

__all__ = ["load_chain"]


def load_chain(source, end_link=None, *, dtype: torch.dtype | None = None, device=None,
               learnable: bool = False, file_format: str | None = None) -> KinematicChain:
    """A kinematic chain in ``dtype`` on ``device`` (None: the source's own, or torch's default) from:

    * a :class:`~diffkin.chain.KinematicChain`: a copy (converted when dtype / device are given);
    * a path ending in ``.urdf``: :func:`~diffkin.models.from_urdf` (``end_link``: a link or a list);
    * a path ending in ``.xml`` / ``.mjcf``: :func:`~diffkin.models.from_mjcf` (``end_link``: bodies or
      sites);
    * a built-in robot name or a DH robot YAML file: :func:`~diffkin.models.load` (``end_link``: a URDF /
      MuJoCo robot's end links instead of its default ones; None for a DH model).

    The geometry is frozen unless ``learnable=True`` (a chain given keeps its own setting, and
    ``learnable=True`` turns it on in the copy).
    ``file_format`` (``"urdf"`` or ``"mjcf"``) names the reader for a file whatever its suffix (the CLI's
    ``--urdf`` / ``--mjcf``: ``robot.urdf.xml`` is a URDF when the user says so); None: by the suffix.

    Errors are :class:`~diffkin.errors.ModelError` naming the source (an unknown name lists the built-in
    ones); a device this torch cannot compute on raises :class:`~diffkin.errors.DeviceError`.
    """
    device = check_device(device)
    _check_learnable(learnable)
    if isinstance(source, KinematicChain):
        chain = source.copy().requires_grad_(True) if learnable else source.copy()
        return chain if dtype is None and device is None else chain.to(dtype=dtype, device=device)
    if not isinstance(source, str | Path):
        raise ModelError(f"expected a robot as a model name, a YAML / URDF / MJCF path or a chain, got "
                         f"{type(source).__name__}")
    from .. import models

    readers = {"urdf": "from_urdf", "mjcf": "from_mjcf"}
    if file_format is not None and file_format not in readers:
        raise ModelError(f"file_format: expected 'urdf', 'mjcf' or None (by the suffix), got {file_format!r}")
    builder = readers[file_format] if file_format else \
        models.OTHER_FORMATS.get(Path(source).suffix.lower())  # from_urdf / from_mjcf by suffix
    if builder is not None:
        if not end_link:
            raise ModelError(f"{source}: a URDF or MJCF robot needs its end link (end_link=, --end-link)")
        return getattr(models, builder)(source, end_link, dtype=dtype, device=device, learnable=learnable)
    # a built-in name: a DH model (end_link refused: it ends where its table ends) or a shipped URDF / MuJoCo
    # robot (end_link: instead of its default end links)
    return models.load(source, dtype=dtype, device=device, learnable=learnable, end_link=end_link or None)
