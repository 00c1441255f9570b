"""Layering rules, checked statically: no import cycles among the project's packages, no library code that
sets process-wide state (torch's thread count, matplotlib's backend) and no subprocesses in the library."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("diffkin", "envs", "training", "benchmarks")
# the project's shared import-cycle tool, vendored unchanged (tests/data/tools/README.md): a clone has it
CYCLES_TOOL = ROOT / "tests" / "data" / "tools" / "import_cycles.py"


def _cycles() -> list[list[str]]:
    proc = subprocess.run(
        [sys.executable, str(CYCLES_TOOL), str(ROOT), *PACKAGES], capture_output=True, text=True
    )
    lines = proc.stdout.splitlines()
    assert lines and re.fullmatch(r"\d+ import cycles", lines[-1]), proc.stdout + proc.stderr
    cycles = [ln.removeprefix("cycle: ").split(" <-> ") for ln in lines if ln.startswith("cycle: ")]
    assert len(cycles) == int(lines[-1].split()[0])
    return cycles


def test_no_import_cycles():
    assert _cycles() == []


def _modules(*packages: str):
    for pkg in packages:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            yield path.relative_to(ROOT).as_posix(), ast.parse(path.read_text(), str(path))


# The lower layers (ARCHITECTURE.md, "Nothing imports upward"), bottom first: a module of one of these layers
# imports diffkin modules of lower layers and of its own layer only; every module not listed here sits above
# them all (models, chain, ik, collision, apps, ...), and so do envs, training, benchmarks and configs.
LAYERS = (
    ("diffkin.errors",),
    ("diffkin._numerics", "diffkin.validation"),
    ("diffkin.kernels",),
    ("diffkin.rotations", "diffkin.transforms"),
)
# Arrows allowed to run back up: none (the raw rotation and transform encodings live in kernels/rigid.py;
# diffkin.rotations and diffkin.transforms are their checked forms, above the kernels).
KNOWN_UPWARD: set[tuple[str, str]] = set()


def _layer(module: str) -> int:
    """Index of ``module``'s layer in ``LAYERS``; ``len(LAYERS)`` for everything above them."""
    for rank, members in enumerate(LAYERS):
        if any(module == m or module.startswith(m + ".") for m in members):
            return rank
    return len(LAYERS)


def _unit(module: str) -> str:
    """The layer member ``module`` belongs to (``diffkin.kernels.tree`` -> ``diffkin.kernels``)."""
    return next((m for ms in LAYERS for m in ms if module == m or module.startswith(m + ".")), module)


