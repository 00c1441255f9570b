"""Hyperparameter sweeps with Optuna on a shared store, in rl-baselines3-zoo's manner.

A sweep is a run config (an entry of ``configs/<algo>.yaml`` such as ``diffkin/Reach-v0:tune``, or a
single-run file; see :mod:`training.config`) with two more sections::

    search_space:                       # dotted paths into the config -> an Optuna distribution
      algo_kwargs.learning_rate: {type: float, low: 1.0e-4, high: 3.0e-3, log: true}
      algo_kwargs.batch_size: {type: categorical, choices: [128, 256, 512]}
      algo_kwargs.gradient_steps: {type: int, low: 1, high: 4}
    tune:
      metric: success_rate              # an evaluation key (tracking_error for Track)
      direction: maximize               # or minimize
      pruner: {type: median, n_startup_trials: 5, n_warmup_steps: 2000}   # or threshold / none
      sampler: {type: tpe, n_startup_trials: 5}                            # or random

Every trial trains the config with the sampled values (same seed), reports each evaluation's metric to
Optuna and is pruned when the pruner says so; its value is the final evaluation's metric. Workers share one
study through the storage: ``sqlite:///runs/tune/NAME.db`` by default (one file, no server; several
processes on one machine), any SQLAlchemy URL (``postgresql://user:pw@host/db``) for workers on several
machines, or ``journal:PATH`` for Optuna's journal file (a shared file system without a database).
``--trials`` counts the trials of one worker, as in rl-zoo.
"""

from __future__ import annotations

import copy
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from diffkin.errors import require
from diffkin.training.config import RunConfig, load_config, read_entry
from diffkin.validation import check_count

__all__ = [
    "SPACE_TYPES",
    "PRUNERS",
    "apply_params",
    "sample_params",
    "make_storage",
    "default_storage",
    "load_study",
    "tune",
    "best_config",
    "show",
    "state_counts",
]

SPACE_TYPES = ("float", "int", "categorical")
PRUNERS = ("median", "threshold", "none")
_TUNE_KEYS = {"metric", "direction", "pruner", "sampler"}


def _optuna():
    return require("optuna", "tune", "diffkin tune")  # MissingExtraError naming the extra


_SPACE_KEYS = {"float": {"type", "low", "high", "log", "step"}, "int": {"type", "low", "high", "log", "step"},
               "categorical": {"type", "choices"}}


def _check_space(space: dict) -> dict:
    """Refuse a malformed search space before any trial runs (each problem named by its path)."""
    if not isinstance(space, dict) or not space:
        raise ValueError("search_space: expected a mapping of dotted config paths to distributions, got "
                         f"{space!r}")
    for key, spec in space.items():
        where = f"search_space.{key}"
        kind = spec.get("type") if isinstance(spec, dict) else None
        if kind not in SPACE_TYPES:
            raise ValueError(f"{where}: type must be one of {SPACE_TYPES}, got {kind!r}")
        unknown = sorted(set(spec) - _SPACE_KEYS[kind])
        if unknown:
            known = sorted(_SPACE_KEYS[kind])
            raise ValueError(f"{where}: unknown keys {unknown} for a {kind}; known: {known}")
        if kind == "categorical":
            if not isinstance(spec.get("choices"), list) or not spec["choices"]:
                raise ValueError(f"{where}: choices must be a non-empty list, got {spec.get('choices')!r}")
            continue
        missing = [k for k in ("low", "high") if k not in spec]
        if missing:
            raise ValueError(f"{where}: {kind} needs {missing}")
        number = int if kind == "int" else (int, float)
        for k in ("low", "high", "step"):
            v = spec.get(k)
            if k in spec and (isinstance(v, bool) or not isinstance(v, number)):
                what = "an integer" if kind == "int" else "a number"
                raise ValueError(f"{where}: {k} must be {what}, got {v!r}")
        if not spec["low"] < spec["high"]:
            raise ValueError(f"{where}: expected low < high, got {spec['low']} and {spec['high']}")
        if spec.get("log") and spec["low"] <= 0:
            raise ValueError(f"{where}: a log scale needs low > 0, got {spec['low']}")
        if "step" in spec and not spec["step"] > 0:
            raise ValueError(f"{where}: step must be > 0, got {spec['step']}")
        if spec.get("log") and "step" in spec:
            raise ValueError(f"{where}: give log or step, not both (Optuna samples one or the other)")
    return space


