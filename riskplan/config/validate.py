"""The ranges of a typed config, checked once per build: every value the schema's types and Choices cannot rule out.

Types, unknown keys and the Choices (Enums) are the schema's (`riskplan.config.typed`); what needs the world's
geometry (a cell on the grid, a reachable source, a positive-definite covariance) or the graph (connectivity, the
weights of Assumption 5) is checked by the engine when it builds those, once. Everything else is here.
"""

from __future__ import annotations

import dataclasses
import math
import unicodedata
import warnings

from riskplan.config.backends import BACKENDS, DEVICES
from riskplan.config.faults import Fault, faults_of
from riskplan.config.hydra_safety import PLAIN_NAME
from riskplan.config.keys import KEYS, Key
from riskplan.config.schema import (
    NO_SOURCE,
    Aggregate,
    Backend,
    Feature,
    Graph,
    MotionKind,
    Order,
    PolicyConf,
    PolicyKind,
    RiskConf,
    RiskplanConf,
    TeamConf,
    TrainConf,
    WeightRule,
    WorldConf,
    source_names,
)
from riskplan.config.typed import check_flat_lists, shown
from riskplan.util.checks import finite, integer_at_least, require, require_installed

SEED_LIMIT = 1 << 63  # seeds are whole numbers 0 <= seed < 2^63: none alias under the 64-bit stream keys
NAME_LENGTH = 64  # characters of a name: the experiment's (a folder's), a source's or region's (a metric's)
HIDDEN = ("Cc", "Cf", "Zl", "Zp", "Cs")  # Unicode categories a name may not hold: controls, format marks, breaks
MIN_RESAMPLES = 40  # bootstrap resamples for a 95% percentile interval: 2.5% of them is at least one
BYZANTINE_LIMIT = 1e100  # largest |value| and scale a byzantine robot sends (team.faults): squares stay finite
MIN_BETA = 1e-9  # below it CVaR's tail, ceil(beta W) of W episodes, is one (a zero gradient) unless W > 10^9 (80 GB)

# The values that need an optional extra: (key, value) -> (the module that provides it, what it is, the extra, a
# note). A missing one is bad input (MissingExtra) in check, train and sweep, before anything is written.
EXTRAS = {
    **{
        (key, spec.name.value): (spec.needs.module, spec.needs.what, spec.needs.extra, spec.needs.note)
        for key, specs in ((KEYS.team.backend, BACKENDS), (KEYS.engine.device, DEVICES))
        for spec in specs.values()
        if spec.needs is not None
    },  # a GPU too for engine.device=cuda: riskplan.run.build checks it
    **{
        ("hydra/launcher", name): ("hydra_plugins.hydra_submitit_launcher", "Hydra's Submitit launcher", "slurm", "")
        for name in ("submitit_slurm", "submitit_local")
    },
    **{
        ("hydra/launcher", name): (
            "hydra_plugins.hydra_ray_launcher",
            "Hydra's Ray launcher",
            "ray",
            "(in an environment of its own: it pins cloudpickle<3)",
        )
        for name in ("ray", "ray_cluster")
    },
    ("hydra/sweeper", "optuna"): ("hydra_plugins.hydra_optuna_sweeper", "Hydra's Optuna sweeper", "optuna", ""),
}


def check_extra(key: str, value: object) -> None:
    """MissingExtra naming `key=value` when the value needs an optional extra (EXTRAS) that is not installed."""
    needed = EXTRAS.get((key, str(value)))
    if needed is not None:
        module, what, extra, note = needed
        require_installed(module, f"{key}={value}", what, extra, note)


def validate(params: RiskplanConf, needs_ray: bool = True) -> None:
    """BadInput naming the first key outside its range; a warning where only a theorem's assumption breaks; and
    MissingExtra for a value whose optional package is not installed, before the run: not a failed run directory.
    `needs_ray=False`: a resumed Ray run, which needs Ray only if a robot has iterations left (run.ray_team)."""
    check_flat_lists(params)
    check_name(params.experiment, KEYS.experiment, "the run directory's name")
    check_risk(params.risk)
    check_policy(params.policy)
    check_train(params.train)
    check_world(params.world)
    check_team(params.team)
    if needs_ray:
        check_extra(KEYS.team.backend, params.team.backend)
    check_extra(KEYS.engine.device, params.engine.device)
    warn_unused(params)
    seed = params.seed if abs(params.seed) < 10**30 else f"about 2^{params.seed.bit_length()}"
    require(
        0 <= params.seed < SEED_LIMIT,
        KEYS.seed,
        f"got {seed}; expected a whole number 0 <= seed < 2^63 (9223372036854775808); seeds are not reduced "
        f"modulo 2^64",
    )


