"""Shared benchmark utilities: timing (median of timed blocks after a warm-up), the pytorch-kinematics Panda
built from the bundled URDF, peak-memory probes, and table printing (rich if available, else plain text).

Timing model: each figure is the median over ``repeats`` blocks; a block calls the function until at least
``min_time`` seconds have passed and records the mean time per call. The machine is shared and has two
cores, so medians (not means) and ratios taken in the same run are what to compare.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

__all__ = [
    "PANDA_URDF",
    "QUICK",
    "FULL",
    "sync",
    "timeit",
    "pk_panda",
    "peak_rss_mb",
    "format_rows",
    "print_table",
    "environment",
    "write_json",
    "cli",
]

ROOT = Path(__file__).resolve().parents[1]
PANDA_URDF = ROOT / "diffkin" / "models" / "data" / "panda.urdf"
#: (min_time seconds per block, repeats) for --quick and for a full run
QUICK = (0.05, 3)
FULL = (0.3, 7)


@contextlib.contextmanager
def torch_threads(n: int):
    """Run a benchmark body with ``n`` torch intra-op threads and restore the previous setting."""
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def sync(device) -> None:
    """Wait for queued CUDA work (no-op on CPU) so wall-clock timings are honest."""
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def timeit(fn: Callable[[], object], min_time: float = 0.3, repeats: int = 7, device="cpu",
           warmup: int = 2) -> float:
    """Median seconds per call of ``fn`` over ``repeats`` blocks of at least ``min_time`` s each."""
    for _ in range(warmup):
        fn()
    sync(device)
    per_call = []
    for _ in range(repeats):
        n, t0 = 0, time.perf_counter()
        while True:
            fn()
            n += 1
            sync(device)
            dt = time.perf_counter() - t0
            if dt >= min_time:
                break
        per_call.append(dt / n)
    return statistics.median(per_call)


def pk_panda(dtype=torch.float32, device="cpu", end_link: str = "panda_link8"):
    """pytorch-kinematics serial chain of the Panda to the flange, from ``diffkin/models/data/panda.urdf``."""
    import pytorch_kinematics as pk

    return pk.build_serial_chain_from_urdf(PANDA_URDF.read_bytes(), end_link).to(dtype=dtype, device=device)


def peak_rss_mb(code: str, timeout: float = 300.0) -> float:
    """Peak resident-memory growth (MB) of ``code`` run in a fresh Python process (Linux).

    ``code`` runs after ``import torch``; it must call ``mark()`` right before the measured section.
    ``mark()`` resets the kernel's high-water mark (``/proc/self/clear_refs``) and records the current RSS;
    the result is the high-water mark at the end minus that RSS, i.e. the peak extra memory of what
    follows, including temporaries that were freed again.
    """
    prog = (
        "import torch\n"
        "torch.set_num_threads(1)\n"
        "def _kb(field):\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith(field):\n"
        "            return int(line.split()[1])\n"
        "_base = [0]\n"
        "def mark():\n"
        "    with open('/proc/self/clear_refs', 'w') as f:\n"
        "        f.write('5')\n"
        "    _base[0] = _kb('VmRSS')\n"
        f"{code}\n"
        "print('PEAK_KB', _kb('VmHWM') - _base[0])\n"
    )
    # A fixed mmap threshold makes glibc map every block >= 64 KiB fresh and unmap it on free, so the RSS
    # follows the live tensors and its peak is the peak working memory (no reuse of already-resident heap).
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "65536"}
    out = subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True, timeout=timeout,
                         cwd=ROOT, check=True, env=env).stdout
    kb = next(float(line.split()[1]) for line in out.splitlines() if line.startswith("PEAK_KB"))
    return kb / 1024.0


def _fmt(v) -> str:
    if isinstance(v, float):
        if v == 0 or 1e-3 <= abs(v) < 1e6:
            return f"{v:.4g}"
        return f"{v:.3e}"
    return str(v)


def format_rows(rows: Sequence[dict], columns: Sequence[str] | None = None):
    """``(column names, formatted cells)``: columns are the union of keys in first-seen order unless given."""
    if columns is None:
        columns = []
        for r in rows:
            columns += [k for k in r if k not in columns]
    return list(columns), [[_fmt(r.get(c, "")) for c in columns] for r in rows]


def print_table(rows: Sequence[dict], title: str = "", columns: Sequence[str] | None = None) -> None:
    """Print ``rows`` as a table (rich when installed, else aligned plain text)."""
    if not rows:
        print(f"{title}: no rows")
        return
    cols, cells = format_rows(rows, columns)
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:  # pragma: no cover - rich is a core dependency
        widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(cols)]
        print(title)
        print("  ".join(c.rjust(w) for c, w in zip(cols, widths)))
        for row in cells:
            print("  ".join(v.rjust(w) for v, w in zip(row, widths)))
        return
    table = Table(title=title or None)
    for c in cols:
        table.add_column(c, justify="right")
    for row in cells:
        table.add_row(*row)
    Console(width=200).print(table)


def environment() -> dict:
    """What the numbers were measured on."""
    info = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "machine": platform.machine(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "argv": sys.argv,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    try:
        from importlib.metadata import version

        info["pytorch_kinematics"] = version("pytorch-kinematics")
    except Exception:  # not installed
        info["pytorch_kinematics"] = None
    return info


def write_json(path, rows: Sequence[dict], extra: dict | None = None) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps({"environment": environment(), **(extra or {}), "rows": list(rows)},
                                     indent=2, default=str))


def cli(parser, run, title: str, argv=None) -> int:
    """The tail of a benchmark's ``main``: add ``--threads``, ``--quick`` and ``--json`` to ``parser``, run
    ``run(args)`` on that many torch threads, print its rows as a table titled ``title``, write the JSON."""
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", default=None, help="write the rows (and the environment) to this JSON file")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = run(args)
    print_table(rows, title)
    if args.json:
        write_json(args.json, rows)
    return 0