def _representative(space: dict) -> dict[str, Any]:
    """One value per path (the low end, or the first choice): what a dry run of the config is built with."""
    return {k: v["choices"][0] if v["type"] == "categorical" else v["low"] for k, v in space.items()}


def sample_params(trial, space: dict) -> dict[str, Any]:
    """One value per dotted path of ``space``, drawn by ``trial`` (an ``optuna.Trial``)."""
    params = {}
    for key, spec in space.items():
        kind = spec["type"]
        if kind == "float":
            params[key] = trial.suggest_float(key, spec["low"], spec["high"], log=spec.get("log", False),
                                              step=spec.get("step"))
        elif kind == "int":
            params[key] = trial.suggest_int(key, spec["low"], spec["high"], log=spec.get("log", False),
                                            step=spec.get("step", 1))
        else:
            params[key] = trial.suggest_categorical(key, list(spec["choices"]))
    return params


def apply_params(cfg: RunConfig, params: dict[str, Any]) -> RunConfig:
    """The config with each dotted path set (``algo_kwargs.policy_kwargs.net_arch``, ``n_envs``, ...)."""
    data = copy.deepcopy(cfg.to_dict())
    for key, value in params.items():
        *parents, leaf = key.split(".")
        node = data
        for p in parents:
            if node.get(p) is None:
                node[p] = {}
            node = node[p]
            if not isinstance(node, dict):
                raise ValueError(f"search_space.{key}: {p} is not a mapping in the config")
        if not parents and leaf not in data:
            raise ValueError(f"search_space.{key}: no such config field")
        if isinstance(node.get(leaf), dict) and not isinstance(value, dict):
            raise ValueError(f"search_space.{key}: the config's {leaf} is a mapping; search one of its keys "
                             f"({key}.<name>), not the mapping itself")
        node[leaf] = value
    return RunConfig(**data)


def default_storage(name: str) -> str:
    """``sqlite:///runs/tune/<name>.db`` (relative to the working directory)."""
    return f"sqlite:///{Path('runs') / 'tune' / f'{name}.db'}"


def _file_of(url: str) -> Path | None:
    """The local file of a ``journal:`` or ``sqlite:///`` storage, else None."""
    for prefix in ("journal:", "sqlite:///"):
        if url.startswith(prefix):
            return Path(url.removeprefix(prefix))
    return None


def _make_parent(path: Path) -> None:
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(f"{path}: cannot create it: {parent} is a file, not a directory")
            break
    path.parent.mkdir(parents=True, exist_ok=True)


def make_storage(url: str, create: bool = True):
    """An Optuna storage: ``journal:PATH`` (journal file) or an SQLAlchemy URL (SQLite, PostgreSQL...).

    ``create=False`` refuses a local file that does not exist yet (reading a study must not create one).
    Several workers starting at once on a new SQLite file may race to create its tables: a failed first
    connection is retried a few times."""
    optuna = _optuna()
    path = _file_of(url)
    if path is not None:
        if not create and not path.exists():
            raise ValueError(f"{url}: no such storage file {path}")
        _make_parent(path)
    if url.startswith("journal:"):
        from optuna.storages.journal import JournalFileBackend

        return optuna.storages.JournalStorage(JournalFileBackend(str(path)))
    # a busy SQLite file (several workers) waits instead of failing at once
    kwargs = {"engine_kwargs": {"connect_args": {"timeout": 60}}} if url.startswith("sqlite:") else {}
    for attempt in range(5):
        try:
            return optuna.storages.RDBStorage(url, **kwargs)
        except ImportError as exc:  # the URL's database driver
            raise ValueError(f"{url}: its database driver is not installed ({exc}); for PostgreSQL: "
                             "pip install psycopg2-binary") from None
        except Exception as exc:  # noqa: BLE001 - SQLAlchemy's errors, named in the message
            kind = type(exc).__name__
            if kind in ("ArgumentError", "NoSuchModuleError") or attempt == 4:
                raise ValueError(f"cannot open the storage {url}: {kind}: {exc}") from None
            time.sleep(0.5 * (attempt + 1))  # another worker creating the tables: try again


