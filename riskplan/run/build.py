"""Everything a run derives from its config, built (and so validated) once at the top: the PureJaxRL way."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from omegaconf import DictConfig

from riskplan.config.schema import RiskplanConf
from riskplan.config.typed import as_dict, typed
from riskplan.config.validate import validate
from riskplan.engine.rollout import Kernel, make_kernel
from riskplan.engine.team.mixer import Mixer
from riskplan.engine.team.network import Network, build_network
from riskplan.engine.world import World, build_world, grid_size
from riskplan.run import budget
from riskplan.util.checks import require


@dataclass(frozen=True)
class Setup:
    """A validated experiment: its frozen config, world, kernel arrays, team network."""

    params: RiskplanConf  # what the engine and the training loop read
    config: dict  # the same as plain data, for the records (.hydra/config.yaml, run.mcap metadata)
    world: World
    kernel: Kernel
    network: Network
    mixer: Mixer
    theta0: np.ndarray  # (M,)

    @property
    def robots(self) -> int:
        """Team size N."""
        return self.network.robots

    @property
    def team(self) -> bool:
        """Whether this is a distributed run (N > 1)."""
        return self.network.robots > 1


def build_setup(cfg: DictConfig | dict | RiskplanConf) -> Setup:
    """Type and validate the config once, then build the run's objects; raises BadInput on the first problem."""
    params = typed(cfg)  # types, unknown keys, Choices, interpolations: the frozen config everything below reads
    validate(params)  # every range, once
    # Sizes first: nothing big is allocated before the memory and time estimates pass.
    width, height = grid_size(params.world.size)
    budget.check(budget.sizes_of(params, width, height, len(params.world.sources), params.team.robots))
    starts = None if params.team.starts is None else [list(s) for s in params.team.starts]
    world = build_world(params.world, starts)
    train = params.train
    theta0 = np.array(list(train.theta0), dtype=float)
    require(
        theta0.shape == (world.sources,) and bool(np.all(np.isfinite(theta0))),
        "train.theta0",
        f"got {list(train.theta0)}; expected {world.sources} finite numbers, one per source",
    )
    require(
        math.isfinite(logit_bound(world, theta0)),
        "train.theta0",
        f"got {list(train.theta0)}; the softmax logits theta . signal overflow to infinity; give smaller values",
    )
    network = build_network(params.team, world.sources, params.seed)
    budget.check(budget.sizes_of(params, world.width, world.height, world.sources, network.robots))  # before the Mixer
    return Setup(
        params=params,
        config=as_dict(params),
        world=world,
        kernel=make_kernel(world),
        network=network,
        mixer=Mixer(network, params.team, params.seed),
        theta0=theta0,
    )


def logit_bound(world: World, thetas: np.ndarray) -> float:
    """Largest |logit| any policy in `thetas` (..., M) can produce: sum_j |theta_j| x peak |signal_j|.

    When it is finite, no logit (or partial sum of one) overflows, so the softmax stays finite.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        return float(np.max(np.abs(np.asarray(thetas, dtype=float)) @ np.abs(world.source_amplitude)))


def starts(setup: Setup) -> np.ndarray:
    """Start cell of each robot (all at world.start unless team.starts is given)."""
    cells = setup.world.starts
    return np.repeat(cells, setup.robots) if len(cells) == 1 else cells