# A key only some variants use: (the node that holds it, the key, the key choosing the variant, the variants that use
# it). Set away from its default under another variant, it is ignored: a warning says so (warn_unused).
VARIANT_KEYS = (
    ("team", "edges", "graph", (Graph.edges,)),
    ("team", "matrix", "weights", (WeightRule.matrix,)),
    ("team", "trim", "aggregate", (Aggregate.trimmed_mean, Aggregate.wmsr)),  # median takes no F
    ("team", "speeds", "backend", (Backend.ray,)),
    ("team", "address", "backend", (Backend.ray,)),
    ("world.sources.*.motion", "prob", "kind", (MotionKind.random_walk,)),
)


class IgnoredKey(UserWarning):
    """A key set where the chosen variant ignores it; `chooser` is the key that chose the variant. A sweep over the
    chooser sets the key for the variants that use it (team.aggregate=mean,trimmed_mean team.trim=1): no warning."""

    def __init__(self, message: str, chooser: str) -> None:
        super().__init__(message)
        self.chooser = chooser


def warn_unused(params: RiskplanConf) -> None:
    """One warning per key of VARIANT_KEYS set (not its default) where the chosen variant ignores it."""
    for where, key, chooser, users in VARIANT_KEYS:
        for path, node in _nodes(params, where.split(".")):
            value, default = getattr(node, key), _default(type(node), key)
            if value != default and getattr(node, chooser) not in users:
                message = (
                    f"{path}.{key}={shown(value)} is ignored with {path}.{chooser}={getattr(node, chooser)}: only "
                    f"{path}.{chooser}={' or '.join(str(u) for u in users)} uses it; drop it"
                )
                warnings.warn(IgnoredKey(message, f"{path}.{chooser}"), stacklevel=3)


def _nodes(node: object, parts: list[str], path: str = "") -> list[tuple[str, object]]:
    """The config nodes at a dotted path, with their paths; `*` stands for every item of a list."""
    if not parts:
        return [(path, node)]
    head, rest = parts[0], parts[1:]
    if head == "*":
        return [found for i, item in enumerate(node) for found in _nodes(item, rest, f"{path}.{i}")]
    return _nodes(getattr(node, head), rest, f"{path}.{head}" if path else head)


def _default(kind: type, key: str) -> object:
    """A schema field's default value."""
    spec = next(f for f in dataclasses.fields(kind) if f.name == key)
    return spec.default_factory() if spec.default is dataclasses.MISSING else spec.default


def check_name(value: str, key: Key, meaning: str) -> None:
    """A name that becomes part of a path: a plain name of at most NAME_LENGTH characters, never path syntax."""
    require(
        PLAIN_NAME.fullmatch(value) is not None and len(value) <= NAME_LENGTH,
        key,
        f"got {value!r}; it is {meaning}: give a plain name of at most {NAME_LENGTH} letters, digits, '.', '_' and "
        f"'-', e.g. paper_single",
    )


def check_source_names(names: list[str]) -> None:
    """Each source's name is its own, and not 'none': the results count the episodes that reach each source by its
    name, and those that reach none as 'none', so a shared name would merge two counts into one."""
    for j, name in enumerate(names):
        key = KEYS.world.sources.at(j).name
        require(
            name != NO_SOURCE,
            key,
            f"got '{NO_SOURCE}', the name the results give the episodes that reach no source; give another name",
        )
        first = names.index(name)
        require(
            first == j,
            key,
            f"'{name}' is also the name of world.sources.{first}; the results count each source's episodes by its "
            f"name: give each source its own",
        )