def _settings(sweep: dict) -> dict:
    tune = dict(sweep.get("tune") or {})
    unknown = set(tune) - _TUNE_KEYS
    if unknown:
        raise ValueError(f"tune: unknown keys {sorted(unknown)}; known: {sorted(_TUNE_KEYS)}")
    tune.setdefault("metric", "success_rate")
    tune.setdefault("direction", "maximize")
    if tune["direction"] not in ("maximize", "minimize"):
        raise ValueError(f"tune.direction must be maximize or minimize, got {tune['direction']!r}")
    return tune


def _pruner(spec: dict | None):
    optuna = _optuna()
    spec = dict(spec or {"type": "median"})
    kind = spec.pop("type", "median")
    if kind == "median":
        return optuna.pruners.MedianPruner(**spec)
    if kind == "threshold":
        return optuna.pruners.ThresholdPruner(**spec)
    if kind == "none":
        return optuna.pruners.NopPruner()
    raise ValueError(f"tune.pruner.type must be one of {PRUNERS}, got {kind!r}")


def _sampler(spec: dict | None, space: dict):
    optuna = _optuna()
    spec = dict(spec or {"type": "tpe"})
    kind = spec.pop("type", "tpe")
    if kind == "tpe":
        return optuna.samplers.TPESampler(**spec)
    if kind == "random":
        return optuna.samplers.RandomSampler(**spec)
    if kind == "grid":  # every combination once, shared out among the workers
        not_categorical = [k for k, v in space.items() if v["type"] != "categorical"]
        if not_categorical:
            raise ValueError(f"tune.sampler grid needs categorical search spaces, not {not_categorical}")
        return optuna.samplers.GridSampler({k: list(v["choices"]) for k, v in space.items()}, **spec)
    raise ValueError(f"tune.sampler.type must be tpe, random or grid, got {kind!r}")


def read_sweep(config: str | Path, env: str | None = None, variant: str | None = None
               ) -> tuple[RunConfig, dict, dict]:
    """The run config, its search space and its tune settings (``env`` / ``variant`` choose the entry of an
    algorithm file, as in :func:`~diffkin.training.config.load_config`)."""
    sweep = read_entry(config, env, variant)
    space = _check_space(sweep.get("search_space"))
    return load_config(config, env, variant), space, _settings(sweep)


def load_study(storage: str, study: str, tune_settings: dict | None = None, create: bool = False,
               space: dict | None = None):
    """The study ``study`` in ``storage`` (created with the settings' direction, pruner and sampler over
    ``space`` when asked)."""
    optuna = _optuna()
    store = make_storage(storage, create=create)
    if not create:
        try:
            return optuna.load_study(study_name=study, storage=store)
        except KeyError:
            names = [s.study_name for s in optuna.get_all_study_summaries(store)]
            raise ValueError(f"no study {study!r} in {storage}; studies there: {names or 'none'}") from None
    tune_settings = tune_settings or _settings({})
    for attempt in range(5):  # workers creating the same study at once: the losers load it
        try:
            return optuna.create_study(
                study_name=study, storage=store, load_if_exists=True, direction=tune_settings["direction"],
                pruner=_pruner(tune_settings.get("pruner")),
                sampler=_sampler(tune_settings.get("sampler"), space or {}),
            )
        except Exception as exc:  # noqa: BLE001 - a race on the study row, or a real error on the 5th try
            if attempt == 4 or isinstance(exc, ValueError | TypeError):
                raise
            time.sleep(0.5 * (attempt + 1))


