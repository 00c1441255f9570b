"""The documentation site: it builds strictly, and every Python block of every page under ``docs/`` runs;
every Python block of the README runs on its own.

The blocks (```` ```python ```` fences in every ``docs/**/*.md`` that has one) run in order, one interpreter
per page (later blocks use what earlier ones defined, like a notebook), in a temporary directory that holds
links to the repository's ``configs/``, ``examples/`` and ``tests/`` (so the paths of a source checkout,
``tests/data/urdf/fr3.urdf``, work as a reader at the checkout's root has them). Tracebacks name the
Markdown file and line. A block whose first line is ``# requires: NAME[, NAME...]`` is skipped when one of
them is missing; NAME is an extra of ``pyproject.toml`` (``rl``, ``viz``, ``mjcf``, ``gym``), an importable
module, or ``cuda`` (a block that needs a GPU: skipped without one). Blocks that use a skipped block's names
carry the same marker. No block is exempt otherwise: a block too long for the suite would say so with
``# requires: cuda`` or be shortened, never left unrun.

The tests check results, not time: no subprocess here has a time limit of its own (the suite's hang guard,
pyproject's pytest ``timeout``, stops a real hang).
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXTRAS = {"rl": ("gymnasium", "stable_baselines3"), "docs": ("mkdocs", "mkdocstrings", "material"),
          "viz": ("viser",), "mjcf": ("mujoco",), "gym": ("gymnasium",)}
_FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*(?P<info>[^\n`]*)$")
_REQUIRES = re.compile(r"^#\s*requires:\s*(?P<names>.+)$")


def python_blocks(path: Path) -> list[tuple[int, str]]:
    """``(first code line, code)`` of every fenced block whose info string starts with ``python``/``py``."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, lang = m["fence"], m["info"].strip().split(" ")[0].lstrip(".{").lower()
        j = i + 1
        while j < len(lines) and not lines[j].strip().startswith(fence):
            j += 1
        if lang in ("python", "py"):
            blocks.append((i + 2, textwrap.dedent("\n".join(lines[i + 1 : j]))))
        i = j + 1
    return blocks


def missing_requirements(code: str) -> list[str]:
    """The names of a block's ``# requires:`` line that are not installed (``cuda``: no CUDA device)."""
    first = code.lstrip().splitlines()[0] if code.strip() else ""
    m = _REQUIRES.match(first.strip())
    if not m:
        return []
    missing = []
    for name in (n.strip() for n in m["names"].split(",")):
        if name == "cuda":
            import torch

            if not torch.cuda.is_available():
                missing.append(name)
            continue
        modules = EXTRAS.get(name, (name,))
        if any(importlib.util.find_spec(mod) is None for mod in modules):
            missing.append(name)
    return missing


#: every page under docs/ with a python block (the site's pages, the tutorials, the API pages' examples)
PAGES = sorted(p for p in (ROOT / "docs").rglob("*.md") if python_blocks(p))


_DRIVER = """
import sys
ns = {"__name__": "__main__"}
for path, line, code in BLOCKS:
    print(f"--- {path}:{line}", flush=True)
    exec(compile("\\n" * (line - 1) + code, path, "exec"), ns)
"""


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT / "docs").with_suffix("").as_posix()
                                           for p in PAGES])
def test_page_code_blocks_run(page: Path, tmp_path: Path):
    blocks = python_blocks(page)
    assert blocks, f"{page} has no python code block"
    run, skipped = [], []
    for line, code in blocks:
        missing = missing_requirements(code)
        (skipped if missing else run).append((line, code, missing))
    if not run:
        pytest.skip(f"every block needs {sorted({m for *_, ms in skipped for m in ms})}")
    rel = str(page.relative_to(ROOT))
    script = f"BLOCKS = {[(rel, line, code) for line, code, _ in run]!r}\n{_DRIVER}"
    for name in ("configs", "examples", "tests"):
        (tmp_path / name).symlink_to(ROOT / name)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    proc = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True,
                          text=True)
    assert proc.returncode == 0, f"{rel}: a code block failed\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}"
    if skipped:
        missing = sorted({m for *_, ms in skipped for m in ms})
        pytest.skip(f"{len(skipped)} block(s) skipped, missing {missing}")


README = ROOT / "README.md"


