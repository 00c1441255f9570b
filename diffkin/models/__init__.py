"""Robot models (§2.9): the textbook's structures and real arms as YAML data, URDF import, workspace.

``load(name)`` builds a robot by name: a :class:`~diffkin.chain.DHChain` from
``diffkin/models/data/<name>.yaml`` (schema in :mod:`diffkin.models.io`), or a shipped URDF / MuJoCo robot of
``diffkin/models/robots/`` (the MuJoCo Menagerie robots and URDFs of :mod:`diffkin.models.catalog`), or a
``robot_descriptions`` name when that package is installed; ``available()`` lists the names
(``details=True``: with format, source and licence); ``from_urdf(source, end_link)`` / ``from_mjcf`` read any
file; ``sample_workspace(chain, n)`` samples reachable end-effector positions (§2.10.1).
"""

from __future__ import annotations

import functools
from pathlib import Path

import torch

from ..chain import DHChain
from ..errors import ModelError
from ..validation import check_device
from . import catalog
from .catalog import RobotInfo
from .io import chain_to_dict, parse_value, read_yaml
from .loading import load_chain
from .mjcf import MJCFChain, from_mjcf
from .urdf import URDFChain, from_urdf
from .workspace import sample_workspace

__all__ = [
    "load",
    "load_chain",
    "available",
    "info",
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
    "RobotInfo",
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


def _dh_names() -> list[str]:
    return sorted(p.stem for p in DATA_DIR.glob("*.yaml"))


def available(*, details: bool = False) -> list[str] | list[RobotInfo]:
    """Names of the built-in robots (sorted): the DH models, then nothing else twice -- the shipped URDF and
    MuJoCo robots by their names (aliases such as ``"g1"`` load too but are not listed). ``details=True``:
    a :class:`RobotInfo` per robot (format, file, default end links, source, licence)."""
    names = sorted({*_dh_names(), *catalog.shipped_names()})
    return [info(name) for name in names] if details else names


def info(name: str) -> RobotInfo:
    """What :func:`load` reads for ``name``: format, file, default end links, source and licence."""
    robot = _named(name)
    if robot is not None:
        return robot
    data = _model_data(name)
    return RobotInfo(name=name, format="dh", path=model_path(name), end_links=None,
                     source=" ".join(str(data.get("source", "")).split()),
                     licence="DH parameters from the cited source (no file licence)")


def _named(name: str) -> RobotInfo | None:
    """A shipped URDF / MJCF robot or a robot_descriptions one (None: a DH name or unknown)."""
    if (DATA_DIR / f"{name}.yaml").is_file():
        return None
    return catalog.shipped(name) or catalog.robot_description(name)


def model_path(name: str) -> Path:
    """Path of a built-in robot's file (its DH YAML, URDF or MJCF; ModelError listing the names if
    unknown)."""
    if not isinstance(name, str):
        raise ModelError(f"unknown model {name!r:.60}: expected a model name (str, see "
                         f"models.available()), got {type(name).__name__}")
    if (path := DATA_DIR / f"{name}.yaml").is_file():
        return path
    robot = catalog.shipped(name) or catalog.robot_description(name)
    if robot is None:
        raise ModelError(f"unknown model {name!r}; available: {', '.join(available())} (or a "
                         "robot_descriptions name such as 'ur10e_mj_description' with that package "
                         "installed)")
    return robot.path


@functools.cache
def _model_data(name: str) -> dict:
    return read_yaml(model_path(name))[0]


def load(name_or_path, dtype: torch.dtype | None = None, device=None, *, learnable: bool = False,
         end_link: str | list[str] | None = None):
    """A robot by name (see :func:`available`) or from a DH YAML file path, in ``dtype`` on ``device``.

    A DH name or YAML file gives a :class:`~diffkin.chain.DHChain`. A shipped URDF or MuJoCo robot
    (``"g1"``, ``"ur10e"``, ``"yumi"``, ...) gives a :class:`URDFChain` / :class:`MJCFChain` to its default
    end links (:func:`info`), or to ``end_link`` (a link / body / site name or a list of them) when given; a
    ``robot_descriptions`` name (``"ur10e_mj_description"``, with that package installed) needs ``end_link``.

    The geometry (DH table, base and tool corrections) is frozen unless ``learnable=True`` (or
    ``chain.requires_grad_()`` later): results then carry no autograd graph unless ``q`` asks for one.

    The numbers are parsed as Python floats and the tensors built directly in ``dtype`` (default: torch's
    default dtype), so ``load(name, dtype=torch.float64)`` is exact to float64. A device this torch cannot
    compute on (``"cuda"`` without CUDA, ``"meta"``) raises :class:`~diffkin.errors.DeviceError`.
    """
    check_device(device)
    if not isinstance(name_or_path, str | Path):  # a list of names, a chain, None ...: one model per call
        raise ModelError(f"expected a model name (str, see models.available()) or a robot YAML path, got "
                         f"{type(name_or_path).__name__} {name_or_path!r:.60}")
    _refuse_other_formats(name_or_path)
    named = _named(name_or_path) if isinstance(name_or_path, str) and "/" not in name_or_path and \
        not name_or_path.endswith((".yaml", ".yml")) else None
    if named is not None:
        return _load_named(named, end_link, dtype=dtype, device=device, learnable=learnable)
    if end_link is not None:
        if isinstance(name_or_path, str) and "/" not in name_or_path and \
                not name_or_path.endswith((".yaml", ".yml")):
            model_path(name_or_path)  # an unknown name is told first
        raise ModelError(f"{name_or_path}: end_link={end_link!r} applies to URDF and MuJoCo robots (a DH "
                         "model ends where its table ends)")
    if isinstance(name_or_path, Path) or (
        isinstance(name_or_path, str) and (name_or_path.endswith((".yaml", ".yml")) or "/" in name_or_path)
    ):
        return chain_from_yaml(Path(name_or_path), dtype=dtype, device=device, learnable=learnable)
    data = _model_data(name_or_path)
    return chain_from_dict(data, dtype=dtype, device=device, where=f"{name_or_path}.yaml",
                           learnable=learnable)


def _load_named(robot: RobotInfo, end_link, *, dtype, device, learnable):
    if not robot.path.is_file():  # a catalogue robot the wheel does not carry (its licence)
        raise ModelError(f"{robot.name}: its {robot.format.upper()} file is not in the installed package "
                         f"(licence: {robot.licence}); it loads by name from a source checkout of diffkin, "
                         "or through robot_descriptions")
    # one default end link is given as a name, so that FK is (..., 4, 4) as for a DH model; several: a list
    ends = end_link if end_link is not None else None if not robot.end_links else \
        robot.end_links[0] if len(robot.end_links) == 1 else list(robot.end_links)
    if not ends:
        raise ModelError(f"{robot.name}: give end_link= (a {robot.format.upper()} robot from "
                         "robot_descriptions has no default end links)")
    if robot.format == "mjcf":
        return from_mjcf(robot.path, ends, dtype=dtype, device=device, learnable=learnable)
    return from_urdf(robot.path, ends, dtype=dtype, device=device, learnable=learnable,
                     floating_base=robot.floating_base)


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
    """Where a built-in robot comes from (a DH model's YAML ``source`` field; a URDF / MuJoCo robot's
    origin)."""
    robot = _named(name) if isinstance(name, str) else None
    return robot.source if robot is not None else str(_model_data(name).get("source", ""))