def check_label(value: str, key: Key) -> None:
    """A source's or region's name: text that reaches figures, tables, logs and trackers' metric names, so at most
    NAME_LENGTH characters, none that would break a line, a CSV row or an SVG (control and format characters), and
    not whitespace alone (an empty name is the default, source_<j> or region_<r>)."""
    hidden = next((c for c in value if unicodedata.category(c) in HIDDEN), None)
    require(
        hidden is None,
        key,
        f"holds the character {hidden!r}; give a name of printable characters (line breaks, tabs and control "
        f"characters would break the logs, tables and figures it appears in)",
    )
    require(len(value) <= NAME_LENGTH, key, f"is {len(value)} characters long; give a name of at most {NAME_LENGTH}")
    require(
        not value.isspace(),
        key,
        f"got {value!r}, only whitespace, which names nothing a reader can see; give a name, or leave it empty for "
        f"the default name",
    )


def check_risk(risk: RiskConf, key: Key = KEYS.risk) -> None:
    """beta, eta, weight and the soft-risk schedule, whatever the measure (so a bad value never waits for the
    measure or the schedule's kind to change; a sweep over measures keeps one schedule, which moves the CVaR level
    of cvar and mean_cvar and leaves the others alone). `key` names the node: risk, or team.risk.<i>."""
    require(0.0 < risk.beta <= 1.0, key.beta, f"got {risk.beta}; expected 0 < beta <= 1")
    require(
        risk.beta >= MIN_BETA,
        key.beta,
        f"got {risk.beta:g}; expected {MIN_BETA:g} <= beta <= 1: CVaR's tail holds ceil(beta x W) of an iteration's "
        f"W episodes, which below {MIN_BETA:g} is one (a zero gradient) unless W is over 10^9",
    )
    require(
        math.isfinite(risk.eta) and risk.eta > 0,
        key.eta,
        f"got {risk.eta}; expected a finite eta > 0 (wang: the distortion's shift in standard deviations; "
        f"entropic: the aversion per unit of reward)",
    )
    require(0.0 <= risk.weight <= 1.0, key.weight, f"got {risk.weight}; expected a weight in [0, 1]")
    plan = risk.schedule
    require(
        math.isfinite(plan.start) and 0.0 < plan.start <= 1.0,
        key.schedule.start,
        f"got {plan.start}; expected 0 < start <= 1",
    )
    require(
        plan.start >= risk.beta,
        key.schedule.start,
        f"got {plan.start}, below {key.beta}={risk.beta}; the schedule goes from start down to beta, so "
        f"expected beta <= start <= 1",
    )
    require(
        plan.iterations >= 1,
        key.schedule.iterations,
        f"got {plan.iterations}; expected a whole number of iterations >= 1",
    )


def check_policy(policy: PolicyConf) -> None:
    """A features policy sees at least one feature, each once; a tabular policy has no features to choose."""
    names = [str(f) for f in policy.features]
    if policy.kind == PolicyKind.tabular:
        require(
            names == [Feature.signals.value],
            KEYS.policy.features,
            f"got {names}; a tabular policy has no features (its theta is the table of (cell, move) logits): drop "
            f"{KEYS.policy.features}, or use {KEYS.policy.kind}=features",
        )
        return
    require(bool(names), KEYS.policy.features, "is empty; expected a list from signals, risky, stay, e.g. [signals]")
    twice = sorted({n for n in names if names.count(n) > 1})
    require(not twice, KEYS.policy.features, f"lists {', '.join(twice)} twice; give each feature once")