def _objective(cfg: RunConfig, space: dict, settings: dict, out: Path, log: Callable[[str], None]):
    optuna = _optuna()
    from diffkin.training.train import train

    metric = settings["metric"]

    def objective(trial) -> float:
        params = sample_params(trial, space)
        run = apply_params(cfg, params).replace(name=f"{cfg.name}-trial{trial.number}")

        def report(point: dict) -> None:
            if metric not in point:
                raise ValueError(f"tune.metric {metric!r} is not an evaluation key; got {sorted(point)}")
            trial.report(float(point[metric]), step=int(point["timesteps"]))
            if trial.should_prune():
                raise optuna.TrialPruned(f"pruned at {point['timesteps']} steps ({metric} {point[metric]})")

        t0 = time.time()
        try:
            res = train(run, out / f"trial{trial.number:04d}", progress_bar=False, log=lambda _m: None,
                        on_evaluate=report)
        except optuna.TrialPruned as exc:
            log(f"trial {trial.number}: {exc} with {json.dumps(params)}")
            raise
        value = float(res["final"][metric])
        trial.set_user_attr("train_wall_s", round(time.time() - t0, 1))
        trial.set_user_attr("timesteps", res["timesteps"])
        log(f"trial {trial.number}: {metric} {value:.4g} with {json.dumps(params)}")
        return value

    return objective


def tune(config: str | Path, trials: int, storage: str | None = None, study: str | None = None,
         out: str | Path | None = None, log: Callable[[str], None] = print, env: str | None = None,
         variant: str | None = None):
    """Run ``trials`` trials of the sweep in ``config`` (its entry ``env`` / ``variant`` for an algorithm
    file) in this process, in the shared ``study``.

    Returns the study. Several processes (on one or several machines) may run this at once on the same
    storage and study name: Optuna hands each its own trials.
    """
    optuna = _optuna()
    trials = check_count(trials, "trials")
    cfg, space, settings = read_sweep(config, env, variant)
    name = study or cfg.name
    storage = storage or default_storage(name)
    out = Path(out) if out else Path("runs") / "tune" / name
    _dry_run(apply_params(cfg, _representative(space)), settings["metric"])  # before the study is touched
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # one line per trial from our own log
    st = load_study(storage, name, settings, create=True, space=space)
    st.set_user_attr("config", str(config))
    st.set_user_attr("env", env)
    st.set_user_attr("variant", variant)
    st.set_user_attr("metric", settings["metric"])
    optuna.logging.set_verbosity(optuna.logging.ERROR)  # a failing trial raises: no second report of it
    states: list[str] = []  # this worker's trials, as they end

    def remember(_study, trial) -> None:
        states.append(trial.state.name.lower())

    st.optimize(_objective(cfg, space, settings, out, log), n_trials=trials, catch=(), callbacks=[remember])
    counts = ", ".join(f"{states.count(k)} {k}" for k in sorted(set(states)))
    log(f"this worker: {len(states)} trials ({counts})")
    return st


def _dry_run(cfg: RunConfig, metric: str) -> None:
    """Build the env, the evaluation env and the model of one trial's config (no training) and check the
    metric: bad algorithm or env settings fail here, before any trial is recorded."""
    from diffkin.envs.vector import TorchVectorEnv
    from diffkin.training.evaluate import run_episodes, scripted_policy
    from diffkin.training.train import build_env, build_model

    try:
        venv = build_env(cfg)
        try:
            build_model(cfg, venv, None)
        finally:
            venv.close()
        probe = TorchVectorEnv(cfg.env_id, 1, **{**cfg.env_kwargs, **cfg.eval_env_kwargs})
        keys = set(run_episodes(probe, scripted_policy))
    except Exception as exc:  # noqa: BLE001 - SB3 / env errors of many kinds, named in one message
        raise ValueError(f"the sweep's config does not build ({type(exc).__name__}: {exc})") from None
    if metric not in keys:
        raise ValueError(f"tune.metric {metric!r} is not an evaluation result of {cfg.env_id}; "
                         f"choose one of {sorted(keys - {'episodes'})}")


def best_config(study, config: str | Path | None = None, env: str | None = None,
                variant: str | None = None) -> dict:
    """The run config of the study's best trial, as a mapping ready for ``yaml.safe_dump`` (a single-run
    file). Without ``config``, the config, env and variant the study recorded."""
    if config is None:
        config = study.user_attrs.get("config")
        env, variant = study.user_attrs.get("env"), study.user_attrs.get("variant")
    if config is None:
        raise ValueError("the study does not record its config: pass --config")
    cfg, _, _ = read_sweep(config, env, variant)
    best = apply_params(cfg, study.best_trial.params).replace(name=f"{cfg.name}-best")
    return best.to_dict()