def _readme_blocks() -> list[tuple[int, str]]:
    return python_blocks(README)


def _readme_params() -> list:
    """The README's blocks; a block that trains a policy (``.learn(``: the RL quick start, about 50 s on 2
    cores) is a long end-to-end run, outside the default run (``make test-all`` runs it)."""
    return [pytest.param(ln, code, id=f"line{ln}", marks=[pytest.mark.extended] if ".learn(" in code else [])
            for ln, code in _readme_blocks()]


@pytest.mark.parametrize("line,code", _readme_params())
def test_readme_code_block_runs_on_its_own(line: int, code: str, tmp_path: Path):
    """Every python block of the README runs alone (its own interpreter, an empty working directory), as a
    reader would paste it. ``# requires: NAME`` as the first line skips it when NAME is missing."""
    missing = missing_requirements(code)
    if missing:
        pytest.skip(f"README.md:{line} needs {missing}")
    script = f"BLOCKS = {[('README.md', line, code)]!r}\n{_DRIVER}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    proc = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True,
                          text=True)
    assert proc.returncode == 0, f"README.md:{line} failed\n{proc.stdout[-4000:]}\n{proc.stderr[-6000:]}"
    if "make_sb3_vec_env" in code:  # the RL quick start: it prints what the README says it printed
        (claimed_success, claimed_mm), got = readme_rl_claim(), _RL_FIGURE.search(proc.stdout)
        assert got, f"README.md:{line} printed no success figure:\n{proc.stdout[-2000:]}"
        success, mm = int(got["success"]), int(got["mm"])
        close = abs(success - claimed_success) <= RL_TOLERANCE[0] and abs(mm - claimed_mm) <= RL_TOLERANCE[1]
        assert close, f"README claims {claimed_success}%, {claimed_mm} mm; the block printed {got[0]!r}"


#: the README's RL quick start prints ``success N%, final distance M mm``; the prose after it quotes the
#: figure (``It printed `success N%, final distance M mm` here``). The run is seeded and single-threaded, so
#: deterministic on one machine; the tolerance (percentage points, mm) covers other CPUs' rounding.
_RL_FIGURE = re.compile(r"success (?P<success>\d+)%, final distance (?P<mm>\d+) mm")
RL_TOLERANCE = (5, 5)


def readme_rl_claim() -> tuple[int, int]:
    """``(success %, final distance mm)`` the README says its RL quick start printed."""
    m = re.search(r"It printed `" + _RL_FIGURE.pattern + "`", README.read_text(encoding="utf-8"))
    assert m, "README.md: the RL quick start's printed figure is not quoted"
    return int(m["success"]), int(m["mm"])


def test_readme_quickstarts_are_there():
    """The README shows SB3 on the batched env with the settings that matter (and the test above runs it)."""
    sb3 = [code for _, code in _readme_blocks() if "make_sb3_vec_env" in code]
    assert len(sb3) == 1
    for needle in ('"MultiInputPolicy"', "n_steps=50", 'reward_type="dense"', "VecNormalize("):
        assert needle in sb3[0], needle


def test_python_blocks_parser(tmp_path: Path):
    md = tmp_path / "x.md"
    md.write_text("text\n```python\na = 1\n```\n\n```bash\nls\n```\n\n    ```py\n    # requires: rl\n"
                  "    b = a\n    ```\n")
    assert python_blocks(md) == [(3, "a = 1"), (11, "# requires: rl\nb = a")]
    assert missing_requirements("# requires: surely_not_a_module_xyz\nx = 1") == ["surely_not_a_module_xyz"]
    assert missing_requirements("x = 1") == []


@pytest.mark.slow
def test_site_builds_strict(tmp_path: Path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings_handlers.python")
    pytest.importorskip("material")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    site = tmp_path / "site"
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
                          cwd=ROOT, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-6000:]
    pages = ("index.html", "textbook/index.html", "tutorials/calibration/index.html", "benchmarks/index.html",
             "rl/RESULTS/index.html")
    for page in pages:
        assert (site / page).is_file(), page
    api = (site / "api" / "ik" / "index.html").read_text(encoding="utf-8")
    assert 'id="diffkin.ik.solve"' in api and ":func:" not in api  # rendered, Sphinx roles turned into links
