"""Robot models (§2.9): the textbook's structures and real arms as YAML data, URDF import, workspace.

``load(name)`` builds a :class:`~diffkin.chain.DHChain` from ``diffkin/models/data/<name>.yaml`` (schema in
:mod:`diffkin.models.io`); ``available()`` lists the names; ``from_urdf(source, end_link)`` builds a
:class:`URDFChain`; ``sample_workspace(chain, n)`` samples reachable end-effector positions (§2.10.1).
"""

from __future__ import annotations

import functools
from pathlib import Path

import torch

from ..chain import DHChain
from ..errors import ModelError
from ..validation import check_device
from .io import chain_to_dict, parse_value, read_yaml
from .loading import load_chain
from .mjcf import MJCFChain, from_mjcf
from .urdf import URDFChain, from_urdf
from .workspace import sample_workspace

__all__ = [
    "load",
    "load_chain",
    "available",
    "source",
    "model_path",
    "from_urdf",
    "from_mjcf",
    "MJCFChain",
    "URDFChain",
    "sample_workspace",
    "parse_value",
    "chain_from_dict",
    "chain_to_dict",
    "DATA_DIR",
]

def chain_from_dict(data: dict, dtype: torch.dtype | None = None, device=None, where: str = "", *,
                    learnable: bool = False) -> DHChain:
    """Build a :class:`DHChain` from a model mapping; errors name the field (``where`` prefixes them)."""
    return DHChain.from_dict(data, dtype=dtype, device=check_device(device), where=where, learnable=learnable)


def chain_from_yaml(path_or_str, dtype: torch.dtype | None = None, device=None, *,
                    learnable: bool = False) -> DHChain:
    """Chain from a YAML file (path) or YAML text; errors are prefixed by the file name."""
    return DHChain.from_yaml(path_or_str, dtype=dtype, device=check_device(device), learnable=learnable)


DATA_DIR = Path(__file__).resolve().parent / "data"


def available() -> list[str]:
    """Names of the bundled models (sorted)."""
    return sorted(p.stem for p in DATA_DIR.glob("*.yaml"))


def model_path(name: str) -> Path:
    """Path of a bundled model's YAML file (ModelError listing the names if unknown)."""
    path = DATA_DIR / f"{name}.yaml"
    if not isinstance(name, str) or not path.is_file():
        raise ModelError(f"unknown model {name!r}; available: {', '.join(available())}")
    return path


@functools.cache
def _model_data(name: str) -> dict:
    return read_yaml(model_path(name))[0]


def load(name_or_path, dtype: torch.dtype | None = None, device=None, *, learnable: bool = False) -> DHChain:
    """A model by name (see :func:`available`) or from a YAML file path, in ``dtype`` on ``device``.

    The geometry (DH table, base and tool corrections) is frozen unless ``learnable=True`` (or
    ``chain.requires_grad_()`` later): results then carry no autograd graph unless ``q`` asks for one.

    The numbers are parsed as Python floats and the tensors built directly in ``dtype`` (default: torch's
    default dtype), so ``load(name, dtype=torch.float64)`` is exact to float64. A device this torch cannot
    compute on (``"cuda"`` without CUDA, ``"meta"``) raises :class:`~diffkin.errors.DeviceError`.
    """
    check_device(device)
    _refuse_other_formats(name_or_path)
    if isinstance(name_or_path, Path) or (
        isinstance(name_or_path, str) and (name_or_path.endswith((".yaml", ".yml")) or "/" in name_or_path)
    ):
        return chain_from_yaml(Path(name_or_path), dtype=dtype, device=device, learnable=learnable)
    data = _model_data(name_or_path)
    return chain_from_dict(data, dtype=dtype, device=device, where=f"{name_or_path}.yaml",
                           learnable=learnable)


#: file suffixes that :func:`load` does not read, and the loader that does
OTHER_FORMATS = {".urdf": "from_urdf", ".xml": "from_mjcf", ".mjcf": "from_mjcf"}


def _refuse_other_formats(name_or_path) -> None:
    """A URDF or MuJoCo XML file given to :func:`load` (which reads built-in names and robot YAML): the error
    names the loader for it, before any YAML parser sees the file."""
    if not isinstance(name_or_path, (str, Path)):
        return
    suffix = Path(name_or_path).suffix.lower()
    if suffix == ".urdf":
        raise ModelError(f"{name_or_path}: a URDF file; load it with diffkin.models.from_urdf(path, "
                         "end_link) (models.load reads built-in names and robot YAML files)")
    if suffix in OTHER_FORMATS:
        raise ModelError(f"{name_or_path}: an XML model; load a MuJoCo MJCF with diffkin.models."
                         "from_mjcf(path, ...) or a URDF with diffkin.models.from_urdf(path, end_link) "
                         "(models.load reads built-in names and robot YAML files)")


def source(name: str) -> str:
    """Where a bundled model's numbers come from (its YAML ``source`` field)."""
    return str(_model_data(name).get("source", ""))
