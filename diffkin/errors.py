"""Typed errors: each says what was expected and what was received.

Every error is a ``ValueError`` (or ``TypeError``) subclass so plain ``except ValueError`` still works.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = [
    "DiffkinError",
    "ShapeError",
    "ConventionError",
    "NonFiniteError",
    "DTypeError",
    "ModelError",
    "RepresentationSingularityError",
    "MissingExtraError",
    "OptionError",
    "NonFiniteOptionError",
    "DeviceError",
    "SamplingError",
    "require",
]


class DiffkinError(ValueError):
    """Base class of diffkin's input errors."""


class ShapeError(DiffkinError):
    """A tensor has the wrong shape; the message names the expected and the received shape."""


class ConventionError(DiffkinError):
    """An unknown convention, representation or option name."""


class NonFiniteError(DiffkinError):
    """Input holds NaN or inf where finite numbers are required."""


class DTypeError(DiffkinError, TypeError):
    """Tensors of mixed or unsupported dtype."""


class ModelError(DiffkinError):
    """A robot model (DH table, YAML or URDF) or a scene (world file, MoveIt PlanningScene, obstacle geometry:
    a negative radius, a zero-length cylinder) is malformed or unknown."""


class RepresentationSingularityError(DiffkinError):
    """A minimal orientation representation is singular at the requested configuration."""


class MissingExtraError(DiffkinError, ImportError):
    """An optional dependency is not installed; the message names the extra that installs it."""


class OptionError(DiffkinError):
    """An option or setting out of its range (a count, a tolerance, a damping, a config value)."""


class NonFiniteOptionError(NonFiniteError, OptionError):
    """A numeric option given as NaN or inf: both a :class:`NonFiniteError` (the rule for every NaN) and an
    :class:`OptionError` (the one type of every numeric option's mistake)."""


class DeviceError(DiffkinError):
    """A device this torch cannot compute on: ``"cuda"`` on a CPU-only build, a missing GPU index, ``"meta"``
    (tensors without values) or an unknown device string."""


class SamplingError(DiffkinError):
    """Rejection sampling found fewer accepted samples than asked for within its bounded number of rounds
    (collision-free configurations of a robot that is almost always in collision)."""


def require(module: str, extra: str, feature: str) -> ModuleType:
    """Import ``module`` for ``feature``, or raise :class:`MissingExtraError` naming the extra to install."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(
            f"{feature} needs {module.split('.')[0]}, which is not installed: pip install 'diffkin[{extra}]'"
        ) from exc
