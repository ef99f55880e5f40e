"""A PettingZoo parallel environment: riskplan's team of N robots in one shared world (the `envs` extra).

    env = SensorTeamEnv(["experiment=paper_team"])   # team.robots robots at world.start (or team.starts)

The robots act simultaneously. Each one is a robot of SensorPlanningEnv: the same observation, action, reward,
termination and info, with its own reward draws. They share the world: its regions and its sources, which a
mobile source makes visible (it walks once per time step, for every robot at once). Robots do not collide, block
or pay each other, and reaching a source does not use it up. This is riskplan's team model: each robot's episodes
are samples of the same world, so each robot's returns have the single-robot kernel's distribution.
A robot leaves `agents` when its episode ends; the environment is over when every robot's has.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

try:
    from gymnasium import spaces
    from pettingzoo import ParallelEnv
except ImportError as err:  # pragma: no cover - the optional extra is missing
    raise ImportError(
        "riskplan.experiments.environments.SensorTeamEnv needs PettingZoo: pip install 'riskplan[envs]'"
    ) from err

from riskplan.engine.world import MOVE_NAMES
from riskplan.experiments.environments.core import Worlds, env_setup, new_seed
from riskplan.experiments.environments.gym import infos, observation_space, observations, render_ansi


class SensorTeamEnv(ParallelEnv):
    """N robots acting simultaneously in one shared riskplan world (module docstring)."""

    metadata: ClassVar[dict] = {"name": "riskplan_sensor_team_v0", "render_modes": ["ansi"], "is_parallelizable": True}

    def __init__(self, config: Any = None, *, render_mode: str | None = None):
        """`config`: riskplan overrides, a composed config or a RunSetup; the team is team.robots robots."""
        self.setup, starts = env_setup(config, render_mode, self.metadata["render_modes"])
        self.world = self.setup.world
        self.render_mode = render_mode
        self._worlds = Worlds(self.world, starts, group=np.zeros(len(starts), dtype=np.int64))  # one shared copy
        self.possible_agents = [f"robot_{i}" for i in range(len(starts))]
        self.agents: list[str] = []
        self._index = {name: i for i, name in enumerate(self.possible_agents)}
        self._observation_space = observation_space(self.world)
        self._action_space = spaces.Discrete(len(MOVE_NAMES))
        self._rng: np.random.Generator | None = None

    def observation_space(self, agent: str) -> spaces.Dict:
        self._known(agent)
        return self._observation_space

    def action_space(self, agent: str) -> spaces.Discrete:
        self._known(agent)
        return self._action_space

    def _known(self, agent) -> None:
        if agent not in self._index:
            raise ValueError(f"no robot {agent!r}; the robots are {', '.join(self.possible_agents)}")

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(seed)
        self._worlds.reset(new_seed(self._rng))
        self.agents = list(self.possible_agents)
        obs, info = observations(self._worlds), infos(self._worlds)
        return ({a: obs[i] for i, a in enumerate(self.agents)}, {a: info[i] for i, a in enumerate(self.agents)})

    def step(self, actions: dict[str, int]):
        if not self.agents:
            raise RuntimeError("every robot's episode has ended; call reset()")
        if not isinstance(actions, Mapping):  # a list's items would be taken for robots' names
            example = ", ".join(f"'{a}': 4" for a in self.agents)
            raise TypeError(f"actions: got {type(actions).__name__}; give a dict of robot to move, e.g. {{{example}}}")
        for agent in actions:
            self._known(agent)
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"no action for {', '.join(missing)}: every live robot acts at every step")
        moves = np.full(len(self.possible_agents), len(MOVE_NAMES) // 2, dtype=np.int64)  # Stay, for the finished
        for agent in self.agents:
            if isinstance(actions[agent], (bool, np.bool_)) or not self._action_space.contains(actions[agent]):
                raise ValueError(f"action {actions[agent]!r} of {agent} is not one of 0..4 ({', '.join(MOVE_NAMES)})")
            moves[self._index[agent]] = int(actions[agent])
        reward, terminated, truncated = self._worlds.step(moves)
        obs, info = observations(self._worlds), infos(self._worlds)
        live = [(a, self._index[a]) for a in self.agents]
        self.agents = [a for a, i in live if not (terminated[i] or truncated[i])]
        return (
            {a: obs[i] for a, i in live},
            {a: float(reward[i]) for a, i in live},
            {a: bool(terminated[i]) for a, i in live},
            {a: bool(truncated[i]) for a, i in live},
            {a: info[i] for a, i in live},
        )

    def render(self):
        if self.render_mode == "ansi":
            return render_ansi(self._worlds)
        return None

    def close(self):
        pass
