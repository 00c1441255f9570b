"""Layering rules, checked statically: no import cycles among the project's packages, no library code that
sets process-wide state (torch's thread count, matplotlib's backend) and no subprocesses in the library."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("diffkin", "envs", "training", "benchmarks")
# the project's shared import-cycle tool, vendored unchanged (tests/data/tools/README.md): a clone has it
CYCLES_TOOL = ROOT / "tests" / "data" / "tools" / "import_cycles.py"
# The cycle the kernel-layer rewrite removes (chain <-> jacobian <-> models.io).
KERNEL_LAYER = ("diffkin.chain", "diffkin.jacobian", "diffkin.models")


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


def test_no_import_cycles_outside_the_kernel_layer():
    """Cycles that do not go through diffkin.chain / diffkin.jacobian / diffkin.models (subsumed by
    ``test_no_import_cycles`` once that passes)."""
    outside = [c for c in _cycles() if not any(m.startswith(KERNEL_LAYER) for m in c)]
    assert outside == []


def _modules(*packages: str):
    for pkg in packages:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            yield path.relative_to(ROOT).as_posix(), ast.parse(path.read_text(), str(path))


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
ENTRY_POINTS = {("diffkin/cli.py", "main"), ("training/train.py", "main"), ("training/evaluate.py", "main"),
                ("training/tune.py", "main"), ("training/compare.py", "main"),
                ("training/robustness.py", "main")}


def test_only_entry_points_set_threads_or_the_matplotlib_backend():
    offenders = []
    for rel, tree in _modules("diffkin", "envs", "training"):
        for call, func in _calls_with_function(tree):
            name = _dotted(call.func)
            if name.endswith(("set_num_threads", "set_num_interop_threads")):
                allowed = ENTRY_POINTS
            elif name in ("matplotlib.use", "mpl.use") or name.endswith("switch_backend"):
                allowed = {("diffkin/cli.py", "main")}  # only the diffkin command, when asked
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
