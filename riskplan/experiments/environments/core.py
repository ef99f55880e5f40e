"""riskplan's world for the Gymnasium and PettingZoo environments: many robots stepped at once, by the engine's kernel.

`Worlds.step` runs riskplan.engine.dynamics.step_robots, the episode kernel's own step once a move is chosen
(its `_entered`, `_draw` and `_walk`), on the tables the training kernel takes (riskplan.engine.rollout.make_kernel):
  * a move is one of E, W, Stay, N, S (riskplan.engine.world.MOVES, in that order); a blocked move stays;
  * the cell entered at each step 1..K is paid its region's reward (first matching region; no region pays 0;
    the start cell is not paid); a risky region counts a risky step;
  * entering a source's cell also pays the source's reward (the first source listed on that cell); with
    world.stop_at_source the robot's episode then ends (terminated);
  * mobile sources (random_walk) move after the robots' moves have been paid, to a uniform E/W/N/S neighbour with
    probability `prob`, staying put at the grid's edge;
  * after K moves the episode ends (truncated).
Draws come from the kernel's counter-based streams (riskplan.engine.rng): each robot its own, each copy's sources
theirs, keyed by the seed `reset` takes. The moves are the agent's, so the episodes are not the kernel's; their
distribution is (tests/experiments/test_environments.py checks it against `riskplan.engine.rollout.simulate`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from omegaconf import DictConfig

from riskplan.config.hydra_safety import check_resolvers
from riskplan.engine.dynamics import step_robots
from riskplan.engine.policy import Policy, move_features, probabilities, tabular_probabilities
from riskplan.engine.rng import ENVIRONMENT, SEED_LIMIT, episode_states, stream_key
from riskplan.engine.rollout import make_kernel
from riskplan.engine.step import RunSetup
from riskplan.engine.world import MOVE_NAMES, World
from riskplan.run.build import build_setup
from riskplan.run.compose import compose
from riskplan.util.errors import BadInput


def make_setup(config: Any = None) -> RunSetup:
    """A riskplan RunSetup from a config: None (the defaults), Hydra overrides (a list like ["world.horizon=10",
    "experiment=paper_team"], or one such string), a composed config or dict, or a RunSetup (used as it is)."""
    if isinstance(config, RunSetup):
        return config
    if config is None:
        config = []
    if isinstance(config, str):
        config = [config]
    if isinstance(config, Sequence):
        return build_setup(compose(list(config), validate=False))
    if not isinstance(config, (Mapping, DictConfig)):
        raise BadInput("config", f"got {config!r}; give overrides (a list of key=value), a config or a RunSetup")
    check_resolvers(config)  # as an override of such a value is refused
    return build_setup(config)


def env_setup(config: Any, render_mode: str | None, modes: list[str]) -> tuple[RunSetup, np.ndarray]:
    """What both environments build first: the render mode checked, the RunSetup, every robot's start cell."""
    if render_mode is not None and render_mode not in modes:
        raise ValueError(f"render_mode {render_mode!r} is not one of {modes}")
    setup = make_setup(config)
    return setup, robot_starts(setup)


def robot_starts(setup: RunSetup) -> np.ndarray:
    """Start cell of each of the team's robots (all at world.start unless team.starts is given)."""
    cells = setup.world.starts
    return np.repeat(cells, setup.robots) if len(cells) == 1 else cells.copy()


def new_seed(generator: np.random.Generator) -> int:
    """A seed for `Worlds.reset` from a numpy generator (an environment's `np_random`): reproducible from its seed."""
    return int(generator.integers(SEED_LIMIT))


def signal_bounds(world: World) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest value of each source's signal (M,): between 0 and its peak (negative for scale < 0)."""
    return np.minimum(world.source_amplitude, 0.0), np.maximum(world.source_amplitude, 0.0)