def _imported(rel: str, tree: ast.AST):
    """(imported module, line) for every import in ``tree`` (function-local ones included), relative imports
    resolved against ``rel``'s package; ``from a import b`` yields ``a`` and ``a.b`` (b may be a module)."""
    parts = rel.removesuffix(".py").split("/")
    package = parts[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from ((a.name, node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                above = package[: len(package) - node.level + 1]
                base = ".".join(above + ([node.module] if node.module else []))
            yield base, node.lineno
            yield from ((f"{base}.{a.name}", node.lineno) for a in node.names)
        elif isinstance(node, ast.Call) and _dotted(node.func) in _DYNAMIC_IMPORTS:
            yield from ((a.value, node.lineno) for a in node.args[:1]
                        if isinstance(a, ast.Constant) and isinstance(a.value, str))


def _upward_imports(modules) -> list[str]:
    """'file:line source -> target' for every import from a lower layer to a layer above it (the package
    root, envs, training, benchmarks and configs included), known arrows excepted."""
    offenders = []
    for rel, tree in modules:
        source = rel.removesuffix(".py").removesuffix("/__init__").replace("/", ".")
        rank = _layer(source)
        for target, line in _imported(rel, tree):
            if target.split(".")[0] not in ("diffkin", "envs", "training", "benchmarks", "configs"):
                continue  # torch, the standard library, ...
            if _unit(target) == _unit(source) or _layer(target) <= rank:
                continue
            if (_unit(source), _unit(target)) not in KNOWN_UPWARD:
                offenders.append(f"{rel}:{line} {source} -> {target}")
    return offenders


def test_lower_layers_never_import_upward():
    """kernels import only kernels, validation, numerics and errors; rotations/transforms import those and
    the kernels; nothing below imports anything above it; none of them imports the apps."""
    assert _upward_imports(_modules("diffkin")) == []


@pytest.mark.parametrize(("rel", "source", "caught"), [
    ("diffkin/kernels/x.py", "from ..chain import KinematicChain", True),
    ("diffkin/kernels/x.py", "def f():\n    from diffkin.models import load", True),
    ("diffkin/kernels/x.py", "from .. import ik", True),
    ("diffkin/kernels/x.py", "import diffkin", True),
    ("diffkin/kernels/x.py", "import importlib\nimportlib.import_module('diffkin.collision')", True),
    ("diffkin/rotations.py", "from .jacobian import geometric_jacobian", True),
    ("diffkin/validation.py", "from .rotations import matrix_to_quaternion", True),
    ("diffkin/errors.py", "from ._numerics import eps_for", True),
    ("diffkin/_numerics.py", "from diffkin.training.config import load_config", True),
    ("diffkin/kernels/x.py", "from ..rotations import _skew\nfrom .tree import Topology", True),
    ("diffkin/kernels/sub/x.py", "from ...transforms import _make_transform\nfrom .. import tree", True),
    ("diffkin/kernels/x.py", "from .rigid import _skew\nfrom .tree import Topology", False),
    ("diffkin/rotations.py", "from .kernels import pose_error", False),  # downward
    ("diffkin/chain.py", "from .ik import solve\nfrom .models import load", False),
])
def test_the_layer_check_catches_a_constructed_violation(rel, source, caught):
    """The check above is only worth its green if it goes red: each of these sources, placed at ``rel``,
    is (or is not) reported."""
    found = _upward_imports([(rel, ast.parse(source))])
    assert bool(found) is caught, found


def _calls_with_function(tree: ast.AST):
    """(call node, name of the innermost enclosing function or None) for every call in ``tree``."""

    def visit(node, func):
        for child in ast.iter_child_nodes(node):
            inner = child.name if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) else func
            if isinstance(child, ast.Call):
                yield child, func
            yield from visit(child, inner)

    yield from visit(tree, None)


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return "?"


# Command-line entry points (the only places that may set process-wide state).
ENTRY_POINTS = {("diffkin/cli/__init__.py", "main"), ("training/train.py", "main"),
                ("training/evaluate.py", "main"), ("training/tune.py", "main"),
                ("training/compare.py", "main"), ("training/robustness.py", "main")}


def test_only_entry_points_set_threads_or_the_matplotlib_backend():
    offenders = []
    for rel, tree in _modules("diffkin", "envs", "training"):
        for call, func in _calls_with_function(tree):
            name = _dotted(call.func)
            if name.endswith(("set_num_threads", "set_num_interop_threads")):
                allowed = ENTRY_POINTS
            elif name in ("matplotlib.use", "mpl.use") or name.endswith("switch_backend"):
                allowed = {("diffkin/cli/__init__.py", "main")}  # only the diffkin command, when asked
            else:
                continue
            if (rel, func) not in allowed:
                offenders.append(f"{rel}:{call.lineno} {name}() in {func or 'module scope'}")
    assert offenders == []


def test_library_draws_files_without_pyplot():
    """File output goes through matplotlib.figure.Figure; pyplot (global figure state, a backend) is for
    figures shown interactively, which the library does not do."""
    offenders = []
    for rel, tree in _modules("diffkin", "envs", "training"):
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            if any(n == "matplotlib.pyplot" or n == "matplotlib.use" for n in names):
                offenders.append(f"{rel}:{node.lineno}")
    assert offenders == []


#: the one exception: the native kernel's build runs the system's C compiler once (kernels/native.py)
_COMPILER_RUNNERS = {"diffkin/kernels/native.py"}


def test_library_starts_no_subprocesses():
    offenders = []
    for rel, tree in _modules("diffkin"):
        if str(rel) in _COMPILER_RUNNERS:
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "subprocess" for a in node.names):
                offenders.append(f"{rel}:{node.lineno}")
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "subprocess":
                offenders.append(f"{rel}:{node.lineno}")
            if isinstance(node, ast.Call) and _dotted(node.func) in ("os.system", "os.popen", "os.execv"):
                offenders.append(f"{rel}:{node.lineno}")
    assert offenders == []


_DYNAMIC_IMPORTS = ("importlib.import_module", "__import__")


def test_environments_know_no_trainer():
    """envs/ imports no RL library (stable-baselines3 and its adapter live in training/)."""
    trainers = ("stable_baselines3", "sb3_contrib", "rl_zoo3", "diffkin.training")
    offenders = []
    for rel, tree in _modules("envs"):
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Call) and _dotted(node.func) in _DYNAMIC_IMPORTS:
                names = [a.value for a in node.args[:1]
                         if isinstance(a, ast.Constant) and isinstance(a.value, str)]
            if any(n == t or n.startswith(t + ".") for n in names for t in trainers):
                offenders.append(f"{rel}:{node.lineno}")
    assert offenders == []
