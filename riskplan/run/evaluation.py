"""The end of a run: the final policies on fresh episodes (eval.parquet), sampled paths (trajectories.parquet) and
summary.json, and the check that no non-finite number is ever recorded as a result."""

from __future__ import annotations

import json

import numpy as np

from riskplan.config.backends import BACKENDS
from riskplan.config.faults import faults_of
from riskplan.config.schema import NO_SOURCE, Aggregate, FaultKind, RiskConf, RiskplanConf
from riskplan.config.typed import as_dict
from riskplan.engine import rng
from riskplan.engine.measures.registry import risk_spec
from riskplan.engine.risk_measures import objective, summary_stats
from riskplan.engine.rollout import simulate
from riskplan.engine.step import RunSetup, TrainState, check_finite, simulator, starts
from riskplan.run.budget import EVAL_BATCH
from riskplan.run.columns import Columns, concat, rows_where
from riskplan.run.intervals import bootstrap_intervals, objective_interval, objective_intervals
from riskplan.run.log_format import EVAL_COLUMNS
from riskplan.run.metrics_rows import AVERAGE
from riskplan.run.provenance import provenance

SCHEMA_VERSION = 2  # of summary.json: 2 adds objective, team_objective, theta_names and robots (a list)
ROBOT_INTERVALS = 32  # distinct (start, risk) pairs up to which each robot's objective gets a bootstrap interval
INITIAL_EPISODES = 10_000  # theta0's episodes for the diagnosis: a tenth of the default evaluation's cost


def robot_risks(params: RiskplanConf) -> list[RiskConf]:
    """Each robot's risk node: team.risk's, or the top-level risk for all."""
    return list(params.team.risk) if params.team.risk is not None else [params.risk] * params.team.robots


def final_health(setup: RunSetup) -> np.ndarray:
    """(N,) bool: the robots no fault of team.faults had stopped by the last iteration."""
    return setup.mixer.healthy(setup.params.train.iterations - 1)


def network_average(setup: RunSetup, thetas: np.ndarray) -> np.ndarray:
    """theta-bar: the mean over the healthy robots (all of them without team.faults)."""
    healthy = final_health(setup)
    return thetas.mean(axis=0) if healthy.all() else thetas[healthy].mean(axis=0)


