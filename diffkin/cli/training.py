"""``diffkin train``, ``tune``, ``evaluate`` and ``bench``: the repository's training package and benchmarks,
called in this process."""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import DiffkinError
from ._common import _check_device, _check_output_dir, _console


# --------------------------------------------------------------------------- train / evaluate / bench
def _missing(command: str, exc: ImportError) -> DiffkinError:
    """The error for a subcommand whose application code (training/, benchmarks/) cannot be imported."""
    if command == "bench":
        if getattr(exc, "name", None) in ("benchmarks", "benchmarks.run"):
            return DiffkinError(
                "`diffkin bench` runs the benchmark suite of a diffkin checkout (benchmarks/ is not "
                "installed with the package): run `make bench` (or `python -m diffkin.cli bench ...`) from "
                "the root of a clone of the repository"
            )
        return DiffkinError(f"the benchmarks need {exc.name or exc}: `make bench` installs the bench extra")
    return DiffkinError(
        f"`diffkin {command}` needs the training code and its dependencies ({exc}): install the `rl` extra "
        "(`pip install -e '.[rl]'` in a clone of the diffkin repository) or run from the repository"
    )


def _check_config(args) -> None:
    path = Path(args.config)
    if not path.is_file():
        raise DiffkinError(f"--config {path}: no such file" if not path.exists() else
                           f"--config {path}: not a file")


def _config_error(args, exc: Exception) -> DiffkinError:
    """``--config FILE: what is wrong`` (once: the config reader's messages may start with the file)."""
    text = str(exc).removeprefix(f"{args.config}: ")
    return DiffkinError(f"--config {args.config}: {text}")


def _config_threads(args) -> int:
    """The run config's ``torch_threads`` (what ``diffkin train`` runs on without ``--threads``)."""
    _check_config(args)
    try:
        from diffkin.training.config import load_config
    except ImportError as exc:
        raise _missing("train", exc) from exc
    try:
        cfg = load_config(args.config, getattr(args, "env", None), getattr(args, "variant", None))
        return cfg.torch_threads
    except (TypeError, ValueError, KeyError) as exc:
        raise _config_error(args, exc) from exc


def cmd_train(args) -> int:
    _check_config(args)
    if args.output:
        _check_output_dir(Path(args.output))
    try:
        from diffkin.training.train import resolve_run, summary_json, train
    except ImportError as exc:
        raise _missing("train", exc) from exc
    try:
        cfg, out = resolve_run(
            args.config, seed=args.seed, total_timesteps=args.total_timesteps, out=args.output, env=args.env,
            variant=args.variant,
        )
    except (TypeError, ValueError, KeyError) as exc:
        raise _config_error(args, exc) from exc
    res = train(cfg, out, progress_bar=not args.no_progress and sys.stderr.isatty())
    print(summary_json(res))
    _console().print(f"wrote {out}")
    return 0


def cmd_tune(args) -> int:
    _check_config(args)
    try:
        from diffkin.training import tune
    except ImportError as exc:
        raise _missing("tune", exc) from exc
    try:
        return tune.run(args, log=print)
    except (TypeError, ValueError, KeyError) as exc:  # messages name the config path, key or storage
        text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)  # no KeyError repr
        raise DiffkinError(text) from exc


def cmd_evaluate(args) -> int:
    run = Path(args.run_dir)
    if not run.is_dir():
        raise DiffkinError(f"{run}: no such run directory" if not run.exists() else f"{run}: not a directory")
    if not (run / "config.yaml").is_file():
        raise DiffkinError(f"{run}: not a training run directory (no config.yaml; see `diffkin train`)")
    try:
        from diffkin.training.evaluate import evaluate_and_save
    except ImportError as exc:
        raise _missing("evaluate", exc) from exc
    import json

    try:
        res = evaluate_and_save(args.run_dir, episodes=args.episodes)
    except (TypeError, ValueError, KeyError) as exc:
        raise DiffkinError(f"{run}: {exc}") from exc
    print(json.dumps(res, indent=2))
    return 0


def cmd_bench(args) -> int:
    _check_device(args.device)
    try:
        from benchmarks.run import main as run_benchmarks
    except ImportError as exc:
        raise _missing("bench", exc) from exc
    argv = [args.which] + (["--quick"] if args.quick else []) + ["--device", args.device]
    if args.threads is not None:
        argv += ["--threads", str(args.threads)]
    return run_benchmarks(argv)
