"""Everything a run derives from its config, built (and so validated) once at the top: the PureJaxRL way."""

from __future__ import annotations

import collections
import dataclasses
import math
import re
import warnings
from typing import NamedTuple

import numpy as np
from omegaconf import DictConfig

from riskplan.config.backends import DEVICES, load
from riskplan.config.schema import Choice, RiskConf, RiskplanConf, ScheduleKind
from riskplan.config.typed import as_dict, typed
from riskplan.config.validate import validate
from riskplan.engine import rng
from riskplan.engine.estimators import mean_gradient, tail_count
from riskplan.engine.measures.registry import check_risk_nodes, risk_spec
from riskplan.engine.policy import Policy, make_policy
from riskplan.engine.reachability import source_distances
from riskplan.engine.rollout import KernelArrays, make_kernel
from riskplan.engine.step import RunSetup, simulator, starts
from riskplan.engine.team.mixer import Mixer
from riskplan.engine.team.network import build_network
from riskplan.engine.world import World, build_world, grid_size
from riskplan.run import budget, maps
from riskplan.util.checks import require
from riskplan.util.errors import BadInput


def build_setup(cfg: DictConfig | dict | RiskplanConf, needs_ray: bool = True) -> RunSetup:
    """Type and validate the config once, then build the run's objects; raises BadInput on the first problem
    (`needs_ray`: see config.validate.validate). The config's warnings are given once it is built: bad input is
    one line, with no warning about the config before it."""
    with warnings.catch_warnings(record=True) as caught:
        setup = _build(cfg, needs_ray)
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)
    return setup


def build_planned(cfg: DictConfig | dict | RiskplanConf) -> RunSetup:
    """build_setup for a sweep's job: the config's warnings are the sweep's to give, once, as it plans (leaving out
    a key that a variant it sweeps ignores: team.aggregate=mean,trimmed_mean team.trim=1), not again in every job's
    log."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return build_setup(cfg)


def _build(cfg: DictConfig | dict | RiskplanConf, needs_ray: bool) -> RunSetup:
    params = typed(cfg)  # types, unknown keys, Choices, interpolations: the frozen config everything below reads
    validate(params, needs_ray)  # every range, once
    check_risk_nodes(params)  # each risk node's measure (built in or a package's) and its parameters
    warn_single_episode_tail(params)
    warn_single_sample(params)
    check_device(params)  # engine.device=cuda: a GPU numba-cuda can use
    # Sizes first: nothing big is allocated before the memory and time estimates pass (a map's from its header).
    found = maps.read_map(params.world)
    width, height = grid_size(params.world.size) if found is None else found.cells
    check_sizes(params, found, width, height)
    world, policy, kernel = _world_and_policy(params, found)
    theta0 = initial_theta(world, policy, list(params.train.theta0))
    network = build_network(params.team, policy.size, params.seed)
    budget.check(budget.sizes_of(params, world.width, world.height, world.sources, network.robots))  # before the Mixer
    return RunSetup(
        params=params,
        config=_plain_config(params),
        world=world,
        kernel=kernel,
        network=network,
        mixer=Mixer(network, params.team, params.seed),
        theta0=theta0,
        policy=policy,
        theta_names=policy.names,
    )


def _world_and_policy(params: RiskplanConf, found: maps.MapFile | None) -> tuple[World, Policy, KernelArrays]:
    """The world (its sources checked reachable), the policy and their kernel arrays. Runs of a sweep that share
    one frozen world and policy config (riskplan.experiments.sweeping.as_data's jobs: those that differ in a seed, a
    level or a step size) share these too: they are frozen, and building them is most of a run's set-up. A map's
    world is built each time (its file may have changed)."""
    configs = (params.world, params.policy, params.team.starts)
    key = tuple(map(id, configs))
    kept = _BUILT.get(key) if found is None else None
    if kept is not None and all(a is b for a, b in zip(kept[0], configs)):
        _BUILT.move_to_end(key)
        return kept[1]
    layout = None if found is None else maps.load_layout(params.world, found)
    given = None if params.team.starts is None else list(params.team.starts)
    world = build_world(params.world, given, layout)
    check_starts(world, per_robot=given is not None)
    check_reach(world, source_distances(world, np.unique(world.starts)))
    policy = make_policy(world, params.policy.kind, params.policy.features)
    built = (world, policy, make_kernel(world, policy))
    if found is None:
        _BUILT[key] = (configs, built)  # the configs kept alive, so that their ids stay theirs
        while len(_BUILT) > BUILT_MEMO:
            _BUILT.popitem(last=False)
    return built


BUILT_MEMO = 4
_BUILT: collections.OrderedDict[tuple, tuple] = collections.OrderedDict()


def _plain_config(params: RiskplanConf) -> dict:
    """as_dict(params), each node's dict made once for all the runs that share the frozen node (a sweep's jobs
    share all but the nodes their overrides change). Nothing writes into a run's config dict."""
    config = {}
    for name, node in vars(params).items():
        if not dataclasses.is_dataclass(node):
            config[name] = node.value if isinstance(node, Choice) else node  # as as_dict writes a Choice
            continue
        kept = _PLAIN.get(id(node))
        if kept is None or kept[0] is not node:
            kept = _PLAIN[id(node)] = (node, as_dict(node))  # the node kept alive, so that its id stays its
            while len(_PLAIN) > PLAIN_MEMO:
                _PLAIN.popitem(last=False)
        config[name] = kept[1]
    return config


