"""Run configuration: rl-zoo-style YAML files (one per algorithm, keyed by env ID) → a frozen dataclass.

``configs/sac.yaml`` and ``configs/ppo.yaml`` hold one entry per env ID (``diffkin/Reach-v0``) and per named
variant (``diffkin/Reach-v0:cartesian``); the algorithm is the file's name. Entries share settings through
YAML anchors and merge keys (``<<: *reach``). :func:`load_config` picks one entry::

    load_config("configs/sac.yaml", env="diffkin/Reach-v0", variant="fast")

A *single-run* file (the fields of :class:`RunConfig` at the top level, ``env_id`` and ``algo`` among them:
what a training run writes as ``config.yaml``, what ``diffkin tune --show`` writes) loads without ``env``.
See ``configs/README.md`` for the layout and the names of the runs.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import yaml

__all__ = ["RunConfig", "load_config", "read_entry", "entries"]

_ALGOS = ("sac", "td3", "ppo", "tqc")
_SWEEP_SECTIONS = ("search_space", "tune")
VARIANT_SEP = ":"


@dataclass(frozen=True)
class RunConfig:
    """One training run.

    ``vectorized``: train on the torch-batched env (``envs.vector``) with ``n_envs`` envs; else
    ``n_envs`` single envs in an SB3 ``DummyVecEnv``. ``her``: ``HerReplayBuffer`` kwargs
    (goal-conditioned envs, off-policy algorithms only). ``normalize_kwargs``: ``VecNormalize``'s keyword
    arguments when ``normalize``. ``env_id`` may be a panda-gym ID (``PandaReach-v3``, the ``panda``
    extra): trained on SB3's ``DummyVecEnv``, evaluated on its own envs. ``eval_env_kwargs`` override
    ``env_kwargs`` for evaluation (e.g. the sparse success metric while training on a dense reward).
    ``max_wall_seconds``
    stops training after that much wall-clock; ``stop_success`` once an evaluation reaches that success.
    """

    name: str
    env_id: str
    algo: str
    total_timesteps: int
    seed: int = 0
    n_envs: int = 1
    vectorized: bool = False
    device: str = "cpu"
    torch_threads: int = 1
    env_kwargs: dict = field(default_factory=dict)
    eval_env_kwargs: dict = field(default_factory=dict)
    algo_kwargs: dict = field(default_factory=dict)
    her: dict | None = None
    normalize: bool = False
    normalize_kwargs: dict = field(default_factory=dict)  # VecNormalize's (rl-zoo: gamma = the algo's)
    eval_freq: int = 2000  # env steps between evaluations
    eval_episodes: int = 100
    max_wall_seconds: float | None = None
    stop_success: float | None = None

    def __post_init__(self):
        if self.algo not in _ALGOS:
            raise ValueError(f"algo must be one of {_ALGOS}, got {self.algo!r}")
        if self.her is not None and self.algo == "ppo":
            raise ValueError("HER needs an off-policy algorithm (sac, td3 or tqc), got ppo")

    def replace(self, **changes) -> RunConfig:
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _read(path: str | Path) -> dict:
    try:
        data = yaml.safe_load(Path(path).read_bytes().decode("utf-8"))
    except yaml.YAMLError as e:  # not a ValueError: the CLI's clean `error:` line needs one
        raise ValueError(f"{path}: invalid YAML: {' '.join(str(e).split())}") from None
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping at the top level")
    return data


def _is_single_run(data: dict) -> bool:
    known = {f.name for f in dataclasses.fields(RunConfig)} | set(_SWEEP_SECTIONS)
    return bool(known & set(data))


def entries(path: str | Path) -> list[str]:
    """The keys of an algorithm file (``ENV_ID`` and ``ENV_ID:VARIANT``), in file order; ``[]`` for a
    single-run file."""
    data = _read(path)
    return [] if _is_single_run(data) else [str(k) for k in data]


def read_entry(path: str | Path, env: str | None = None, variant: str | None = None) -> dict:
    """The raw mapping of one run: the entry ``env`` (+ ``:variant``) of an algorithm file, with ``env_id``,
    ``algo`` and ``name`` filled in, or the whole of a single-run file. Sweep sections are kept.

    ``env`` may name the variant itself (``"diffkin/Reach-v0:fast"``). The default ``name`` is
    ``<algo>_<env name>[_<variant>]``, e.g. ``sac_Reach-v0_fast``; ``algo`` is the file's name
    (``sac.yaml``) unless the entry sets it.
    """
    data = _read(path)
    if _is_single_run(data):
        if variant is not None or (env is not None and env != data.get("env_id")):
            raise ValueError(f"{path}: a single-run file (env_id {data.get('env_id')!r}); it has no entries "
                             f"to choose with env={env!r}, variant={variant!r}")
        data.setdefault("name", Path(path).stem)
        return data
    if env is None:
        raise ValueError(f"{path}: one entry per env ID; choose one with --env (and --variant): {list(data)}")
    key = env if variant is None else f"{env}{VARIANT_SEP}{variant}"
    if key not in data:
        raise ValueError(f"{path}: no entry {key!r}; entries: {list(data)}")
    entry = data[key]
    if not isinstance(entry, dict):
        raise ValueError(f"{path}: entry {key!r}: expected a mapping, got {type(entry).__name__}")
    entry = json.loads(json.dumps(entry))  # anchors share objects between entries: give this one its own
    env_id, _, var = key.partition(VARIANT_SEP)
    algo = entry.get("algo", Path(path).stem)
    if algo not in _ALGOS:
        raise ValueError(f"{path}: entry {key!r} sets no algo, and the file's name {Path(path).stem!r} is "
                         f"not one of {_ALGOS}")
    if entry.setdefault("env_id", env_id) != env_id:
        raise ValueError(f"{path}: entry {key!r} sets env_id {entry['env_id']!r}")
    entry["algo"] = algo
    entry.setdefault("name", f"{algo}_{env_id.rsplit('/', 1)[-1]}" + (f"_{var}" if var else ""))
    return entry


def load_config(path: str | Path, env: str | None = None, variant: str | None = None) -> RunConfig:
    """One run of a YAML config: the entry ``env`` (+ ``variant``) of an algorithm file (``configs/sac.yaml``)
    or a single-run file (see :func:`read_entry`). Unknown keys raise ``ValueError`` naming them. A sweep's
    ``search_space`` and ``tune`` sections (:mod:`training.tune`) are left to the sweep."""
    data = read_entry(path, env, variant)
    for section in _SWEEP_SECTIONS:  # read by training.tune; a sweep config trains as its base config
        data.pop(section, None)
    known = {f.name for f in dataclasses.fields(RunConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{path}: unknown keys {unknown}; known: {sorted(known)}")
    return RunConfig(**data)