def policies(setup: RunSetup, thetas: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The evaluated policies: (robot ids, thetas, start cells); teams add the network average (robot -1)."""
    ids = np.arange(setup.robots)
    cells = starts(setup)
    if not setup.team:
        return ids, thetas, cells
    return np.append(ids, AVERAGE), np.vstack([thetas, network_average(setup, thetas)]), np.append(cells, cells[0])


def evaluate(setup: RunSetup, thetas: np.ndarray) -> Columns:
    """The final policies on fresh episodes (own stream), one row per episode: each policy's in turn, every
    kernel call's results copied once, into columns made for all of them (a team's are 900,000 rows)."""
    count = setup.params.train.eval_episodes
    ids, evaluated, cells = policies(setup, thetas)
    healthy = np.append(final_health(setup), True)[: len(ids)]  # the network average is the healthy robots'
    table = {
        "episode": np.tile(np.arange(count, dtype=np.int64), len(ids)),
        "robot": np.repeat(ids.astype(np.int64), count),
        "healthy": np.repeat(healthy, count),
        **{name: np.empty(count * len(ids), dtype) for name, dtype in OUTCOMES.items()},
    }
    run = simulator(setup)  # rollout.simulate, or its GPU port (engine.device=cuda)
    for p in range(len(ids)):
        for first in range(0, count, EVAL_BATCH):
            key = np.array([rng.stream_key(setup.params.seed, rng.EVAL, p, first)], dtype=np.uint64)
            size = min(EVAL_BATCH, count - first)
            batch = run(setup.world, setup.kernel, evaluated[p : p + 1], cells[p : p + 1], key, size, scores=False)
            rows = slice(p * count + first, p * count + first + size)
            for name in OUTCOMES:
                table[name][rows] = getattr(batch, name)
    return table


OUTCOMES = {name: np.dtype(dtype) for name, dtype in list(EVAL_COLUMNS.items())[3:]}  # after episode, robot, healthy


def sample_paths(setup: RunSetup, thetas: np.ndarray) -> Columns:
    """A few sampled paths of the initial and the final policies (own stream), one row per step."""
    count = setup.params.train.paths
    frames = []
    for name, policy_thetas in (("initial", np.tile(setup.theta0, (setup.robots, 1))), ("final", thetas)):
        ids, evaluated, cells = policies(setup, policy_thetas)
        keys = rng.robot_keys(setup.params.seed, rng.PATHS, 0 if name == "initial" else 1, len(ids))
        batch = simulate(setup.world, setup.kernel, evaluated, cells, keys, count, record=True, scores=False)
        alive = batch.path_cells >= 0
        episode, step = np.nonzero(alive)
        x, y = setup.world.xy(batch.path_cells[alive])
        frames.append(
            {
                "policy": np.full(len(step), name, dtype=object),
                "episode": (episode % max(count, 1)).astype(np.int64),
                "robot": ids[episode // max(count, 1)].astype(np.int64),
                "step": step.astype(np.int64),
                "x": x.astype(np.int64),
                "y": y.astype(np.int64),
                "reward": batch.path_rewards[alive],
            }
        )
    return concat(frames)


def summarize(
    setup: RunSetup,
    state: TrainState,
    evaluation: Columns,
    metrics: Columns,
    train_seconds: float,
    trained_from: int = 0,
) -> dict:
    """summary.json: headline policy's figures with intervals, per-policy basics, timing, provenance. The loop
    took `train_seconds` over the iterations from `trained_from` (where a resumed run went on), so the throughput
    counts their episodes alone."""
    params = setup.params
    headline = AVERAGE if setup.team else 0
    z = evaluation["total_reward"][evaluation["robot"] == headline]
    check_finite("the evaluation's total reward", evaluation["total_reward"])
    figures = bootstrap_intervals(z, params.risk.beta, params.train.bootstrap, params.seed)
    check_finite("the summary's figures", *[v for f in figures.values() for v in f.values()])
    steps = float(metrics["samples"][(metrics["robot"] >= 0) & (metrics["iteration"] >= trained_from)].sum())
    per_policy = {}
    for robot in np.unique(evaluation["robot"]):
        group = rows_where(evaluation, evaluation["robot"] == robot)
        per_policy[str(robot)] = {
            "healthy": bool(group["healthy"][0]),
            **{k: float(v) for k, v in summary_stats(group["total_reward"], params.risk.beta).items()},
            "risky_fraction": float((group["risky_steps"] > 0).mean()),
            "source_reached": {
                name: float((group["source_reached"] == j).mean()) for j, name in enumerate(setup.world.source_names)
            }
            | {NO_SOURCE: float((group["source_reached"] < 0).mean())},
        }
    _, final_thetas, _ = policies(setup, state.thetas)
    objective_figure = _objective(params.risk, z, figures, params)
    reached_none = per_policy[str(headline)]["source_reached"][NO_SOURCE]
    robots, team_objective = robot_objectives(setup, state.thetas, evaluation, objective_figure)
    return {
        "schema_version": SCHEMA_VERSION,
        "experiment": params.experiment,
        "risk": params.risk.measure,
        "beta": params.risk.beta,
        "team_size": setup.robots,
        "headline_robot": headline,
        "objective": objective_figure,
        "team_objective": team_objective,
        **figures,
        "risky_fraction": per_policy[str(headline)]["risky_fraction"],
        "source_reached": per_policy[str(headline)]["source_reached"],
        "theta_names": list(setup.theta_names),
        "theta_final": final_thetas[-1].tolist() if setup.team else final_thetas[0].tolist(),
        "robots": robots,
        "policies": per_policy,
        "diagnosis": diagnose(setup, objective_figure, reached_none),
        "iterations": state.iteration,
        "eval_episodes": params.train.eval_episodes,
        "wall_time": train_seconds,
        "deterministic": BACKENDS[params.team.backend].deterministic,  # ray: the wall clock orders the messages
        "throughput_episodes_per_s": steps / train_seconds if steps and train_seconds > 0 else None,
        "provenance": provenance(),
    }


def initial_objective(setup: RunSetup) -> dict:
    """The initial policy theta0 on the first INITIAL_EPISODES streams of the headline policy's evaluation (the same
    episodes' random numbers; its own call, so no evaluated number changes): the trained measure with its 95%
    bootstrap interval, `episodes`, and `reached_none`, the share of them that reached no source."""
    params = setup.params
    count = min(params.train.eval_episodes, INITIAL_EPISODES)  # <= EVAL_BATCH: one call, as evaluate's first
    headline = setup.robots if setup.team else 0  # its index among `policies`, which `evaluate` keys by
    key = np.array([rng.stream_key(params.seed, rng.EVAL, headline, 0)], dtype=np.uint64)
    run = simulator(setup)
    batch = run(setup.world, setup.kernel, setup.theta0[None, :], starts(setup)[:1], key, count, scores=False)
    check_finite("the initial policy's total reward", batch.total_reward)
    figure, _ = objective_interval(batch.total_reward, params.risk, params.train.bootstrap, params.seed)
    return {**figure, "episodes": count, "reached_none": float((batch.source_reached < 0).mean())}


def diagnose(setup: RunSetup, objective_figure: dict, reached_none: float) -> dict:
    """summary.json's `diagnosis`: whether the run learned something degenerate, each finding with its likely
    cause, and theta0's objective it is judged against. Findings: `reached_no_source`, the headline policy's
    evaluation reached no source at all; `below_initial`, its objective's 95% interval lies wholly below theta0's
    (apart, not merely lower: noise alone rarely parts two 95% intervals), judged from JUDGED episodes on: the
    bootstrap interval of one episode is that episode, and two single episodes are apart by chance."""
    params = setup.params
    initial = initial_objective(setup)
    findings = []
    if reached_none == 1.0:
        findings.append({"check": "reached_no_source", "message": _no_source(params, initial)})
    if params.train.eval_episodes >= JUDGED and objective_figure["high"] < initial["low"]:
        findings.append({"check": "below_initial", "message": _below_initial(params, objective_figure, initial)})
    return {"degenerate": bool(findings), "findings": findings, "initial_objective": initial}


JUDGED = 30  # evaluation episodes from which two 95% bootstrap intervals apart say more than chance


def degenerate_findings(summary: dict) -> list[dict]:
    """A summary.json's degenerate findings ({"check", "message"}); none for one written before runs were
    diagnosed."""
    return (summary.get("diagnosis") or {}).get("findings", [])


def _figure(f: dict) -> str:
    return f"{f['value']:.1f} [{f['low']:.1f}, {f['high']:.1f}]"


def _no_source(params: RiskplanConf, initial: dict) -> str:
    """What reaching no source says, and its likely cause: the world when theta0 reached none either, else the
    training."""
    episodes = f"reached no source in its {params.train.eval_episodes} evaluation episodes"
    if initial["reached_none"] == 1.0:
        return (
            f"{episodes}, nor did the initial policy in {initial['episodes']}: the sources are likely out of "
            f"reach within world.horizon={params.world.horizon} moves of the start, or their signals too narrow to "
            f"lead there (riskplan check prints each source's distance); move the start or the sources, widen the "
            f"signals' covariance, lengthen the horizon or change train.theta0"
        )
    cause = _fault_cause(params) or (
        "a risk-averse measure that found the regions' rewards safer than any source's, or too large a step size "
        "(train.step_size)"
    )
    return (
        f"{episodes}, where the initial policy reached one in {1 - initial['reached_none']:.1%}: it learned to go "
        f"nowhere, likely {cause}"
    )


def _below_initial(params: RiskplanConf, final: dict, initial: dict) -> str:
    cause = _fault_cause(params) or (
        f"too large a step size (train.step_size) or too few samples for a steady gradient "
        f"(train.samples={params.train.samples})"
    )
    return (
        f"its objective ({final['measure']}) ended below the initial policy's: {_figure(final)} against "
        f"{_figure(initial)} (95% intervals apart): training made it worse, likely {cause}"
    )


def _fault_cause(params: RiskplanConf) -> str | None:
    """The likely cause where faulty robots send values (stuck or Byzantine) into the plain mean, which resists none
    of them: the step size or the samples would be the wrong advice there."""
    senders = [f for f in faults_of(params.team) if f.kind in (FaultKind.stuck, FaultKind.byzantine)]
    if not senders or params.team.aggregate != Aggregate.mean:
        return None
    which = ", ".join(f"robot {f.robot}: {f.kind.value}" for f in senders)
    return (
        f"the faulty robot{'s' if len(senders) > 1 else ''} of team.faults ({which}) pulling the healthy ones "
        f"through team.aggregate=mean, which "
        f"resists none; team.aggregate=trimmed_mean or wmsr with team.trim={len(senders)} resists them where the graph "
        f"is robust enough (riskplan check says)"
    )


def _objective(risk, z: np.ndarray, figures: dict, params) -> dict:
    """{"measure", "value", "low", "high"} of the trained measure on the evaluation episodes z: the figures' own
    where the measure is one of them (CVaR at the reported beta, the mean), else from the same bootstrap resamples."""
    measure, values = risk_spec(risk)
    figure = measure.reported(values, figures, params.risk.beta)
    if figure is not None:
        return {"measure": measure.name, **figure}
    return objective_interval(z, risk, params.train.bootstrap, params.seed)[0]


def robot_objectives(
    setup: RunSetup, thetas: np.ndarray, evaluation: Columns, headline: dict
) -> tuple[list[dict], dict]:
    """Each robot's objective at the network average theta-bar (from its own start, by its own measure: the team
    objective's terms) and the team objective, their sum over the healthy robots (team.faults), with bootstrap
    intervals from the same resamples.

    theta-bar's episodes from robot 0's start are eval.parquet's robot -1 rows; each other start gets episodes of
    its own stream (not saved). A centralized run is a team of one: its entry is the run's own objective. When
    every robot shares one start and one measure (the common case), each term is the headline `objective` and the
    team objective is that many times it, interval included: no further bootstrap."""
    params = setup.params
    risks = robot_risks(params)
    cells = starts(setup)
    healthy = final_health(setup)
    pairs = {_term(c, r): (int(c), r) for c, r in zip(cells, risks)}
    if len(pairs) == 1 and risks[0] == params.risk:  # one term, the headline's: the robots share it
        x, y = setup.world.xy(int(cells[0]))
        robots = [
            {"robot": i, "start": [int(x), int(y)], "healthy": bool(ok), "objective_at_average": headline}
            for i, ok in enumerate(healthy)
        ]
        terms = int(healthy.sum())
        return robots, {k: terms * headline[k] for k in ("value", "low", "high")}
    returns = _returns_at_average(setup, thetas, evaluation, cells)
    with_intervals = len(pairs) <= ROBOT_INTERVALS
    figures = _term_figures({key: (returns[cell], risk) for key, (cell, risk) in pairs.items()}, params, with_intervals)
    robots, total, resamples = [], 0.0, np.zeros(params.train.bootstrap) if with_intervals else None
    for i, (cell, risk) in enumerate(zip(cells, risks)):
        figure, values = figures[_term(cell, risk)]
        x, y = setup.world.xy(int(cell))
        robots.append(
            {"robot": i, "start": [int(x), int(y)], "healthy": bool(healthy[i]), "objective_at_average": figure}
        )
        if not healthy[i]:  # a faulty robot's objective is reported, not counted in the team's
            continue
        total += figure["value"]
        if with_intervals:
            resamples = resamples + values
    team = {"value": total}
    if with_intervals:
        low, high = np.percentile(resamples, [2.5, 97.5])
        team |= {"low": float(low), "high": float(high)}
    check_finite("the team objective", *[v for v in team.values()])
    return robots, team


def _term(cell, risk: RiskConf) -> tuple[int, str]:
    """A team objective's term: a start cell and a risk node (robots that share both share the term)."""
    return int(cell), json.dumps(as_dict(risk), sort_keys=True)