def show(storage: str, study: str, top: int = 5, output: str | Path | None = None,
         config: str | Path | None = None, env: str | None = None,
         variant: str | None = None) -> tuple[list[dict], Path | None]:
    """The ``top`` best finished trials (rows of number, value, params, state counts) and, when the study
    has a finished trial, the best config written to ``output`` (default ``runs/tune/<study>/best.yaml``)."""
    optuna = _optuna()
    st = load_study(storage, study)
    done = [t for t in st.trials if t.state == optuna.trial.TrialState.COMPLETE]
    maximize = st.direction == optuna.study.StudyDirection.MAXIMIZE
    done.sort(key=lambda t: -t.value if maximize else t.value)
    rows = [{"trial": t.number, "value": t.value, "params": t.params,
             "train_wall_s": t.user_attrs.get("train_wall_s")} for t in done[:top]]
    if not done:
        return rows, None
    path = Path(output) if output else Path("runs") / "tune" / study / "best.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    text = yaml.safe_dump(best_config(st, config, env, variant), sort_keys=False)
    path.write_text(f"# best trial {st.best_trial.number} of study {study!r}: "
                    f"{st.user_attrs.get('metric', 'value')} = {st.best_value:.6g}\n" + text)
    return rows, path


def state_counts(storage: str, study: str) -> dict[str, int]:
    """How many trials of the study are complete, pruned, failed, running."""
    st = load_study(storage, study)
    counts: dict[str, int] = {}
    for t in st.trials:
        counts[t.state.name.lower()] = counts.get(t.state.name.lower(), 0) + 1
    return counts



def add_arguments(p) -> None:
    """The options of ``diffkin tune`` / ``python -m diffkin.training.tune``."""
    p.add_argument("--config", required=True, help="run config with search_space and tune sections: "
                   "configs/<algo>.yaml with --env (and --variant), or a single-run file")
    p.add_argument("--env", help="the entry's env ID in an algorithm file, e.g. diffkin/Reach-v0")
    p.add_argument("--variant", help="the entry's variant, e.g. tune (the key diffkin/Reach-v0:tune)")
    p.add_argument("--trials", type=int, default=10, help="trials this worker runs (default: 10)")
    p.add_argument("--storage", help="sqlite:///FILE, an SQLAlchemy URL (postgresql://...) or journal:FILE "
                   "(default: sqlite:///runs/tune/<study>.db)")
    p.add_argument("--study", help="study name shared by the workers (default: the config's name)")
    p.add_argument("--show", action="store_true", help="print the best trials and write the best config")
    p.add_argument("--top", type=int, default=5, help="trials --show prints (default: 5)")
    p.add_argument("--output", help="best config written by --show (default: runs/tune/<study>/best.yaml)")


def run(args, log: Callable[[str], None] = print) -> int:
    """Carry out parsed arguments (a sweep, or ``--show``)."""
    env, variant = getattr(args, "env", None), getattr(args, "variant", None)
    name = args.study or load_config(args.config, env, variant).name
    storage = args.storage or default_storage(name)
    if args.show:
        rows, path = show(storage, name, top=args.top, output=args.output, config=args.config, env=env,
                          variant=variant)
        counts = state_counts(storage, name)
        log(f"study {name!r} in {storage}: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())))
        for r in rows:
            log(f"  trial {r['trial']:4d}  value {r['value']:.6g}  {json.dumps(r['params'])}")
        log(f"wrote {path}" if path else "no finished trial yet: no best config")
        return 0
    tune(args.config, args.trials, storage=storage, study=name, log=log, env=env, variant=variant)
    log(f"the study: {json.dumps(state_counts(storage, name))}; `--show` prints the best trials")
    return 0


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m diffkin.training.tune", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    import torch

    cfg = load_config(args.config, args.env, args.variant)
    torch.set_num_threads(cfg.torch_threads)  # the entry point applies the config's
    return run(args)


if __name__ == "__main__":
    raise SystemExit(main())
