"""One iteration of the paper's algorithm, as a pure function of arrays and frozen parameters:
`step(setup, state) -> (state, statistics)`.

Read top to bottom, iteration l of Algorithm 1 for a team of N robots (N = 1 is the centralized run):
  1. rollouts: W_l episodes per robot at its theta^i_l, from its own counter-based stream (eqs. 1-3; all robots in
     one kernel call);
  2. estimates: the statistics of the total reward Z: the mean, VaR_beta and CVaR_beta (eqs. 5-6);
  3. gradients: each robot's, by its risk measure (eq. 4 for the mean, eq. 9 for CVaR, each other measure's own
     estimator; riskplan.engine.gradients);
  4. the step: eps_l, then theta^i_{l+1} = sum_j A^{ij} theta^j_{t^{ij}(l)} + eps_l Delta^i (eq. 14; N = 1 is
     eq. 11), adapt-then-combine or gradient tracking (team.order);
  5. the fault rules (which robots are healthy) and the finiteness checks: a NaN or infinity is never a result.

`estimate` is steps 1-3 for some of the robots: a Ray robot runs it for itself, and a batched sweep hands it the
episodes of one kernel call over many runs (`rollouts(..., batch=...)`). The step has no files, clocks or rows; the
drivers (riskplan.run.training, the Ray robots) add those. The Mixer is the team's scratch space: the step reads its
state from `state.mixer` and returns the new one, so the same state always gives the same next state.
"""

from __future__ import annotations

import collections
import functools
import itertools
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from riskplan.config.backends import DEVICES, load
from riskplan.config.schema import Device, Order, RiskConf, RiskplanConf
from riskplan.config.typed import as_dict
from riskplan.engine import rng
from riskplan.engine.gradients import gradients
from riskplan.engine.policy import Policy
from riskplan.engine.risk_measures import summary_stats
from riskplan.engine.rollout import KernelArrays
from riskplan.engine.schedules import samples_at, step_size
from riskplan.engine.team.convergence import consensus_error
from riskplan.engine.team.mixer import Mixer
from riskplan.engine.team.network import Network
from riskplan.engine.world import World


@dataclass(frozen=True)
class RunSetup:
    """A validated experiment: its frozen config, world, kernel arrays, team network (riskplan.run.build builds it
    from a config, once)."""

    params: RiskplanConf  # what the engine and the training loop read
    config: dict  # the same as plain data, for the records (.hydra/config.yaml, run.mcap metadata)
    world: World
    kernel: KernelArrays
    network: Network
    mixer: Mixer
    theta0: np.ndarray  # (len(theta_names),): M for the paper's policy, C * 5 for a tabular one
    policy: Policy  # what theta parameterises (policy.kind, policy.features); the kernel packs it
    theta_names: tuple[str, ...]  # one unique name per entry of theta (summary.json, the MCAP metadata)

    @property
    def robots(self) -> int:
        """Team size N."""
        return self.network.robots

    @property
    def team(self) -> bool:
        """Whether this is a distributed run (N > 1)."""
        return self.network.robots > 1


class TrainState(NamedTuple):
    """Where training stands before iteration `iteration`: every robot's theta and the consensus buffers."""

    iteration: int
    thetas: np.ndarray  # (N, P)
    mixer: Mapping[str, np.ndarray]  # Mixer.snapshot(): the messages in flight and what each link last did


class Estimates(NamedTuple):
    """Steps 1-3 for some robots: their episodes' total rewards and what was estimated from them."""

    episodes: int  # W_l per robot
    z: np.ndarray  # (R, W_l) total rewards
    stats: dict[str, np.ndarray]  # mean, cvar, value_at_risk, std at risk.beta, and objective: (R,) each
    grads: np.ndarray  # (R, P)
    levels: np.ndarray  # (R,) the gradient's CVaR level beta_l (NaN for a measure without one)


class Statistics(NamedTuple):
    """What iteration l measured: each robot's estimates at theta_l, the step taken, the team's agreement."""

    iteration: int
    thetas: np.ndarray  # (N, P) theta_l, the parameters the episodes ran at
    estimates: Estimates
    step_size: float  # eps_l
    consensus_error: float  # max ||theta^i - theta^j|| over the healthy robots (NaN for one robot)
    healthy: np.ndarray  # (N,) bool: the robots no fault has stopped by iteration l
    team: dict[str, float] | None  # a team's network average: its statistics on the pooled healthy episodes


class NumericalTrouble(RuntimeError):
    """theta or a gradient stopped being finite; the last good checkpoint is kept."""