def check_train(train: TrainConf) -> None:
    """Iterations, samples, the step-size schedule (Assumption 6 only warns), evaluation and records."""
    keys = KEYS.train
    require(train.iterations >= 1, keys.iterations, f"got {train.iterations}; expected a whole number >= 1")
    require(train.samples >= 1, keys.samples, f"got {train.samples}; expected W >= 1")
    require(
        math.isfinite(train.samples_growth) and train.samples_growth >= 0,
        keys.samples_growth,
        f"got {train.samples_growth}; expected a finite exponent >= 0",
    )
    step = train.step_size
    require(
        math.isfinite(step.initial) and step.initial >= 0,
        keys.step_size.initial,
        f"got {step.initial}; expected a finite step >= 0",
    )
    require(math.isfinite(step.decay) and step.decay > 0, keys.step_size.decay, f"got {step.decay}; expected > 0")
    require(math.isfinite(step.power) and step.power >= 0, keys.step_size.power, f"got {step.power}; expected >= 0")
    if not 0.5 < step.power <= 1.0:
        warnings.warn(f"{keys.step_size.power}={step.power} breaks Assumption 6 (needs 0.5 < power <= 1)", stacklevel=3)
    if step.initial == 0:  # allowed (the initial policy's own figures), but nothing is learnt
        warnings.warn(f"{keys.step_size.initial}=0 breaks Assumption 6 (sum eps = 0: theta never moves)", stacklevel=3)
    require(train.eval_episodes >= 1, keys.eval_episodes, f"got {train.eval_episodes}; expected >= 1")
    require(train.paths >= 0, keys.paths, f"got {train.paths}; expected >= 0")
    require(train.checkpoint_every >= 1, keys.checkpoint_every, f"got {train.checkpoint_every}; expected >= 1")
    require(train.bootstrap >= 1, keys.bootstrap, f"got {train.bootstrap}; expected >= 1 resamples")
    if train.bootstrap < MIN_RESAMPLES:  # allowed (quick tests), but the 2.5% tails hold no resample of their own
        warnings.warn(
            f"{keys.bootstrap}={train.bootstrap} is too few resamples for a 95% interval (its bounds are the "
            f"extreme resamples); use >= {MIN_RESAMPLES} (default 1000)",
            stacklevel=3,
        )


def check_world(world: WorldConf) -> None:
    """The horizon, world.map_cell and each source's motion probability (cells, shapes and rewards need the grid:
    engine.world; the map's files are read by run.maps)."""
    require(world.horizon >= 1, KEYS.world.horizon, f"got {world.horizon}; expected a whole number of moves >= 1")
    require(
        world.map_cell >= 1,
        KEYS.world.map_cell,
        f"got {world.map_cell}; expected k >= 1 (one cell is k x k map pixels)",
    )
    for j, source in enumerate(world.sources):
        check_label(source.name, KEYS.world.sources.at(j).name)
    check_source_names(source_names(world.sources))
    for r, region in enumerate(world.regions):
        check_label(region.name, KEYS.world.regions.at(r).name)
    for j, source in enumerate(world.sources):
        where = KEYS.world.sources.at(j).motion.prob
        prob = source.motion.prob  # checked for static sources too: a probability outside [0, 1] is a typo
        require(0.0 <= prob <= 1.0, where, f"got {prob}; expected a probability in [0, 1]")
        require(
            source.motion.kind == MotionKind.static or prob > 0.0,
            where,
            f"got {prob}; a random walk needs a step probability in (0, 1]",
        )


def check_team(team: TeamConf) -> None:
    """The team's scalar settings: size, delays and drops (Assumption 5 (3)-(4)), rounds, switching, the link
    radius. The graph and its weights are checked when the network is built."""
    keys = KEYS.team
    integer_at_least(team.robots, keys.robots, 1, "the number of robots")
    integer_at_least(team.delay.max, keys.delay.max, 0, "the largest message delay in iterations (B0)")
    drop = finite(team.drop, keys.drop)
    require(0.0 <= drop < 1.0, keys.drop, f"is {drop:g}; the drop probability must be in [0, 1)")
    integer_at_least(team.max_gap, keys.max_gap, 1, "the longest gap between deliveries on a link (B)")
    integer_at_least(team.consensus_rounds, keys.consensus_rounds, 1, "the number of consensus rounds per iteration")
    integer_at_least(team.resample, keys.resample, 0, "the number of random_geometric redraws")
    integer_at_least(team.switching.window, keys.switching.window, 1, "the switching window (iterations)")
    up = finite(team.switching.up, keys.switching.up)
    require(0.0 < up <= 1.0, keys.switching.up, f"is {up:g}; the per-iteration link-up probability must be in (0, 1]")
    radius = finite(team.radius, keys.radius)
    require(radius > 0, keys.radius, f"is {radius:g}; the link radius must be > 0 (the unit square is 1 x 1)")
    integer_at_least(team.trim, keys.trim, 0, "the number of extreme values trimmed at each end (F)")
    require(
        team.aggregate == Aggregate.mean or team.order != Order.gradient_tracking,
        keys.aggregate,
        f"got {team.aggregate}; gradient tracking mixes running sums, which trimming would break: use "
        f"{keys.aggregate}=mean, or {keys.order}=combine_then_adapt or adapt_then_combine",
    )
    if team.risk is not None:
        count = len(team.risk)
        require(
            count == team.robots,
            keys.risk,
            f"gives {count} risk node{'' if count == 1 else 's'} for {team.robots} robots; give one per robot or null",
        )
        for i, node in enumerate(team.risk):
            check_risk(node, keys.risk.at(i))
    check_byzantine(faults_of(team))
    require(
        not team.faults or team.order != Order.gradient_tracking,
        keys.faults,
        "gradient tracking mixes running sums, whose invariant a faulty robot breaks: drop the faults, or use "
        f"{keys.order}=combine_then_adapt or adapt_then_combine",
    )
    check_backend(team)
    if team.starts is not None:
        count = len(team.starts)
        require(
            count == team.robots,
            keys.starts,
            f"gives {count} start cell{'' if count == 1 else 's'} for {team.robots} robots; give one [x, y] per "
            f"robot or null",
        )