class Worlds:
    """`len(starts)` robots in `groups` copies of one world, stepped together.

    Robot b lives in copy group[b] (default: each robot its own copy). Robots of one copy share its sources, which
    matters only for mobile sources: they walk once per time step, independently in each copy. Robots never block
    or pay each other, and every reward draw is independent. A robot whose episode has ended stays where it is and
    is paid nothing; each copy's sources walk while any of its robots is still moving. `seed`: the streams'
    (`reset(seed)` starts new ones).
    """

    def __init__(self, world: World, starts: np.ndarray, group: np.ndarray | None = None, seed: int = 0):
        self.world = world
        self.starts = start_cells(world, starts, "starts")
        self.group = np.arange(len(self.starts)) if group is None else np.asarray(group, dtype=np.int64)
        if self.group.shape != self.starts.shape or (len(self.group) and self.group.min() < 0):
            raise ValueError("group must give a copy index >= 0 for every robot")
        self.groups = int(self.group.max()) + 1 if len(self.group) else 0
        self._mobile = world.mobile
        self._features = None if self._mobile else move_features(world)  # (C, 5, M) for static sources
        self._tables = make_kernel(world).tables
        self.reset(seed)

    @property
    def robots(self) -> int:
        """Number of robots B."""
        return len(self.starts)

    def reset(self, seed: int | None = None) -> None:
        """Every robot back at its start, every source at its initial cell, nothing paid; with `seed` (a whole number
        0 <= seed < 2^63), new streams: robot b's is episode b of the key (seed, ENVIRONMENT), copy g's sources' is
        episode B + g. Without, the episodes go on drawing from the streams they had."""
        b = self.robots
        if seed is not None:
            if isinstance(seed, (bool, np.bool_)) or not (
                isinstance(seed, (int, np.integer)) and 0 <= seed < SEED_LIMIT
            ):
                raise BadInput(
                    "seed", f"got {seed!r}; give a whole number 0 <= seed < 2^63 (or None: the streams go on)"
                )
            states = episode_states(np.uint64(stream_key(int(seed), ENVIRONMENT)), b + self.groups)
            self._states, self._walk_states = states[:b], states[b:]
        self.cell = self.starts.copy()
        self.sources = np.tile(self.world.source_cells, (self.groups, 1))  # (G, M) current source cells
        self.steps = np.zeros(b, dtype=np.int64)
        self.done = np.zeros(b, dtype=bool)
        self.risky_steps = np.zeros(b, dtype=np.int64)
        self.source_reached = np.full(b, -1, dtype=np.int64)
        self.total_reward = np.zeros(b)

    def signals(self) -> np.ndarray:
        """The policy's features s^j(x + u) for every robot and move, shape (B, 5, M): what each robot senses."""
        if self._features is not None:
            return self._features[self.cell]
        world = self.world
        nx, ny = np.divmod(world.next_cell[self.cell], world.height)  # (B, 5)
        sx, sy = np.divmod(self.sources[self.group], world.height)  # (B, M)
        dx = (nx[:, :, None] - sx[:, None, :]).astype(float)
        dy = (ny[:, :, None] - sy[:, None, :]).astype(float)
        p = world.source_precision
        quad = p[:, 0] * dx * dx + 2.0 * p[:, 1] * dx * dy + p[:, 2] * dy * dy
        return world.source_amplitude * np.exp(-0.5 * quad)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Move every robot still in its episode by its action (0..4 = E, W, Stay, N, S; ignored for the others).

        Returns (reward, terminated, truncated), each of shape (B,); the flags are set only on the step that
        ends a robot's episode.
        """
        actions = np.asarray(actions).reshape(-1)
        if actions.shape != self.starts.shape:
            raise ValueError(f"expected {self.robots} actions, got {actions.shape[0]}")
        active = ~self.done
        moves = actions[active]
        if moves.dtype.kind not in "iu" or ((moves < 0) | (moves >= len(MOVE_NAMES))).any():
            raise ValueError(f"actions must be whole numbers 0..4 ({', '.join(MOVE_NAMES)}); got {moves.tolist()}")
        reward, risky, hit = np.empty(self.robots), np.empty(self.robots, dtype=np.int64), np.empty_like(self.cell)
        step_robots(
            self._tables,
            self.cell,
            np.where(active, actions, 0).astype(np.int64),
            active,
            self.group,
            self.sources,
            self._states,
            self._walk_states,
            reward,
            risky,
            hit,
        )
        self.steps[active] += 1
        self.risky_steps += risky
        self.source_reached = np.where((self.source_reached < 0) & (hit >= 0), hit, self.source_reached)
        terminated = (hit >= 0) & self.world.stop_at_source
        truncated = active & ~terminated & (self.steps >= self.world.horizon)
        self.done |= terminated | truncated
        self.total_reward += reward
        return reward, terminated, truncated

    def positions(self) -> np.ndarray:
        """Each robot's cell as (x, y), shape (B, 2)."""
        out = np.empty((len(self.cell), 2), dtype=np.int64)
        out[:, 0], out[:, 1] = np.divmod(self.cell, self.world.height)
        return out


