"""What every ``diffkin demo`` section shares: the report, the machine line, figures, tables, timing and the
shipped robots' files."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..errors import require

REPO_ROOT = Path(__file__).resolve().parents[2]
_NOT_SHIPPED = ("{} is not in the installed package (its licence is not stated: the robot ships in the "
                "source repository only).")


def _shipped(name: str) -> Path:
    """The file of a catalogued robot (``models.model_path``): the demo reads what the package installs."""
    from ..models import model_path

    return model_path(name)


@dataclass
class Report:
    out: Path
    sections: list[str] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)

    def add(self, title: str, body: str) -> None:
        self.sections.append(f"## {title}\n\n{body.strip()}\n")

    def write(self) -> Path:
        head = f"# diffkin demo report\n\nGenerated {time.strftime('%Y-%m-%d %H:%M:%S')} on {_machine()}.\n"
        path = self.out / "report.md"
        path.write_text(head + "\n" + "\n".join(self.sections))
        return path


def _machine() -> str:
    import platform

    threads = torch.get_num_threads()
    cpu = platform.processor() or platform.machine()
    return (
        f"{cpu} CPU, {threads} torch thread(s) (`diffkin demo` uses 1 unless given `--threads N`), "
        f"torch {torch.__version__}"
    )


def _figure_module():
    return require("matplotlib.figure", "plot", "diffkin demo (its figures)")


def _figure(**kwargs):
    """A figure for file output: no pyplot, no backend switch."""
    return _figure_module().Figure(**kwargs)


def _md_table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0
