"""Gymnasium environments on the diffkin kernels. Importing this package registers the IDs below.

``diffkin/Reach-v0`` (goal-conditioned, HER-ready), ``diffkin/Track-v0`` (path tracking) and
``diffkin/Imitate-v0`` (reference-motion tracking of a retargeted clip), all listed in one table
(:data:`diffkin.envs.registry.ENVS`); the torch-batched vector env is
:class:`diffkin.envs.vector.TorchVectorEnv`. The environments know no trainer: the stable-baselines3
adapter is :mod:`diffkin.training.sb3`.
"""

from __future__ import annotations

from diffkin.errors import require

require("gymnasium", "gym", "diffkin.envs")  # one line naming the extra, not a traceback deep in an import
from gymnasium.envs.registration import register  # noqa: E402
from gymnasium.envs.registration import registry as _gym_registry  # noqa: E402

from .imitate import ImitateEnv as ImitateEnv  # noqa: E402
from .reach import ReachEnv as ReachEnv  # noqa: E402
from .registry import ENV_IDS as ENV_IDS  # noqa: E402
from .registry import ENVS as ENVS  # noqa: E402
from .track import TrackEnv as TrackEnv  # noqa: E402

# Episode length is enforced by the envs themselves (``episode_steps=``; the batched env shares the logic),
# so no TimeLimit is registered. ``gymnasium.make(..., max_episode_steps=k)`` only adds an outer TimeLimit.
for _env_id, _entry in ENV_IDS.items():
    if _env_id not in _gym_registry:
        register(id=_env_id, entry_point=_entry)
