"""Robots by name: the URDF and MuJoCo (MJCF) robots that ship inside the package, and any
``robot_descriptions`` name when that package is installed.

``robots/catalog.json`` lists each shipped robot once: its name (the MuJoCo Menagerie directory name, or the
URDF's file name) and short aliases, its format and file under ``robots/``, the end links
:func:`~diffkin.models.load` gives it by default, and where it comes from with its licence (as recorded in
``robots/mjcf/README.md`` and ``robots/urdf/README.md``). The DH models of ``models/data/*.yaml`` are the
third kind of built-in name; :func:`entries` lists all of them.
"""

from __future__ import annotations

import functools
import importlib
import json
from dataclasses import dataclass
from pathlib import Path

from ..errors import ModelError

ROBOTS_DIR = Path(__file__).resolve().parent / "robots"


@dataclass(frozen=True)
class RobotInfo:
    """One robot loadable by name. ``format``: ``"dh"`` (a YAML table of :mod:`diffkin.models.data`),
    ``"urdf"`` or ``"mjcf"``; ``path``: its file; ``end_links``: the default end links (URDF / MJCF; None for
    a DH table, which ends where its table ends); ``floating_base``: a URDF read with a free root joint (an
    MJCF file declares its own free joints); ``wheel``: whether the installed package carries the file (only
    files whose licence permits it ship, with their licence text beside them; the others load by name from a
    source checkout)."""

    name: str
    format: str
    path: Path
    end_links: tuple[str, ...] | None
    source: str
    licence: str
    category: str = ""
    aliases: tuple[str, ...] = ()
    floating_base: bool = False
    wheel: bool = True


@functools.cache
def _shipped() -> dict[str, RobotInfo]:
    """Name and alias -> :class:`RobotInfo` of ``robots/catalog.json``."""
    out: dict[str, RobotInfo] = {}
    for row in json.loads((ROBOTS_DIR / "catalog.json").read_text())["robots"]:
        info = RobotInfo(name=row["name"], format=row["format"], path=(ROBOTS_DIR / row["file"]).resolve(),
                         end_links=tuple(row["end_links"]), source=row["source"], licence=row["licence"],
                         category=row.get("category", ""), aliases=tuple(row.get("aliases", ())),
                         floating_base=bool(row.get("floating_base", False)),
                         wheel=bool(row.get("wheel", True)))
        for key in (info.name, *info.aliases):
            if key in out:
                raise ModelError(f"robots/catalog.json: the name {key!r} is given twice")
            out[key] = info
    return out


def shipped(name: str) -> RobotInfo | None:
    """The shipped URDF / MJCF robot called ``name`` (a name or an alias), or None."""
    return _shipped().get(name)


def shipped_names() -> list[str]:
    """Every shipped URDF / MJCF robot's name whose file is here (aliases not repeated): in an installed
    package the robots of the wheel, in a source checkout all of them."""
    return sorted({info.name for info in _shipped().values() if info.path.is_file()})


def robot_description(name: str) -> RobotInfo | None:
    """A ``robot_descriptions`` module's robot (``"ur10e_mj_description"``, ``"panda_description"``) when that
    package is installed and ``name`` is one of its descriptions, else None. Importing the module makes
    ``robot_descriptions`` fetch the description into its cache once (``ROBOT_DESCRIPTIONS_CACHE``); its
    ``MJCF_PATH`` is preferred to its ``URDF_PATH``. End links are not known for these: ``load`` needs
    ``end_link=``."""
    if not name.endswith("_description") or not name.replace("_", "").isalnum():
        return None
    try:
        listing = importlib.import_module("robot_descriptions._descriptions")
    except ImportError:
        return None
    if name not in getattr(listing, "DESCRIPTIONS", {}):
        return None
    try:
        module = importlib.import_module(f"robot_descriptions.{name}")
    except Exception as exc:  # a clone that cannot reach its repository, a git error: named, not hidden
        raise ModelError(f"robot_descriptions could not provide {name!r}: {type(exc).__name__}: "
                         f"{exc}") from exc
    for attr, fmt in (("MJCF_PATH", "mjcf"), ("URDF_PATH", "urdf")):
        path = getattr(module, attr, None)
        if path:
            return RobotInfo(name=name, format=fmt, path=Path(path), end_links=None,
                             source=f"robot_descriptions.{name} ({path})",
                             licence="see the description's repository")
    raise ModelError(f"robot_descriptions.{name} has neither an MJCF_PATH nor a URDF_PATH")
