"""Robot models as data: the YAML / dict schema of :class:`~diffkin.chain.DHChain`, with exact numbers.

Schema (one mapping per robot)::

    name: panda                      # required
    convention: modified             # "standard" (default, the book's (2.52)) or "modified" (Craig)
    joint_types: RRRRRRR             # one letter R/P per row (default all R)
    dh:                              # required, one row per joint
      - {a: 0, alpha: 0, d: 0.333, theta: 0}
      - {a: 0, alpha: -pi/2, d: 0, theta: 0}
    q_limits:                        # optional: [lower, upper] per joint, or {lower: [...], upper: [...]}
      - [-2.8973, 2.8973]
    base: {xyz: [0, 0, 0], rpy: [0, 0, 0]}   # optional fixed transforms: xyz + rpy (URDF order: roll about
    tool: {matrix: [[1, 0, 0, 0], ...]}      # x, pitch about y, yaw about z; R = Rz(yaw) Ry(pitch) Rx(roll)),
                                             # or a 4x4 / 3x4 matrix (also as a bare nested list)
    home: [0, -0.785, 0, -2.356, 0, 1.571, 0.785]   # optional: a comfortable, non-singular start
                                     # configuration (one value per joint, within q_limits)
    planar: false                    # optional: true when every joint moves the arm in the base frame's
                                     # x-y plane (the planar arms of §2.9.1; envs draw and sample in 2-D)
    description: ...                 # optional free text; also source, notes

Every number may be a YAML number or a string expression of numbers and ``pi`` with ``+ - * /`` and
parentheses, optionally followed by ``deg`` (degrees): ``pi/2``, ``-pi/2``, ``0.5*pi``, ``170 deg``. They are
evaluated by a tiny AST walker (no ``eval``) into Python floats, and tensors are built directly in the
requested dtype, so a float64 load is exact (``pi/2`` is ``math.pi / 2``), never a float32 table cast up.
"""

from __future__ import annotations

import ast
import math
import operator
import re
from pathlib import Path

import numpy as np
import torch
import yaml

from ..errors import DTypeError, ModelError
from ..transforms import as_rigid_transform
from ..validation import SUPPORTED_DTYPES

__all__ = [
    "parse_value",
    "rpy_to_matrix",
    "transform_from_spec",
    "parse_chain_dict",
    "read_yaml",
    "chain_to_dict",
    "chain_to_yaml",
]

_TOP_KEYS = {"name", "convention", "joint_types", "dh", "q_limits", "base", "tool", "description", "source",
             "notes", "home", "planar"}
_META_KEYS = ("description", "source", "notes")
_ROW_KEYS = ("a", "alpha", "d", "theta")
_BINOPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv}
_DEG = re.compile(r"^(?P<expr>.*?)\s*(deg|°)$")


# ------------------------------------------------------------------------------------ expressions
def _eval_node(node: ast.AST) -> float:
    if isinstance(node, ast.Constant) and type(node.value) in (int, float):
        return float(node.value)
    if isinstance(node, ast.Name) and node.id == "pi":
        return math.pi
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        v = _eval_node(node.operand)
        return -v if isinstance(node.op, ast.USub) else v
    if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
        return _BINOPS[type(node.op)](_eval_node(node.left), _eval_node(node.right))
    raise ValueError(f"unsupported element {ast.dump(node)[:40]}")