def check_byzantine(faults: tuple[Fault, ...]) -> None:
    """What a byzantine robot sends stays within BYZANTINE_LIMIT, whatever the world: a `value` in [-1e100, 1e100],
    noise of a `scale` <= 1e100. The thetas that mix it, their gaps squared (the consensus error) and their softmax
    logits (every signal peaks below 1e100, riskplan.engine.world.SIGNAL_LIMIT) then stay finite; a value of 1e308
    made the consensus error inf, and its thetas the report's axes overflow. The engine's step checks what still
    could overflow at run time (riskplan.engine.step.check_agreement)."""
    for i, fault in enumerate(faults):
        where = KEYS.team.faults.at(i)
        if fault.value is not None:
            largest = max(fault.value, key=abs)
            require(
                abs(largest) <= BYZANTINE_LIMIT,
                f"{where}.value",
                f"got {largest:g}; expected numbers in [-1e100, 1e100]: beyond that, the thetas that mix what a "
                f"byzantine robot sends overflow when squared (the consensus error), and their softmax logits may",
            )
        if fault.scale is not None:
            require(
                fault.scale <= BYZANTINE_LIMIT,
                f"{where}.scale",
                f"got {fault.scale:g}; expected a noise scale in (0, 1e100]: beyond that, the thetas that mix what a "
                f"byzantine robot sends overflow when squared (the consensus error), and their softmax logits may",
            )


def check_backend(team: TeamConf) -> None:
    """team.staleness, team.speeds and team.address, whatever the backend; the simulated network's delays, drops
    and switching links do not apply to real messages (team.backend=ray), so they are refused there."""
    keys = KEYS.team
    integer_at_least(team.staleness, keys.staleness, 0, "the oldest neighbour message a robot mixes, in iterations,")
    if team.speeds is not None:
        require(
            len(team.speeds) == team.robots,
            keys.speeds,
            f"gives {len(team.speeds)} factors for {team.robots} robots; give one per robot (1 = full speed) or null",
        )
        for i, speed in enumerate(team.speeds):
            require(
                math.isfinite(speed) and speed >= 1.0,
                keys.speeds.at(i),
                f"got {speed}; expected a slow-down factor >= 1 (4 = four times slower)",
            )
    require(
        team.address is None or bool(team.address.strip()),
        keys.address,
        "is empty; give auto, host:port of a Ray cluster's head, or null for a local Ray instance",
    )
    if BACKENDS[team.backend].simulated_network:
        return
    simulated = [
        (key, value)
        for key, value in (
            (keys.delay.max, team.delay.max),
            (keys.drop, team.drop),
            (keys.switching.enabled, team.switching.enabled),
        )
        if value
    ]
    require(
        not simulated,
        simulated[0][0] if simulated else keys.backend,
        f"got {simulated[0][1] if simulated else ''}; it simulates the network, and with {keys.backend}=ray messages "
        f"take the time they really take: drop it (bound their age with {keys.staleness})",
    )
