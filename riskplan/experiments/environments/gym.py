"""A Gymnasium environment: one robot in riskplan's world (needs the `envs` extra: pip install 'riskplan[envs]').

    env = SensorPlanningEnv()                      # the paper's Section V world (riskplan's defaults)
    env = SensorPlanningEnv(["world.horizon=30"])  # any riskplan overrides, a composed config or a RunSetup
    env = gymnasium.make("riskplan.experiments.environments.gym:riskplan/SensorPlanning-v0", config=["world.horizon=30"])

Observation (a Dict space):
  "position": MultiDiscrete([width, height]) - the robot's cell (x, y);
  "signals":  Box (5, M) float64 - s^j(x + u), the signal of source j at the cell each move u (E, W, Stay, N, S)
              leads to (a blocked move sees the robot's own cell): the features of the paper's policy (2)-(3);
  "step":     Discrete(K + 1) - moves made so far.
Action: Discrete(5), the moves E, W, Stay, N, S (riskplan.engine.world.MOVE_NAMES).
Reward: the reward of the cell entered (its region's draw, plus the source's draw on a source cell); an episode's
return is the kernel's total reward z. terminated: a source reached with world.stop_at_source; truncated: K moves.
info: "risky_steps" (so far), "source_reached" (index of the first source reached, -1 for none), "steps".
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

try:
    import gymnasium
    from gymnasium import spaces
except ImportError as err:  # pragma: no cover - the optional extra is missing
    raise ImportError(
        "riskplan.experiments.environments.SensorPlanningEnv needs Gymnasium: pip install 'riskplan[envs]'"
    ) from err

from riskplan.engine.world import MOVE_NAMES, World
from riskplan.experiments.environments.core import Worlds, env_setup, new_seed, signal_bounds

ENV_ID = "riskplan/SensorPlanning-v0"


def observation_space(world: World) -> spaces.Dict:
    """The observation space of one robot (see the module docstring)."""
    low, high = signal_bounds(world)
    shape = (len(MOVE_NAMES), world.sources)
    return spaces.Dict(
        {
            "position": spaces.MultiDiscrete([world.width, world.height]),
            "signals": spaces.Box(np.broadcast_to(low, shape), np.broadcast_to(high, shape), shape, dtype=np.float64),
            "step": spaces.Discrete(world.horizon + 1),
        }
    )


def observations(worlds: Worlds) -> list[dict[str, Any]]:
    """Each robot's observation."""
    positions, signals = worlds.positions(), worlds.signals()
    return [
        {"position": positions[b], "signals": signals[b], "step": np.int64(worlds.steps[b])}
        for b in range(worlds.robots)
    ]


def infos(worlds: Worlds) -> list[dict[str, int]]:
    """Each robot's info: risky steps so far, the first source reached (-1 for none), moves made."""
    return [
        {
            "risky_steps": int(worlds.risky_steps[b]),
            "source_reached": int(worlds.source_reached[b]),
            "steps": int(worlds.steps[b]),
        }
        for b in range(worlds.robots)
    ]


def render_ansi(worlds: Worlds) -> str:
    """The grid as text, north up: R robot, S source, # obstacle, ~ risky region, . anything else."""
    world = worlds.world
    risky = np.zeros(world.cells, dtype=bool)
    inside = world.region_of >= 0
    risky[inside] = world.region_risky[world.region_of[inside]]
    chars = np.where(world.obstacle, "#", np.where(risky, "~", ".")).astype("<U1")
    chars[np.unique(worlds.sources)] = "S"
    chars[worlds.cell] = "R"
    grid = chars.reshape(world.width, world.height).T[::-1]  # rows y = height-1 .. 0, columns x
    return "\n".join("".join(row) for row in grid) + "\n"


class SensorPlanningEnv(gymnasium.Env):
    """One robot in riskplan's world: the numba kernel's episode as a Gymnasium environment (module docstring)."""

    metadata: ClassVar[dict] = {"render_modes": ["ansi"], "render_fps": 4}

    def __init__(self, config: Any = None, *, robot: int = 0, render_mode: str | None = None):
        """`config`: riskplan overrides, a composed config or a RunSetup (riskplan.experiments.environments.make_setup); `robot`: whose
        start cell to use when team.starts gives several."""
        self.setup, starts = env_setup(config, render_mode, self.metadata["render_modes"])
        self.world = self.setup.world
        self.render_mode = render_mode
        if not 0 <= robot < len(starts):
            raise ValueError(f"robot {robot} is not one of the team's robots 0..{len(starts) - 1}")
        self._worlds = Worlds(self.world, starts[robot : robot + 1])
        self._started = False  # step() before reset() is refused, as gymnasium's OrderEnforcing does
        self.observation_space = observation_space(self.world)
        self.action_space = spaces.Discrete(len(MOVE_NAMES))

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._worlds.reset(new_seed(self.np_random))
        self._started = True
        return observations(self._worlds)[0], infos(self._worlds)[0]

    def step(self, action):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        if self._worlds.done[0]:
            raise RuntimeError("the episode has ended; call reset()")
        if isinstance(action, (bool, np.bool_)) or not self.action_space.contains(action):
            raise ValueError(f"action {action!r} is not one of 0..4 ({', '.join(MOVE_NAMES)})")
        reward, terminated, truncated = self._worlds.step(np.array([int(action)]))
        obs, info = observations(self._worlds)[0], infos(self._worlds)[0]
        return obs, float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        if self.render_mode == "ansi":
            return render_ansi(self._worlds)
        return None


gymnasium.register(id=ENV_ID, entry_point="riskplan.experiments.environments.gym:SensorPlanningEnv")