def parse_value(value, where: str = "value") -> float:
    """A YAML number or expression (numbers, ``pi``, ``+ - * /``, parentheses, optional ``deg``) -> float."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ModelError(f"{where}: expected a number or an expression like 'pi/2', got {value!r}")
    if isinstance(value, str):
        text = value.strip()
        m = _DEG.match(text)
        expr = m.group("expr") if m else text
        try:
            out = _eval_node(ast.parse(expr, mode="eval").body)
        except (SyntaxError, ValueError, ZeroDivisionError, RecursionError) as e:
            raise ModelError(
                f"{where}: cannot parse {value!r} (numbers, pi, + - * / and a 'deg' suffix only): {e}"
            ) from None
        if m:
            out = math.radians(out)
    else:
        out = float(value)
    if not math.isfinite(out):
        raise ModelError(f"{where}: {value!r} is not finite")
    return out


def _parse_list(value, length: int, where: str) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != length:
        raise ModelError(f"{where}: expected a list of {length} numbers, got {value!r}")
    return [parse_value(v, f"{where}[{i}]") for i, v in enumerate(value)]


# ------------------------------------------------------------------------------------ transforms
def _snap(v: float) -> float:
    return 0.0 if abs(v) < 1e-15 else v


def rpy_to_matrix(rpy) -> list[list[float]]:
    """URDF roll-pitch-yaw -> rotation ``Rz(yaw) Ry(pitch) Rx(roll)`` as nested Python floats (float64).

    Entries below 1e-15 in magnitude (e.g. cos(pi/2) = 6e-17) are set to exactly 0.
    """
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = (_snap(f(t)) for t in (r, p, y) for f in (math.cos, math.sin))
    R = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    return [[_snap(v) for v in row] for row in R]


def _xyz_rpy_matrix(xyz, rpy) -> list[list[float]]:
    R = rpy_to_matrix(rpy)
    return [R[0] + [xyz[0]], R[1] + [xyz[1]], R[2] + [xyz[2]], [0.0, 0.0, 0.0, 1.0]]


def transform_from_spec(spec, where: str) -> list[list[float]]:
    """A YAML transform (matrix, or mapping with ``matrix`` or ``xyz``/``rpy``) -> 4x4 nested floats."""
    if isinstance(spec, dict):
        unknown = set(spec) - {"xyz", "rpy", "matrix"}
        if unknown:
            raise ModelError(f"{where}: unknown keys {sorted(unknown)} (expected xyz, rpy or matrix)")
        if "matrix" in spec:
            if len(spec) > 1:
                raise ModelError(f"{where}: give either 'matrix' or 'xyz'/'rpy', not both")
            return transform_from_spec(spec["matrix"], f"{where}.matrix")
        xyz = _parse_list(spec.get("xyz", [0, 0, 0]), 3, f"{where}.xyz")
        rpy = _parse_list(spec.get("rpy", [0, 0, 0]), 3, f"{where}.rpy")
        return _xyz_rpy_matrix(xyz, rpy)
    if isinstance(spec, (list, tuple)) and len(spec) in (3, 4):
        rows = [_parse_list(row, 4, f"{where}[{i}]") for i, row in enumerate(spec)]
        return rows if len(rows) == 4 else rows + [[0.0, 0.0, 0.0, 1.0]]
    raise ModelError(f"{where}: expected a 4x4 (or 3x4) matrix or a mapping with xyz/rpy, got {spec!r}")


# -------------------------------------------------------------------------------------- dict -> chain
def _parse_rows(rows, where: str) -> dict[str, list[float]]:
    """Columns a, alpha, d, theta (and beta, Hayati's, when every row has it) of the ``dh`` rows."""
    if not isinstance(rows, list) or not rows:
        raise ModelError(f"{where}dh: expected a non-empty list of rows {{a, alpha, d, theta}}, got {rows!r}")
    with_beta = isinstance(rows[0], dict) and "beta" in rows[0]
    keys = (*_ROW_KEYS, "beta") if with_beta else _ROW_KEYS
    cols: dict[str, list[float]] = {k: [] for k in keys}
    for i, row in enumerate(rows):
        w = f"{where}dh[{i}]"
        if not isinstance(row, dict):
            raise ModelError(f"{w}: expected a mapping with keys a, alpha, d, theta, got {row!r}")
        unknown, missing = set(row) - set(keys), [k for k in keys if k not in row]
        if unknown or missing:
            raise ModelError(
                f"{w}: keys must be {', '.join(keys)} (beta in every row or none; "
                f"unknown {sorted(unknown)}, missing {missing})"
            )
        for k in keys:
            cols[k].append(parse_value(row[k], f"{w}.{k}"))
    return cols


def _parse_limits(lim, n: int, where: str) -> list[list[float]] | None:
    if lim is None:
        return None
    if isinstance(lim, dict):
        if set(lim) != {"lower", "upper"}:
            raise ModelError(f"{where}q_limits: a mapping needs exactly the keys lower and upper")
        lo = _parse_list(lim["lower"], n, f"{where}q_limits.lower")
        hi = _parse_list(lim["upper"], n, f"{where}q_limits.upper")
        pairs = [list(p) for p in zip(lo, hi)]
    else:
        if not isinstance(lim, list) or len(lim) != n:
            raise ModelError(f"{where}q_limits: expected {n} pairs [lower, upper], got {lim!r}")
        pairs = [_parse_list(p, 2, f"{where}q_limits[{i}]") for i, p in enumerate(lim)]
    for i, (lo, hi) in enumerate(pairs):
        if not lo < hi:
            raise ModelError(f"{where}q_limits[{i}]: lower {lo} must be < upper {hi}")
    return pairs


def _parse_home_planar(data: dict, n: int, limits, where: str) -> dict:
    """The model data ``home`` (n floats within the limits, or None) and ``planar`` (a bool)."""
    home = data.get("home")
    if home is not None:
        home = _parse_list(home, n, f"{where}home")
        for i, (v, (lo, hi)) in enumerate(zip(home, limits or [(-math.inf, math.inf)] * n)):
            if not lo <= v <= hi:
                raise ModelError(f"{where}home[{i}]: {v} is outside q_limits [{lo}, {hi}]")
    planar = data.get("planar", False)
    if not isinstance(planar, bool):
        raise ModelError(f"{where}planar: expected true or false, got {planar!r}")
    return {"home": home, "planar": planar}


def parse_chain_dict(data: dict, dtype: torch.dtype | None = None, device=None, where: str = "") -> dict:
    """The keyword arguments of :class:`~diffkin.chain.DHChain` (plus ``metadata`` and the model data
    ``home`` / ``planar``, which the chain carries as attributes) from a model mapping;
    errors name the field (``where`` prefixes them). :meth:`DHChain.from_dict` builds the chain."""
    pre = f"{where}: " if where else ""
    if not isinstance(data, dict):
        raise ModelError(f"{pre}expected a mapping at the top level, got {type(data).__name__}")
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise ModelError(f"{pre}unknown keys {sorted(unknown)}; allowed: {sorted(_TOP_KEYS)}")
    name = data.get("name")
    if not isinstance(name, str) or not name:
        raise ModelError(f"{pre}name: expected a non-empty string, got {name!r}")
    cols = _parse_rows(data.get("dh"), pre)
    n = len(cols["a"])
    joint_types = data.get("joint_types", "R" * n)
    if not isinstance(joint_types, str) or len(joint_types) != n or set(joint_types.upper()) - {"R", "P"}:
        raise ModelError(f"{pre}joint_types: expected {n} letters R/P (one per dh row), got {joint_types!r}")
    convention = data.get("convention", "standard")
    if convention not in ("standard", "modified"):
        raise ModelError(f"{pre}convention: expected 'standard' or 'modified', got {convention!r}")
    limits = _parse_limits(data.get("q_limits"), n, pre)
    dtype = _model_dtype(dtype)
    fixed = {}
    for key in ("base", "tool"):
        if data.get(key) is None:
            fixed[key] = None
            continue
        M = transform_from_spec(data[key], f"{pre}{key}")
        try:
            fixed[key] = as_rigid_transform(M, key, dtype, device)
        except ModelError as e:
            raise ModelError(f"{pre}{e}") from None
    return dict(
        **{k: torch.tensor(cols[k], dtype=dtype, device=device) for k in _ROW_KEYS},
        beta=torch.tensor(cols["beta"], dtype=dtype, device=device) if "beta" in cols else None,
        joint_types=joint_types.upper(),
        convention=convention,
        base=fixed["base"],
        tool=fixed["tool"],
        q_limits=None if limits is None else torch.tensor(limits, dtype=dtype, device=device),
        name=name,
        dtype=dtype,
        metadata={k: str(data[k]) for k in _META_KEYS if data.get(k) is not None},
        **_parse_home_planar(data, n, limits, pre),
    )


def _model_dtype(dtype) -> torch.dtype:
    """A model's dtype: float32 or float64 (default: torch's); anything else raises DTypeError (an integer
    dtype would truncate the DH table)."""
    dtype = dtype or torch.get_default_dtype()
    if dtype not in SUPPORTED_DTYPES:
        raise DTypeError(f"a model's dtype must be torch.float32 or torch.float64, got {dtype}")
    return dtype


# -------------------------------------------------------------------------------------- chain -> dict
_PI_DENOMS = (1, 2, 3, 4, 6, 12)


def _nice(v: float, dtype: torch.dtype):
    """A float as a plain number or an exact ``k*pi/m`` expression (exact in ``dtype``)."""
    if dtype == torch.float32:
        v = float(str(np.float32(v)))  # shortest decimal that round-trips in float32

        def same(w: float) -> bool:
            return np.float32(w) == np.float32(v)
    else:

        def same(w: float) -> bool:
            return w == v

    if v != 0.0:
        for m in _PI_DENOMS:
            k = round(v * m / math.pi)
            if k == 0 or abs(k) > 4 * m or math.gcd(k, m) != 1:
                continue
            num = "pi" if abs(k) == 1 else f"{abs(k)}*pi"
            text = ("-" if k < 0 else "") + (num if m == 1 else f"{num}/{m}")
            if same(parse_value(text)):
                return text
        deg = round(math.degrees(v))
        if abs(deg) <= 720 and same(math.radians(deg)):
            return f"{deg} deg"
    return int(v) if v == int(v) and abs(v) < 1e15 else v


class _Flow(list):
    """A list dumped in YAML flow style."""


class _FlowMap(dict):
    """A mapping dumped in YAML flow style."""


class _Dumper(yaml.SafeDumper):
    pass


_Dumper.add_representer(_Flow, lambda dumper, v: dumper.represent_sequence(
    "tag:yaml.org,2002:seq", v, flow_style=True))
_Dumper.add_representer(_FlowMap, lambda dumper, v: dumper.represent_mapping(
    "tag:yaml.org,2002:map", v, flow_style=True))


def chain_to_dict(chain) -> dict:
    """The model mapping of ``chain`` (round-trips through :func:`chain_from_dict` exactly)."""
    dt = chain.dtype
    table = chain.dh_table().cpu().tolist()
    out: dict = {"name": chain.name, "convention": chain.convention, "joint_types": chain.joint_types}
    out.update(getattr(chain, "metadata", {}))
    keys = _ROW_KEYS
    if getattr(chain, "beta", None) is not None:
        keys = (*_ROW_KEYS, "beta")
        table = [row + [b] for row, b in zip(table, chain.beta.detach().cpu().tolist())]
    out["dh"] = [_FlowMap({k: _nice(v, dt) for k, v in zip(keys, row)}) for row in table]
    if chain.q_limits is not None:
        out["q_limits"] = [_Flow(_nice(v, dt) for v in pair) for pair in chain.q_limits.cpu().tolist()]
    for key in ("base", "tool"):
        T = getattr(chain, key)
        if T is not None:
            rows = T.detach().cpu().tolist()
            out[key] = {"matrix": [_Flow(_nice(v, dt) for v in row) for row in rows]}
    if getattr(chain, "home", None) is not None:
        out["home"] = _Flow(_nice(v, dt) for v in chain.home)
    if getattr(chain, "planar", False):
        out["planar"] = True
    return out


def chain_to_yaml(chain, path=None) -> str:
    text = yaml.dump(chain_to_dict(chain), Dumper=_Dumper, sort_keys=False, allow_unicode=True, width=110)
    if path is not None:
        Path(path).write_text(text)
    return text


def _looks_like_path(x) -> bool:
    if isinstance(x, Path):
        return True
    return isinstance(x, str) and "\n" not in x and (x.endswith((".yaml", ".yml")) or Path(x).is_file())


def read_yaml(path_or_str) -> tuple[object, str]:
    """``(data, where)`` of a YAML file (path) or YAML text; ``where`` (the file name) prefixes errors."""
    if _looks_like_path(path_or_str):
        path = Path(path_or_str)
        if not path.is_file():
            raise ModelError(f"model file {str(path)!r} not found")
        where = path.name
        try:
            text = path.read_bytes().decode("utf-8")
        except UnicodeDecodeError as e:
            raise ModelError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start}); expected a UTF-8 YAML "
                             "model file") from None
    else:
        text, where = str(path_or_str), "<yaml>"
    try:
        return yaml.safe_load(text), where
    except yaml.YAMLError as e:
        raise ModelError(f"{where}: invalid YAML: {e}") from None
