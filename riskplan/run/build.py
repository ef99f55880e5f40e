"""Everything a run derives from its config, built (and so validated) once at the top: the PureJaxRL way."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from omegaconf import DictConfig

from riskplan.config.schema import RiskConf, RiskplanConf, StepSizeConf, TrainConf
from riskplan.config.typed import as_dict, typed
from riskplan.engine.rng import SEED_LIMIT
from riskplan.engine.rollout import Kernel, make_kernel
from riskplan.engine.team.consensus import Mixer, Network, build_network, check_settings
from riskplan.engine.world import World, build_world, grid_size
from riskplan.run import budget
from riskplan.util.checks import require

MEASURES = ("cvar", "neutral")
ORDERS = ("combine_then_adapt", "adapt_then_combine", "gradient_tracking")
SCHEDULES = ("none", "linear", "exponential")  # risk.schedule.kind


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
    """Validate every key and build the run's objects; raises BadInput on the first problem."""
    cfg = typed(cfg)  # types, unknown keys, interpolations: the frozen config everything below reads
    risk, train, team = cfg.risk, cfg.train, cfg.team
    require(
        risk.measure in MEASURES,
        "risk.measure",
        f"got '{risk.measure}'; expected one of {', '.join(MEASURES)} (risk=cvar or risk=neutral)",
    )
    require(0.0 < risk.beta <= 1.0, "risk.beta", f"got {risk.beta}; expected 0 < beta <= 1")
    check_schedule(risk)
    require(train.iterations >= 1, "train.iterations", f"got {train.iterations}; expected a whole number >= 1")
    require(train.samples >= 1, "train.samples", f"got {train.samples}; expected W >= 1")
    require(
        math.isfinite(train.samples_growth) and train.samples_growth >= 0,
        "train.samples_growth",
        f"got {train.samples_growth}; expected a finite exponent >= 0",
    )
    sched = train.step_size
    require(
        math.isfinite(sched.initial) and sched.initial >= 0,
        "train.step_size.initial",
        f"got {sched.initial}; expected a finite step >= 0",
    )
    require(math.isfinite(sched.decay) and sched.decay > 0, "train.step_size.decay", f"got {sched.decay}; expected > 0")
    require(
        math.isfinite(sched.power) and sched.power >= 0, "train.step_size.power", f"got {sched.power}; expected >= 0"
    )
    if not 0.5 < sched.power <= 1.0:
        warnings.warn(f"train.step_size.power={sched.power} breaks Assumption 6 (needs 0.5 < power <= 1)", stacklevel=2)
    require(train.eval_episodes >= 1, "train.eval_episodes", f"got {train.eval_episodes}; expected >= 1")
    require(train.paths >= 0, "train.paths", f"got {train.paths}; expected >= 0")
    require(train.checkpoint_every >= 1, "train.checkpoint_every", f"got {train.checkpoint_every}; expected >= 1")
    require(train.bootstrap >= 1, "train.bootstrap", f"got {train.bootstrap}; expected >= 1 resamples")
    seed = cfg.seed if abs(cfg.seed) < 10**30 else budget.show(cfg.seed)
    require(
        0 <= cfg.seed < SEED_LIMIT,
        "seed",
        f"got {seed}; expected a whole number 0 <= seed < 2^63 "
        f"(9223372036854775808); seeds are not reduced modulo 2^64",
    )

    # Sizes first, on the raw config: nothing big is allocated before the memory and time estimates pass.
    settings = check_settings(team)
    width, height = grid_size(cfg.world.size)
    budget.check(budget.sizes_of(cfg, width, height, len(cfg.world.sources), settings.robots))

    require(team.order in ORDERS, "team.order", f"got '{team.order}'; expected one of {', '.join(ORDERS)}")
    starts = None
    if team.starts is not None:
        starts = [list(s) for s in team.starts]
        require(
            len(starts) == team.robots,
            "team.starts",
            f"gives {len(starts)} start cell{'' if len(starts) == 1 else 's'} for {team.robots} robots; give one [x, y] per robot or null",
        )
    world = build_world(cfg.world, starts)
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
    network = build_network(team, world.sources, int(cfg.seed))
    budget.check(budget.sizes_of(cfg, world.width, world.height, world.sources, network.robots))  # before the Mixer
    return Setup(
        params=cfg,
        config=as_dict(cfg),
        world=world,
        kernel=make_kernel(world),
        network=network,
        mixer=Mixer(network, team, int(cfg.seed)),
        theta0=theta0,
    )


def logit_bound(world: World, thetas: np.ndarray) -> float:
    """Largest |logit| any policy in `thetas` (..., M) can produce: sum_j |theta_j| x peak |signal_j|.

    When it is finite, no logit (or partial sum of one) overflows, so the softmax stays finite.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        return float(np.max(np.abs(np.asarray(thetas, dtype=float)) @ np.abs(world.source_amplitude)))


def step_size(iteration: int, schedule: StepSizeConf) -> float:
    """eps_l = initial / (1 + l / decay)^power (0 once the denominator overflows a float)."""
    try:
        return schedule.initial / (1.0 + iteration / schedule.decay) ** schedule.power
    except OverflowError:  # (1 + l/decay)^power beyond 1.8e308: the step is 0 to double precision
        return 0.0


def check_schedule(risk: RiskConf) -> None:
    """The soft-risk schedule's keys (checked whatever the kind, so a bad value never waits for kind to change)."""
    plan = risk.schedule
    require(plan.kind in SCHEDULES, "risk.schedule.kind", f"got '{plan.kind}'; expected one of {', '.join(SCHEDULES)}")
    require(
        math.isfinite(plan.start) and 0.0 < plan.start <= 1.0,
        "risk.schedule.start",
        f"got {plan.start}; expected 0 < start <= 1",
    )
    require(
        plan.start >= risk.beta,
        "risk.schedule.start",
        f"got {plan.start}, below risk.beta={risk.beta}; the schedule goes from start down to beta, so "
        f"expected beta <= start <= 1",
    )
    require(
        plan.iterations >= 1,
        "risk.schedule.iterations",
        f"got {plan.iterations}; expected a whole number of iterations >= 1",
    )


def risk_level(iteration: int, risk: RiskConf) -> float:
    """beta_l, the CVaR level of iteration l's gradient (soft risk, CeSoR): risk.beta with kind=none; otherwise
    from start at l = 0 to risk.beta at l = schedule.iterations, linearly or geometrically, then risk.beta."""
    plan, beta = risk.schedule, risk.beta
    if plan.kind == "none" or iteration >= plan.iterations:
        return beta
    if iteration <= 0:
        return plan.start
    fraction = iteration / plan.iterations
    if plan.kind == "linear":
        return plan.start + (beta - plan.start) * fraction
    return plan.start * (beta / plan.start) ** fraction  # exponential: log beta_l linear in l


def samples_at(iteration: int, train: TrainConf) -> int:
    """W_l = ceil(samples * (1 + l)^samples_growth)."""
    return math.ceil(train.samples * (1.0 + iteration) ** train.samples_growth)