PLAIN_MEMO = 64
_PLAIN: collections.OrderedDict[int, tuple] = collections.OrderedDict()


class SingleTail(NamedTuple):
    """A risk node whose gradient's CVaR tail holds one of train.samples episodes."""

    where: str  # risk, or team.risk.<i>
    shown: str  # its level as the warning shows it: risk.beta=0.1
    level: float
    vanishes: bool  # the whole gradient is zero, not only a CVaR part of it (mean_cvar's)
    lifted: bool  # soft risk or train.samples_growth lift the tail in some iterations


def warn_single_episode_tail(params: RiskplanConf) -> None:
    """A warning (one `warning:` line from the CLI) when a risk node's gradient takes CVaR at a level whose tail,
    ceil(beta W) of an iteration's train.samples W episodes, holds the worst episode alone: its total is the VaR v,
    so every (z - v) 1{z <= v} of eq. 9 is 0, and that gradient is zero in every iteration, silently. Only a measure
    with a CVaR level below 1 (`Measure.level`: cvar, mean_cvar's CVaR part) has such a tail; the other measures
    weigh every episode. Soft risk's higher beta_l and train.samples_growth's larger W_l lift some iterations."""
    samples, team = params.train.samples, params.team.risk
    nodes = [("risk", params.risk)] if team is None else [(f"team.risk.{i}", node) for i, node in enumerate(team)]
    found = [tail for where, node in nodes if (tail := _single_tail(node, where, params)) is not None]
    if not found:
        return
    first, lowest = found[0], min(tail.level for tail in found)
    least = math.floor(1.0 / lowest) + 1  # the fewest episodes whose tail holds two
    while tail_count(lowest, least) < 2:  # 1 / lowest rounded down
        least += 1
    whose = "the gradient" if team is None else f"robot {first.where.rsplit('.', 1)[1]}'s gradient"
    if len(found) == len(nodes) and all(tail.vanishes for tail in found):  # no robot's gradient moves it
        effect = ("the gradient" if team is None else "every robot's gradient") + " is zero: theta never moves"
    elif first.vanishes:
        effect = f"{whose} is zero (its theta moves only by consensus)"
    else:
        effect = f"{whose}'s CVaR part is zero"
    if first.lifted:
        effect += " (except in iterations where soft risk or train.samples_growth raise beta_l x W_l above 1)"
    more = f" (and {len(found) - 1} more of team.risk's nodes)" if len(found) > 1 else ""
    warnings.warn(
        f"{first.shown}{more} with train.samples={samples}: CVaR's tail holds ceil({first.level:g} x {samples}) = 1 "
        f"episode, the worst, so every (z - v) of eq. 9 is 0 and {effect}; use train.samples >= {least}",
        stacklevel=2,
    )


def warn_single_sample(params: RiskplanConf) -> None:
    """A warning when train.samples=1 leaves every risk node's gradient zero: a baseline compares an episode with
    the iteration's others (the mean's, entropic's 1/W), and a CVaR tail of one holds the VaR itself, so with one
    episode theta never moves, silently. REINFORCE without its baseline (train.baseline=false) still moves it."""
    if params.train.samples != 1:
        return
    team = params.team.risk
    nodes = [("risk", params.risk)] if team is None else [(f"team.risk.{i}", node) for i, node in enumerate(team)]
    one = np.array([1.0])
    for where, node in nodes:
        measure, values = risk_spec(node, where)
        if measure.gradient(one, one[:, None], values, baseline=params.train.baseline).any():
            return
    lifted = " (until train.samples_growth raises W_l above 1)" if params.train.samples_growth > 0 else ""
    warnings.warn(
        f"train.samples=1: one episode per iteration, and every gradient compares it with the iteration's others, so "
        f"it is zero and theta never moves{lifted}; use train.samples >= 2",
        stacklevel=2,
    )


