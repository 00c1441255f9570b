"""The stable-baselines3 algorithms a run config may name (shared by :mod:`training.train` and
:mod:`training.evaluate`, which must not import each other), and the import of the packages that register
environments outside diffkin (panda-gym)."""

from __future__ import annotations

from stable_baselines3 import PPO, SAC, TD3

from diffkin.errors import require

__all__ = ["ALGOS", "EVAL_SEED", "algo_class", "import_env_package", "is_diffkin_env"]

ALGOS = {"sac": SAC, "td3": TD3, "ppo": PPO}
try:  # TQC lives in sb3-contrib (the `contrib` extra); configs/tqc.yaml names it
    from sb3_contrib import TQC

    ALGOS["tqc"] = TQC
except ImportError:  # pragma: no cover - depends on the installed extras
    pass
EVAL_SEED = 10_000  # seed of the evaluation episodes during training

#: env ID prefix → (module that registers it, extra that installs it)
_ENV_PACKAGES = {"Panda": ("panda_gym", "panda")}


def algo_class(name: str):
    """The SB3 class of an algorithm name (``"sac"``, ``"td3"``, ``"ppo"``, ``"tqc"``); ``tqc`` without
    sb3-contrib raises ``MissingExtraError`` naming the extra."""
    if name == "tqc" and "tqc" not in ALGOS:
        require("sb3_contrib", "contrib", "algo 'tqc'")
    return ALGOS[name]


def is_diffkin_env(env_id: str) -> bool:
    """Whether ``env_id`` is one of diffkin's own envs (batched evaluation on ``TorchVectorEnv``)."""
    return env_id.startswith("diffkin/")


def import_env_package(env_id: str) -> None:
    """Import what registers ``env_id`` with Gymnasium: diffkin's envs, or panda-gym for ``Panda*`` IDs
    (``MissingExtraError`` naming the ``panda`` extra when it is not installed)."""
    if is_diffkin_env(env_id):
        import diffkin.envs  # noqa: F401
        return
    for prefix, (module, extra) in _ENV_PACKAGES.items():
        if env_id.startswith(prefix):
            require(module, extra, f"env {env_id!r}")
