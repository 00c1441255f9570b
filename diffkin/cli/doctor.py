"""``diffkin doctor``, ``--version`` and ``diffkin demo``: versions, the fused kernel's state, the tour."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from ._common import _check_output_dir


def _kernel_line() -> str:
    """``fused C kernel: in use (PATH)`` or ``fused C kernel: not in use: WHY`` (builds it if not tried)."""
    from ..kernels import native

    ok, what = native.status()
    return f"fused C kernel: in use ({what})" if ok else f"fused C kernel: not in use: {what}"


class _Version(argparse.Action):
    """``--version``: the version and the fused kernel's state, computed only when asked for."""

    def __init__(self, option_strings, version: str, dest=argparse.SUPPRESS, help=None):
        self.version = version
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{self.version}\n{_kernel_line()}")
        parser.exit()


def cmd_doctor(args) -> int:
    from .. import __version__

    cuda = (f"{torch.cuda.device_count()} device(s), CUDA {torch.version.cuda}" if torch.cuda.is_available()
            else f"not available (CUDA build: {torch.version.cuda or 'no'})")
    print(f"diffkin {__version__} ({Path(__file__).parents[1]})")
    print(f"python {sys.version.split()[0]}, torch {torch.__version__}; CUDA: {cuda}")
    print(_kernel_line())
    return 0


def cmd_demo(args) -> int:
    from ..demo import run_demo

    if args.output:
        _check_output_dir(Path(args.output))
    return run_demo(quick=args.quick, out=args.output, skip_rl=args.skip_rl)
