"""riskplan's world for other people's algorithms: a Gymnasium environment (one robot) and a PettingZoo parallel
environment (the team), over the same world semantics and reward programs as the numba kernel. This module is the
public face of `riskplan.experiments.environments`.

    from riskplan.envs import SensorPlanningEnv, SensorTeamEnv, SoftmaxPolicy

`SensorPlanningEnv` and `SensorTeamEnv` need the optional extra (pip install 'riskplan[envs]'); `Worlds`,
`SoftmaxPolicy` and `run_episodes` need only numpy. See README, "A world others' algorithms can use".
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Any

from riskplan.experiments.environments.core import (
    Episodes,
    SoftmaxPolicy,
    Worlds,
    make_setup,
    robot_starts,
    run_episodes,
)

if TYPE_CHECKING:  # provided lazily by __getattr__ below
    from riskplan.experiments.environments.gym import SensorPlanningEnv
    from riskplan.experiments.environments.petting import SensorTeamEnv

with contextlib.suppress(ImportError):  # lets gymnasium.make("riskplan.envs:riskplan/SensorPlanning-v0") find it
    import riskplan.experiments.environments.gym  # noqa: F401 - registers the Gymnasium id

__all__ = [
    "Episodes",
    "SensorPlanningEnv",
    "SensorTeamEnv",
    "SoftmaxPolicy",
    "Worlds",
    "make_setup",
    "robot_starts",
    "run_episodes",
]


def __getattr__(name: str) -> Any:
    """The environments, imported on first use: Gymnasium and PettingZoo are optional."""
    if name == "SensorPlanningEnv":
        from riskplan.experiments.environments.gym import SensorPlanningEnv

        return SensorPlanningEnv
    if name == "SensorTeamEnv":
        from riskplan.experiments.environments.petting import SensorTeamEnv

        return SensorTeamEnv
    raise AttributeError(f"module 'riskplan.envs' has no attribute {name!r}")