def start_cells(world: World, starts, key: str) -> np.ndarray:
    """Start cells as the kernel takes them (B,): whole numbers 0..C-1, none an obstacle; BadInput naming `key`
    otherwise (the kernel would read past its tables: a crash, not an error)."""
    cells = np.asarray(starts)
    if cells.dtype.kind not in "iu":
        raise BadInput(key, f"got {starts!r}; give cell indices, whole numbers 0..{world.cells - 1}")
    cells = cells.astype(np.int64).reshape(-1)
    off = cells[(cells < 0) | (cells >= world.cells)]
    if len(off):
        raise BadInput(
            key, f"cell {int(off[0])} is off the grid; give cell indices 0..{world.cells - 1} (x * height + y)"
        )
    blocked = cells[world.obstacle[cells]]
    if len(blocked):
        x, y = world.xy(int(blocked[0]))
        raise BadInput(key, f"cell {int(blocked[0])} ({int(x)}, {int(y)}) is an obstacle; start on a free cell")
    return cells


OVERFLOW = "the softmax logits theta . f(x, u) overflow to infinity"  # probabilities would be NaN


class SoftmaxPolicy:
    """The softmax policy (2)-(3) on the environments' observations: mu(u | x) ∝ exp(theta . f(x, u)).

    `SoftmaxPolicy(theta)` is the paper's policy: f is the observation's "signals", a (5, M) array (or a batch
    (B, 5, M)). `SoftmaxPolicy(theta, config)` is the policy a riskplan config (overrides, a composed config or a
    RunSetup, as `make_setup` takes) trains, theta as long as its RunSetup.theta_names:
      * policy.features with risky or stay: the signals and those features of x + u, in the order of
        policy.features; the extras are looked up from the observation's "position" (x, y);
      * policy.kind=tabular: theta is the (C * 5,) table of logits, theta[c * 5 + a] for the cell c at "position"
        (the signals are not used).
    `act` samples a move as the kernel does (the first move whose cumulative probability exceeds a uniform draw).
    """

    def __init__(self, theta: Sequence[float] | np.ndarray, config: Any = None):
        self.theta = np.asarray(theta, dtype=float).reshape(-1)
        if not (self.theta.size and np.all(np.isfinite(self.theta))):
            raise ValueError(f"theta must be one or more finite numbers, got {theta!r}")
        self._setup = None if config is None else make_setup(config)
        self._policy: Policy | None = None if self._setup is None else self._setup.policy
        self._table: np.ndarray | None = None
        policy = self._policy
        if policy is None:
            return
        if self.theta.shape != (policy.size,):
            shown = ", ".join(policy.names) if policy.size <= 8 else f"{', '.join(policy.names[:8])}, ..."
            raise ValueError(
                f"theta has {self.theta.size} entries; the config's {policy.kind} policy has {policy.size} ({shown})"
            )
        if not np.isfinite(policy.logit_bound(self.theta[None])):
            raise BadInput("theta", f"{OVERFLOW}; give a smaller theta (training refuses this one too)")
        if policy.tabular:
            self._table = tabular_probabilities(self.theta, self._setup.world.cells)  # (C, 5)
        elif policy.features == ("signals",):
            self._policy = None  # the paper's policy: the signals alone, no position needed

    @property
    def needs_position(self) -> bool:
        """Whether the policy looks at the observation's "position" (extra features or a table), not only signals."""
        return self._policy is not None

    def features(self, signals: np.ndarray, position: np.ndarray | None = None) -> np.ndarray:
        """f(x, u) of each move in theta's order, (5, F) for one observation, (B, 5, F) for a batch."""
        signals = np.asarray(signals, dtype=float)
        policy = self._policy
        if policy is None:
            return signals
        if policy.tabular:
            raise ValueError("a tabular policy has no features: its theta is the table of (cell, move) logits")
        one = signals.ndim == 2
        cells = self._cells(position, 1 if one else len(signals))
        batch = signals[None] if one else signals
        out = np.empty(batch.shape[:2] + (policy.size,))
        if policy.signal_at >= 0:
            out[..., policy.signal_at : policy.signal_at + batch.shape[-1]] = batch
        out[..., policy.extra_at] = policy.extras[cells]
        return out[0] if one else out

    def probabilities(self, signals: np.ndarray, position: np.ndarray | None = None) -> np.ndarray:
        """Move probabilities, shape (5,) for one observation, (B, 5) for a batch. `position` (x, y) or (B, 2):
        needed by a policy with extra features or a table (`needs_position`)."""
        signals = np.asarray(signals, dtype=float)
        one = signals.ndim == 2
        if self._table is not None:
            probs = self._table[self._cells(position, 1 if one else len(signals))]
        else:
            feats = self.features(signals, position)
            if feats.shape[-1] != self.theta.size:
                raise ValueError(
                    f"theta has {self.theta.size} entries; the observation gives {feats.shape[-1]} features"
                )
            with np.errstate(over="ignore", invalid="ignore"):  # said just below, in one line
                probs = probabilities(feats[None] if one else feats, self.theta)
            if not np.isfinite(probs).all():  # the paper's policy: its bound needs the observation
                raise BadInput("theta", f"{OVERFLOW} at this observation; give a smaller theta")
        return probs[0] if one else probs

    def act(
        self, signals: np.ndarray, rng: np.random.Generator, position: np.ndarray | None = None
    ) -> np.ndarray | int:
        """A sampled move (int) for one observation, or moves (B,) for a batch (see `probabilities`)."""
        probs = self.probabilities(signals, position)
        cum = np.cumsum(np.atleast_2d(probs), axis=-1)
        u = rng.random(cum.shape[0])
        moves = (u[:, None] > cum[:, :4]).sum(axis=1)
        return int(moves[0]) if probs.ndim == 1 else moves

    def __call__(self, observation: dict, rng: np.random.Generator) -> int:
        """A move for one environment observation (a dict with "signals" and "position")."""
        return self.act(observation["signals"], rng, observation.get("position"))

    def _cells(self, position: np.ndarray | None, count: int) -> np.ndarray:
        """Cell indices (count,) of positions (x, y) or (B, 2)."""
        if position is None:
            raise ValueError(
                f"this {self._policy.kind} policy (features {list(self._policy.features)}) looks up the robot's cell: "
                f'pass position (the observation\'s "position")'
            )
        xy = np.asarray(position, dtype=np.int64).reshape(-1, 2)
        if len(xy) != count:
            raise ValueError(f"got {len(xy)} positions for {count} observations")
        world = self._setup.world
        if ((xy < 0) | (xy >= (world.width, world.height))).any():
            raise ValueError(f"positions off the {world.width}x{world.height} grid: {xy.tolist()}")
        return xy[:, 0] * world.height + xy[:, 1]


