"""Run diffkin's benchmarks and print one table per benchmark (ratios are against the reference timed in the
same run, on the same machine and thread count).

    python -m benchmarks.run [fk|jacobian|ik|ik_grad|closed_form|env|calibration|model|kernels|
                              velocity_ik|collision|mjcf|single_call|teleop|all ...]
                             [--quick]
                             [--device cpu|cuda] [--threads N] [--compile] [--json out.json]

Interface for a benchmark module (add ``benchmarks/bench_<name>.py``; it is picked up by name):

* ``run(args) -> list[dict]``: ``args`` is an ``argparse.Namespace`` holding at least ``quick`` (bool),
  ``device`` (str), ``threads`` (int) and ``compile`` (bool); read every option with
  ``getattr(args, name, default)`` so the module also runs alone with its own parser.
* each row is a flat dict of JSON-serialisable scalars; use these keys where they apply: ``benchmark``
  (table name), ``impl``, ``batch``, ``dtype``, ``device``, ``seconds`` (median per call), a rate
  (``configs_per_s`` / ``per_second`` / ``steps_per_s``) and a ratio against the reference in the same run
  (``speedup_vs_pk`` = reference time / this time, or ``ratio_*``). Rows are grouped into tables by
  ``benchmark``; columns are the union of keys in first-seen order.
* optional ``main(argv)`` for running the module alone: ``python -m benchmarks.bench_<name>``.

Timing helpers (median of timed blocks, warm-up, CUDA sync), the pytorch-kinematics Panda built from the
bundled URDF and table printing live in :mod:`benchmarks.common`.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

from benchmarks.common import print_table, write_json

NAMES = ("fk", "jacobian", "ik", "ik_grad", "closed_form", "env", "calibration", "model", "sharded",
         "kernels", "velocity_ik", "collision", "mjcf", "single_call", "teleop")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description="diffkin benchmarks")
    p.add_argument("names", nargs="*", default=["all"], choices=[*NAMES, "all"], metavar="NAME",
                   help=f"benchmarks to run: {', '.join(NAMES)} or all (default)")
    p.add_argument("--quick", action="store_true", help="small batches and short timing blocks")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1)")
    p.add_argument("--compile", action="store_true", help="also time torch.compile fast paths")
    p.add_argument("--json", default=None, help="write all rows (and the environment) to this JSON file")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    names = list(NAMES) if "all" in args.names else list(dict.fromkeys(args.names))
    all_rows: list[dict] = []
    for name in names:
        module_name = f"benchmarks.bench_{name}"
        if importlib.util.find_spec(module_name) is None:
            print(f"[{name}] skipped: no module {module_name}", file=sys.stderr)
            continue
        module = importlib.import_module(module_name)
        rows = module.run(args)
        groups: dict[str, list[dict]] = {}
        for r in rows:
            groups.setdefault(str(r.get("benchmark", name)), []).append(r)
        for title, group in groups.items():
            print_table(group, title)
        all_rows += rows
    if args.json:
        write_json(args.json, all_rows, {"benchmarks": names})
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