def _returns_at_average(
    setup: RunSetup, thetas: np.ndarray, evaluation: Columns, cells: np.ndarray
) -> dict[int, np.ndarray]:
    """theta-bar's total rewards from each robot's start cell: eval.parquet's from robot 0's, fresh episodes of a
    stream of their own from each other start."""
    params, count = setup.params, setup.params.train.eval_episodes
    headline_robot = AVERAGE if setup.team else 0
    average = network_average(setup, thetas)[None, :]
    returns = {int(cells[0]): evaluation["total_reward"][evaluation["robot"] == headline_robot]}
    for q, cell in enumerate(dict.fromkeys(int(c) for c in cells if int(c) not in returns)):
        parts = []
        for first in range(0, count, EVAL_BATCH):
            key = np.array([rng.stream_key(params.seed, rng.EVAL, setup.robots + 1 + q, first)], dtype=np.uint64)
            size = min(EVAL_BATCH, count - first)
            batch = simulator(setup)(setup.world, setup.kernel, average, np.array([cell]), key, size, scores=False)
            parts.append(batch.total_reward)
        returns[cell] = np.concatenate(parts)
    return returns


def _term_figures(terms: dict, params: RiskplanConf, with_intervals: bool) -> dict:
    """Each term's (objective figure, its bootstrap resamples) from its (returns, risk node), or without intervals
    (figure, None); the terms bootstrap together (objective_intervals: each resample drawn once for all)."""
    for returns, _ in terms.values():
        check_finite("the evaluation's total reward", returns)
    if with_intervals:
        zs, risks = zip(*terms.values())
        return dict(zip(terms, objective_intervals(list(zs), list(risks), params.train.bootstrap, params.seed)))
    return {
        key: ({"measure": risk_spec(risk).measure.name, "value": float(objective(returns, risk))}, None)
        for key, (returns, risk) in terms.items()
    }
