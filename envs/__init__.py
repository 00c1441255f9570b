"""Gymnasium environments on the diffkin kernels. Importing this package registers the IDs below.

``diffkin/Reach-v0`` (goal-conditioned, HER-ready) and ``diffkin/Track-v0`` (path tracking); a torch-batched
vector env and its SB3 adapter live in :mod:`envs.vector`.
"""

from __future__ import annotations

from diffkin.errors import require

require("gymnasium", "gym", "diffkin.envs")  # one line naming the extra, not a traceback deep in an import
from gymnasium.envs.registration import register, registry  # noqa: E402

from .reach import ReachEnv as ReachEnv  # noqa: E402
from .track import TrackEnv as TrackEnv  # noqa: E402

ENV_IDS = {
    "diffkin/Reach-v0": "diffkin.envs.reach:ReachEnv",
    "diffkin/Track-v0": "diffkin.envs.track:TrackEnv",
}

# Episode length is enforced by the envs themselves (``episode_steps=``; the batched env shares the logic),
# so no TimeLimit is registered. ``gymnasium.make(..., max_episode_steps=k)`` only adds an outer TimeLimit.
for _env_id, _entry in ENV_IDS.items():
    if _env_id not in registry:
        register(id=_env_id, entry_point=_entry)