def initial_state(setup: RunSetup) -> TrainState:
    """Iteration 0: every robot at theta_0, no message in flight."""
    return TrainState(0, np.tile(setup.theta0, (setup.robots, 1)), setup.mixer.fresh())


def step(setup: RunSetup, state: TrainState, batch: tuple[np.ndarray, np.ndarray] | None = None):
    """Iteration `state.iteration` of the team: (the next state, its Statistics). NumericalTrouble when an
    estimate or the new theta is not finite. `batch`: the (z, scores) of this iteration's episodes when a caller
    ran them already; else the step runs them. (riskplan.engine.loop runs many iterations of many runs.)"""
    l = state.iteration
    z, scores = rollouts(setup, l, state.thetas) if batch is None else batch
    return advance(setup, state, estimate(setup, l, z, scores))


def advance(setup: RunSetup, state: TrainState, estimates: Estimates) -> tuple[TrainState, Statistics]:
    """Steps 4-5 of iteration `state.iteration` from its estimates: eps_l, the consensus step, the checks, the
    team's agreement and network average."""
    l, thetas = state.iteration, state.thetas
    eps = step_size(l, setup.params.train.step_size)
    mixer = setup.mixer.at(state.mixer)
    with np.errstate(over="ignore", invalid="ignore"):  # a theta that overflows is caught by check_step, in one line
        new_thetas = consensus_step(setup, mixer, thetas, estimates.grads, eps, l)
    check_step(setup, l, thetas, estimates.grads, new_thetas)
    healthy = mixer.healthy(l)  # team.faults: the averages and the consensus error are the healthy robots'
    error = math.nan  # one robot: no team to agree
    if setup.team:
        kept = thetas if healthy.all() else thetas[healthy]
        error = consensus_error(kept)
        check_agreement(l, kept, error)
    team = team_statistics(setup, l, estimates.z, estimates.stats["objective"]) if setup.team else None
    statistics = Statistics(l, thetas, estimates, eps, error, healthy, team)
    return TrainState(l + 1, new_thetas, mixer.snapshot()), statistics


def rollouts(setup: RunSetup, l: int, thetas: np.ndarray, robots=None) -> tuple[np.ndarray, np.ndarray]:
    """Step 1: W_l episodes of each robot at its theta, from the stream keyed by (seed, iteration, robot) and from
    its start cell: z (R, W_l), scores (R, W_l, P). `robots`: the team indices of the thetas given (default: the
    whole team); robot i's episodes are the same whoever else runs in the call."""
    n, episodes = len(thetas), samples_at(l, setup.params.train)
    if robots is None:
        keys, cells = rng.robot_keys(setup.params.seed, rng.TRAIN, l, n), starts(setup)
    else:
        keys = np.array([rng.stream_key(setup.params.seed, rng.TRAIN, l, int(i)) for i in robots], dtype=np.uint64)
        cells = np.asarray(starts(setup)[np.asarray(robots)])
    batch = simulator(setup)(setup.world, setup.kernel, thetas, cells, keys, episodes)
    return batch.total_reward.reshape(n, episodes), batch.score.reshape(n, episodes, -1)


def simulator(setup: RunSetup):
    """The episode kernel of a setup's engine.device (riskplan.config.backends.DEVICES): riskplan.engine.rollout's
    `simulate` on the CPU, its GPU port (numba-cuda, imported for engine.device=cuda alone) with the same arguments
    and numbers."""
    return _kernel(setup.params.engine.device)


@functools.cache
def _kernel(device: Device):
    return load(DEVICES[device].kernel)