def _single_tail(node: RiskConf, where: str, params: RiskplanConf) -> SingleTail | None:
    """The SingleTail of a risk node whose gradient takes CVaR at a level whose tail holds one of train.samples
    episodes; None for any other node (no CVaR level, a tail of two or more, or no weight on its CVaR)."""
    samples = params.train.samples
    measure, values = risk_spec(node, where)
    level = measure.level(values)
    if level is None or level >= 1.0 or tail_count(level, samples) > 1:
        return None
    ranks = np.arange(min(samples, 2), dtype=float)  # a tail of 1 at W = 2 too (level <= 1 / W <= 1/2)
    probe = measure.gradient(ranks, ranks[:, None], values)  # distinct totals and scores: a tail of 2 gives > 0
    if np.array_equal(probe, mean_gradient(ranks, ranks[:, None])):  # no weight on CVaR (mean_cvar's weight=0)
        return None
    scheduled = measure.scheduled and node.schedule.kind != ScheduleKind.none
    lifted = params.train.samples_growth > 0 or (scheduled and tail_count(node.schedule.start, samples) > 1)
    shown = f"{measure.key('beta', where)}={level:g}" if "beta" in values else f"{where}'s CVaR level {level:g}"
    return SingleTail(where, shown, level, not probe.any(), lifted)


def check_device(params: RiskplanConf) -> None:
    """A device that needs hardware (engine.device=cuda: a GPU that numba-cuda can use; the package itself is
    checked with the extras, in validate): BadInput naming it, when the run is built, so check and sweep refuse it
    too."""
    device = DEVICES[params.engine.device]
    if device.check is None:
        return
    try:
        check = load(device.check)  # imports the device's optional package, for a run that chose it alone
    except Exception as err:  # a numba-cuda that fails at import (0.30.4 with numpy 2.5, which lacks np.row_stack)
        extra = device.needs.extra if device.needs else ""
        raise BadInput(
            f"engine.device={device.name.value}",
            f"{device.needs.what if device.needs else 'its package'} fails to import ({type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''}); pip install 'riskplan[{extra}]', which pins a numpy "
            f"it supports",
        ) from None
    check()


def check_sizes(params: RiskplanConf, found: maps.MapFile | None, width: int, height: int) -> None:
    """The memory and time estimates of the grid before it is built; a map too large is named as world.map."""
    try:
        budget.check(budget.sizes_of(params, width, height, len(params.world.sources), params.team.robots))
    except BadInput as err:
        if found is None or err.where != "world.size":
            raise
        problem = re.sub(r"^got [^;]*; ", "", err.problem)
        problem = problem.replace("lower it, or", "give a smaller map or a larger world.map_cell, or")
        raise BadInput(
            "world.map",
            f"{found.shown} is {found.pixels[0]}x{found.pixels[1]} pixels, a {width}x{height} grid at "
            f"world.map_cell={found.cell}: {problem}",
        ) from None


def initial_theta(world: World, policy: Policy, given: list) -> np.ndarray:
    """theta_0 from train.theta0, which lists the weights of `policy.seed_names` in that order (the features in the
    order of policy.features; without signals, the extras come first).

    Entries left off at the end start at 0 (the paper's [20, 20] with policy.features=[signals, risky] starts the
    risky weight at 0); more entries than weights is BadInput. A features policy starts at these weights, a tabular
    one at the logits they give (riskplan.engine.policy.Policy.initial).
    """
    names = policy.seed_names
    count = len(names)
    shown = ", ".join(names) if count <= 8 else f"{', '.join(names[:8])}, ..."
    what = "signal weights to seed its table" if policy.tabular else "parameters"
    require(
        len(given) <= count,
        "train.theta0",
        f"got {given}; the policy has {count} {what} ({shown}); give at most {count} numbers",
    )
    weights = np.array(given, dtype=float)
    require(
        bool(np.all(np.isfinite(weights))),
        "train.theta0",
        f"got {given}; expected finite numbers, one per parameter ({shown})",
    )
    weights = np.concatenate([weights, np.zeros(count - len(weights))])
    require(
        math.isfinite(policy.seed_bound(weights)),
        "train.theta0",
        f"got {given}; the softmax logits theta . signal overflow to infinity; give smaller values",
    )
    return policy.initial(world, weights)