@dataclass(frozen=True)
class Episodes:
    """Outcomes of independent episodes, as riskplan.engine.rollout.EpisodeBatch names them."""

    total_reward: np.ndarray  # (E,) float64
    risky_steps: np.ndarray  # (E,) int64
    source_reached: np.ndarray  # (E,) int64, -1 for none
    steps: np.ndarray  # (E,) int64


def run_episodes(
    config: Any, theta: Sequence[float] | np.ndarray, episodes: int, rng: np.random.Generator, start: int | None = None
) -> Episodes:
    """`episodes` independent single-robot episodes of the softmax policy theta, all stepped at once in numpy.

    The same dynamics as the environments (each episode its own copy of the world), without their per-step Python
    overhead. theta is the config's policy's (`SoftmaxPolicy(theta, config)`: the paper's, extra features or a
    table). `start`: the start cell (default: the first robot's).
    """
    setup = make_setup(config)
    cell = robot_starts(setup)[:1] if start is None else start_cells(setup.world, start, "start")
    if len(cell) != 1:
        raise BadInput("start", f"got {start!r}; give one start cell (an index 0..{setup.world.cells - 1})")
    worlds = Worlds(setup.world, np.full(episodes, cell[0], dtype=np.int64), seed=new_seed(rng))
    policy = SoftmaxPolicy(theta, setup)
    while not worlds.done.all():
        position = worlds.positions() if policy.needs_position else None
        worlds.step(policy.act(worlds.signals(), rng, position))
    return Episodes(worlds.total_reward, worlds.risky_steps, worlds.source_reached, worlds.steps)
