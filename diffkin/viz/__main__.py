"""``python -m diffkin.viz ...``: the viewer with the options of ``diffkin view``."""

import argparse
import sys

from ..errors import DiffkinError
from . import add_parser, cmd_view

parser = argparse.ArgumentParser(prog="python -m diffkin.viz")
add_parser(parser.add_subparsers(dest="command", required=True))
args = parser.parse_args(["view", *sys.argv[1:]])
try:
    sys.exit(cmd_view(args))
except (DiffkinError, FileNotFoundError) as exc:
    print(f"error: {exc}", file=sys.stderr)
    sys.exit(2)