REACH_EPISODES = 1000  # theta0's episodes per distinct start behind the reach warning: 1% is about 10 of them
RARE = 0.01  # a source reached by fewer of theta0's episodes than this gets a warning


def check_starts(world: World, per_robot: bool) -> None:
    """BadInput for a start on a source's (initial) cell: an episode reaches a source when a move ends on it, so one
    that started there would count as not reaching it at step 0, while reach_lines said 0 moves. `per_robot`: the
    starts are team.starts' (each robot's own), not world.start."""
    sources = world.source_cells.tolist()
    for robot, cell in enumerate(world.starts.tolist()):
        if cell in sources:
            j = sources.index(cell)
            x, y = world.xy(cell)
            raise BadInput(
                f"team.starts.{robot}" if per_robot else "world.start",
                f"({x}, {y}) is the cell of world.sources.{j} '{world.source_names[j]}'; an episode reaches a source "
                f"when a move ends on it, never where it starts: choose a start off the sources",
            )


def check_reach(world: World, moves: np.ndarray) -> None:
    """BadInput for a static source that no start reaches within world.horizon moves (`moves`: (starts, sources)
    fewest moves, -1 for no path). One walled off from a start was refused by engine.world already, so every static
    source has a path from every start here. A random walk is measured from its start cell and not refused: it may
    walk nearer, and the sampled episodes of `reach_lines` tell how often the policy meets it."""
    for j, name in enumerate(world.source_names):
        nearest = int(moves[:, j].min())
        if world.source_motion[j] > 0 or nearest <= world.horizon:
            continue
        x, y = world.xy(world.source_cells[j])
        raise BadInput(
            f"world.sources.{j}.position",
            f"'{name}' at ({x}, {y}) is {nearest} moves from the nearest start, beyond world.horizon="
            f"{world.horizon}: no episode can reach it; move it or the start nearer, or lengthen world.horizon",
        )


def reach_lines(setup: RunSetup) -> list[str]:
    """One line per source: its fewest moves from each start beside the horizon, and the share of theta0's episodes
    that reach it (`initial_shares`). A share under RARE is also a warning (`warnings.warn`: one `warning:` line
    from the CLI) saying what to change."""
    world = setup.world
    cells = np.unique(world.starts)
    moves = source_distances(world, cells)
    shares = initial_shares(setup)
    here = ", ".join(f"({x}, {y})" for x, y in zip(*world.xy(cells)))
    lines = [f"reach from the start{'s' * (len(cells) > 1)} {here} within horizon K={world.horizon}:"]
    for j, name in enumerate(world.source_names):
        walk = " (a random walk: from its start cell)" if world.source_motion[j] > 0 else ""
        away = ", ".join("no path" if d < 0 else f"{d} moves" for d in moves[:, j].tolist())
        lines.append(f"  source {j} '{name}': {away}{walk}; theta0's episodes reach it in {shares[j]:.1%}")
        if shares[j] < RARE:
            advice = (  # a policy that weighs no signal cannot be steered towards a source by its signal
                f"raise its weight in train.theta0, widen its signal (world.sources.{j}.covariance)"
                if setup.policy.signal_at >= 0
                else "add signals to policy.features (the policy sees no source's signal)"
            )
            warnings.warn(
                f"source {j} '{name}' is reached by {shares[j]:.1%} of the initial policy's episodes (under "
                f"{RARE:.0%} of {REACH_EPISODES * len(cells)} sampled): training will rarely see it; {advice} "
                f"or lengthen world.horizon",
                stacklevel=2,
            )
    return lines


def initial_shares(setup: RunSetup) -> np.ndarray:
    """(sources,) the share of theta0's episodes that reach each source: REACH_EPISODES from each distinct start
    (robots that share a start and theta0 share their odds; a team of 1,000 costs what one robot does), on the
    streams of the first iteration's first robots."""
    cells = np.unique(starts(setup))
    keys = rng.robot_keys(setup.params.seed, rng.TRAIN, 0, len(cells))
    thetas = np.repeat(setup.theta0[None, :], len(cells), axis=0)
    batch = simulator(setup)(setup.world, setup.kernel, thetas, cells, keys, REACH_EPISODES, scores=False)
    reached = batch.source_reached
    return np.bincount(reached[reached >= 0], minlength=setup.world.sources) / len(reached)