def batched_rollouts(setups: list[RunSetup], l: int, thetas: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Step 1 for many runs at once (`batch_episodes`), split into each run's (z, scores): bit for bit those
    `rollouts` gives it alone."""
    z, scores, bounds = batch_episodes(setups, l, thetas)
    return [(z[a:b], scores[a:b]) for a, b in itertools.pairwise(bounds)]


def batch_episodes(
    setups: list[RunSetup], l: int, thetas: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 1 for many runs at once: one kernel call over every run's robots, each run's episodes from its own
    streams (its seed) and start cells. Returns the block z (T, W_l) and scores (T, W_l, P) of every robot of
    every run, and the bounds of each run's rows in it (R + 1,). The runs must share a world, a policy and W_l
    (batch_key)."""
    first = setups[0]
    episodes = samples_at(l, first.params.train)
    keys = np.concatenate([rng.robot_keys(s.params.seed, rng.TRAIN, l, s.robots) for s in setups])
    cells = np.concatenate([starts(s) for s in setups])
    batch = simulator(first)(first.world, first.kernel, np.vstack(thetas), cells, keys, episodes)
    z = batch.total_reward.reshape(len(keys), episodes)
    scores = batch.score.reshape(len(keys), episodes, -1)
    return z, scores, np.cumsum([0] + [s.robots for s in setups])


def batch_key(params: RiskplanConf) -> str:
    """What runs must share to run their episodes in one kernel call: the world (grid, sources, rewards, regions,
    horizon), the policy, and the sample schedule W_l. Seeds, risk measures and levels, step sizes, theta_0, team
    sizes, graphs and the iterations may differ."""
    kept = _SHARED.get((id(params.world), id(params.policy)))
    if kept is None or kept[0] is not params.world or kept[1] is not params.policy:
        text = [json.dumps(as_dict(node), sort_keys=True, default=str) for node in (params.policy, params.world)]
        kept = (params.world, params.policy, *text)
        _SHARED[(id(params.world), id(params.policy))] = kept  # the nodes kept alive, so their ids stay theirs
        while len(_SHARED) > SHARED_MEMO:
            _SHARED.popitem(last=False)
    samples = json.dumps([params.train.samples, params.train.samples_growth], default=str)
    return f'{{"policy": {kept[2]}, "samples": {samples}, "world": {kept[3]}}}'  # JSON with its keys sorted


SHARED_MEMO = 16  # a sweep's jobs share their world and policy nodes (riskplan.experiments.sweeping.as_data)
_SHARED: collections.OrderedDict[tuple[int, int], tuple] = collections.OrderedDict()


def team_statistics(setup: RunSetup, l: int, z: np.ndarray, objectives: np.ndarray) -> dict[str, float]:
    """A team's network average at iteration l: the statistics of the healthy robots' episodes pooled (z (N, W)),
    and the team objective, the sum of their objectives."""
    healthy = setup.mixer.healthy(l)
    ok = slice(None) if healthy.all() else healthy
    return summary_stats(z[ok].ravel(), setup.params.risk.beta, parallel=True) | {"objective": objectives[ok].sum()}


def estimate(setup: RunSetup, l: int, z: np.ndarray, scores: np.ndarray, robots=None, where: str = "") -> Estimates:
    """Steps 2-3 for the robots whose episodes are z (R, W) and scores (R, W, P): the statistics at risk.beta and
    each robot's gradient by its own risk node. `robots`: their indices in the team (default: all of it), for
    team.risk; `where` names them in a message."""
    params, beta = setup.params, setup.params.risk.beta
    where = f"iteration {l}" + (f": {where}" if where else "")
    check_finite(f"{where}: an episode's total reward", z)
    with np.errstate(over="ignore", invalid="ignore"):  # non-finite results are caught just below, in one line
        stats = summary_stats(z, beta, parallel=True)  # z is finite: a large W's statistics on every core
        check_finite(f"{where}: the statistics of the total reward", *stats.values())
        grads, levels, stats["objective"] = np.empty((len(z), scores.shape[-1])), np.empty(len(z)), np.empty(len(z))
        for risk, members in risk_groups(params, robots):  # one group of all, unless team.risk gives robots their own
            grads[members], levels[members], stats["objective"][members] = gradients(
                z[members], scores[members], risk, l, stats, members, params.train.baseline, beta
            )
        check_finite(f"{where}: the objective of the total reward", stats["objective"])
    return Estimates(z.shape[1], z, stats, grads, levels)


def consensus_step(setup: RunSetup, mixer: Mixer, thetas: np.ndarray, grads: np.ndarray, eps: float, l: int):
    """Step 4: eq. (14) combine-then-adapt, A theta + eps Delta (default), adapt-then-combine, A (theta + eps
    Delta), or gradient tracking, A theta + eps y with y the robot's tracker of the average gradient (Mixer.track).
    One robot has no neighbours: theta + eps Delta, eq. (11)."""
    if setup.params.team.order == Order.gradient_tracking and setup.team:
        mixed, tracker = mixer.track(thetas, grads, l)
        return mixed + eps * tracker
    adapt_first = setup.params.team.order == Order.adapt_then_combine
    mixed = thetas + eps * grads if adapt_first else thetas
    for round_index in range(setup.params.team.consensus_rounds if setup.team else 0):
        mixed = mixer.mix(mixed, l, round_index)
    return mixed if adapt_first else mixed + eps * grads


def check_step(setup: RunSetup, l: int, thetas: np.ndarray, grads: np.ndarray, new_thetas: np.ndarray, who: str = ""):
    """Step 5: NumericalTrouble unless the gradients and the new thetas are finite and the new softmax logits are."""
    where = f"iteration {l}" + (f": {who}" if who else "")  # a robot alone gives its own theta (P,)
    if not (np.all(np.isfinite(grads)) and np.all(np.isfinite(new_thetas))):
        raise NumericalTrouble(
            f"{where}: theta or its gradient is not finite (theta={_shown(thetas)}, "
            f"gradient={_shown(grads)}); lower train.step_size.initial"
        )
    if not math.isfinite(logit_bound(setup.world, np.atleast_2d(new_thetas), setup.policy)):
        raise NumericalTrouble(
            f"{where}: the new theta={_shown(new_thetas)} overflows the softmax "
            f"(theta . features is not finite); lower train.step_size.initial"
        )


def check_agreement(l: int, thetas: np.ndarray, error: float) -> None:
    """Step 5 for a team: NumericalTrouble unless the consensus error of the healthy robots' thetas (H, P) and their
    mean (the network average's theta) are finite; each theta is (check_step), but they may be too far apart."""
    with np.errstate(over="ignore", invalid="ignore"):  # what overflows is said below, in one line
        mean_ok = bool(np.isfinite(thetas.mean(axis=0)).all())
    if not (math.isfinite(error) and mean_ok):
        what, why = (
            ("consensus error max ||theta^i - theta^j||", "too far apart")
            if not math.isfinite(error)
            else ("mean theta", "too large")
        )
        raise NumericalTrouble(
            f"iteration {l}: the healthy robots' {what} is not finite (overflow; theta={_shown(thetas)}): their "
            f"thetas are {why} for a float; lower train.step_size.initial (or a byzantine robot's team.faults value "
            f"or scale)"
        )


def check_finite(what: str, *arrays) -> None:
    """NumericalTrouble unless every value is finite: a NaN or infinity is never recorded as a result."""
    for values in arrays:
        if not np.all(np.isfinite(values)):
            raise NumericalTrouble(f"{what} is not finite (overflow); use smaller rewards or fewer steps")


def risk_groups(params: RiskplanConf, robots=None) -> list[tuple[RiskConf, slice | np.ndarray]]:
    """The robots that share a risk node, as (node, index into the given robots): one group of all (a slice, so the
    default path copies nothing) unless team.risk gives robots nodes of their own. `robots`: the team indices of the
    robots at hand (default: the whole team)."""
    if params.team.risk is None:
        return [(params.risk, slice(None))]
    members = range(params.team.robots) if robots is None else np.atleast_1d(robots)
    groups: dict[str, tuple[RiskConf, list[int]]] = {}
    for position, robot in enumerate(members):
        node = params.team.risk[int(robot)]
        groups.setdefault(json.dumps(as_dict(node), sort_keys=True), (node, []))[1].append(position)
    return [(node, np.array(positions)) for node, positions in groups.values()]


def starts(setup: RunSetup) -> np.ndarray:
    """Start cell of each robot (all at world.start unless team.starts is given)."""
    cells = setup.world.starts
    return np.repeat(cells, setup.robots) if len(cells) == 1 else cells


def logit_bound(world: World, thetas: np.ndarray, policy: Policy | None = None) -> float:
    """Largest |logit| any policy in `thetas` (..., len(theta)) can produce: sum_i |theta_i| x peak |f_i| for a
    features policy (a signal's peak |amplitude|, 1 for risky and stay), the largest |theta| for a tabular one.

    When it is finite, no logit (or partial sum of one) overflows, so the softmax stays finite. Pass the run's
    `policy` (RunSetup.policy) for the exact bound; without it, theta of length M is the paper's policy (exact, as
    before), theta of length C * 5 a table, and any other length is bounded with every feature at the largest peak,
    max(1, max |amplitude|) (an upper bound whatever the order of the features).
    """
    if policy is not None:
        return policy.logit_bound(thetas)
    thetas = np.asarray(thetas, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        if thetas.shape[-1] == world.sources:
            return float(np.max(np.abs(thetas) @ np.abs(world.source_amplitude)))
        if thetas.shape[-1] == world.cells * 5:
            return float(np.max(np.abs(thetas))) if thetas.size else 0.0
        peak = max(1.0, float(np.max(np.abs(world.source_amplitude))))
        return float(np.max(np.abs(thetas).sum(axis=-1) * peak))


def _shown(values: np.ndarray) -> str:
    """An array for a one-line message: every number when few (the paper's theta), else a summary (a table)."""
    values = np.asarray(values, dtype=float)
    return str(values.tolist()) if values.size <= 16 else np.array2string(values, threshold=8, max_line_width=10**6)
