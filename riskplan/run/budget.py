"""Memory and time a run will need, estimated from its sizes before anything is allocated (riskplan.util.limits checks).

`build_setup` calls `check` twice: once on the raw config sizes, before the world's arrays exist (a 10^10-cell
grid must fail here, not while allocating), and once on the built world and network. Everything is computed in
Python floats from Python ints, never numpy, so a key of 10^30 (or 10^400) is a number, not an overflow.

The bytes per unit are measured peaks of `riskplan train` (tracemalloc and max RSS over growing sizes, M = 2
sources, rounded up), and the costs are in trajectory-step equivalents of limits.STEPS_PER_SECOND. P is the length
of theta: M for the paper's policy, M + the extra features (risky, stay) for a features policy, C * 5 for a
tabular one (policy.kind, policy.features):
  grid        (200 + 40 F) B per cell (next_cell, signals, features; F = P, or M for a tabular policy's seed)
  tables      (40 + 40 P) B per cell and robot (move probabilities and scores of every robot's policy; a tabular
              policy.s: 160 B, its logits, probabilities and bins)
  batch       (48 + 16 P) B per episode of the largest iteration, per robot (totals, scores, sort): a tabular
              policy's scores are C * 5 floats per episode, W C 5 8 B per robot
  gradients   P / 4 steps per training episode (the scores' product with the weights: a tabular policy's C * 5)
  evaluation  160 B per episode and evaluated policy (eval.parquet's frame, concatenated), and a tabular
              policy's scores (8 P B per episode of a kernel call, EVAL_BATCH at most, unless it asks for none)
  paths       250 B and 400 steps per recorded step (trajectories.parquet, the /paths replay in run.mcap)
  rows        (2000 + 200 P) B and 2000 steps per metrics row (kept for the checkpoint and the log)
  messages    (64 + 80 P) B per (delay slot, round, ordered robot pair) of the consensus buffers (and their
              checkpoint), twice that with gradient tracking, 100 steps each per checkpoint
  network     (1000 + 400 P) B and 300 steps per ordered robot pair (weights, checks, logged graph)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from riskplan.config.keys import KEYS
from riskplan.config.schema import Graph, Order
from riskplan.util import limits

EVAL_BATCH = 100_000  # episodes per kernel call during evaluation (training uses it; it bounds memory)
ITERATION_STEPS = 10_000  # fixed cost of an iteration (gradient, logging, fsync-free bookkeeping)
# The paper's defaults: the key named in a message is the one furthest above its default.
DEFAULTS = {
    KEYS.world.size: 144.0,
    KEYS.team.robots: 1.0,
    KEYS.train.samples: 6000.0,
    KEYS.train.samples_growth: 1.0,
    KEYS.train.iterations: 200.0,
    KEYS.world.horizon: 20.0,
    KEYS.train.eval_episodes: 100_000.0,
    KEYS.train.bootstrap: 1000.0,
    KEYS.train.paths: 20.0,
    KEYS.team.delay.max: 1.0,
    KEYS.team.consensus_rounds: 1.0,
    KEYS.team.resample: 101.0,
}


@dataclass(frozen=True)
class Sizes:
    """The sizes a run's cost depends on (Python numbers of any size)."""

    width: int
    height: int
    sources: int  # M
    robots: int  # N
    horizon: int  # K
    iterations: int  # L
    samples: int  # W
    growth: float  # g: W_l = ceil(W (1 + l)^g)
    eval_episodes: int
    bootstrap: int
    paths: int
    delay: int  # B0
    rounds: int  # R
    resample: int
    geometric: bool
    checkpoint_every: int
    tracking: bool = False  # team.order=gradient_tracking: trackers travel with theta (about twice the buffers)
    params: int = 0  # P, the length of theta (0: M, the paper's policy)
    tabular: bool = False  # policy.kind=tabular: theta is the (C * 5,) table of logits


def sizes_of(cfg, width: int, height: int, sources: int, robots: int) -> Sizes:
    """Sizes from a schema-checked config (cfg.train, cfg.world, cfg.team) and the validated grid and team."""
    train, team = cfg.train, cfg.team
    policy = getattr(cfg, "policy", None)
    tabular = policy is not None and str(policy.kind) == "tabular"
    features = ["signals"] if policy is None else [str(f) for f in policy.features]
    if tabular:
        params = int(width) * int(height) * 5
    else:
        params = max(int(sources), 1) * ("signals" in features) + sum(f != "signals" for f in features)
    return Sizes(
        width,
        height,
        max(int(sources), 1),
        robots,
        int(cfg.world.horizon),
        int(train.iterations),
        int(train.samples),
        float(train.samples_growth),
        int(train.eval_episodes),
        int(train.bootstrap),
        int(train.paths),
        int(team.delay.max),
        int(team.consensus_rounds),
        int(team.resample),
        team.graph == Graph.random_geometric,
        int(train.checkpoint_every),
        team.order == Order.gradient_tracking,
        params,
        tabular,
    )


def check(sizes: Sizes) -> None:
    """BadInput (through riskplan.util.limits) when the run would need more memory or time than allowed."""
    memory, time = estimate(sizes)
    need = sum(amount for amount, _, _ in memory)
    if not need <= limits.memory_budget()[0]:
        key, what = _culprit(memory)
        limits.check_memory(key, need, what)
    steps = sum(amount for amount, _, _ in time)
    if not steps / limits.STEPS_PER_SECOND <= limits.time_budget():
        key, what = _culprit(time)
        limits.check_time(key, steps / limits.STEPS_PER_SECOND, what)


Scale = tuple[str, object, float]  # (key, shown value, ratio to its default): what a part scales with
Part = tuple[float, str, list[Scale]]  # (amount, description, what it scales with)


def estimate(s: Sizes) -> tuple[list[Part], list[Part]]:
    """(memory parts in bytes, time parts in trajectory steps), each with what it is and the keys it scales with."""
    counts = _counts(s)
    scales = _scales(s, counts)
    return _memory(s, counts, scales), _time(s, counts, scales)


@dataclass(frozen=True)
class _Counts:
    """What a run's parts are made of, as floats (see the module's table)."""

    cells: float
    n: float  # N
    k: float  # K
    p: float  # the length of theta
    f: float  # the features of each (cell, move) the world keeps
    team: bool
    policies: float  # evaluated policies: evaluation adds the network average
    rows: float  # metrics rows per iteration
    w_last: float  # episodes per robot in the largest iteration
    w_total: float  # episodes per robot over all iterations
    slots: float  # consensus buffer slots
    pairs: float  # ordered robot pairs
    checkpoints: float
    record: float  # recorded path steps
    tables: float  # policy tables built


def _counts(s: Sizes) -> _Counts:
    cells = _prod(s.width, s.height)
    m, n, k = float(s.sources), _f(s.robots), _f(s.horizon)
    p = _f(s.params) if s.params else m
    team = s.robots > 1
    policies = n + 1.0 if team else 1.0
    return _Counts(
        cells=cells,
        n=n,
        k=k,
        p=p,
        f=m if s.tabular else p,
        team=team,
        policies=policies,
        rows=n + 1.0 if team else 1.0,
        w_last=_last_samples(s.samples, s.growth, s.iterations),
        w_total=_total_samples(s.samples, s.growth, s.iterations),
        slots=_prod(_f(s.delay) + 1.0, s.rounds, n, n),
        pairs=_prod(n, n),
        checkpoints=_f(s.iterations) / max(_f(s.checkpoint_every), 1.0) + 1.0,
        record=_prod(2.0, policies, s.paths, k + 1.0),
        tables=_f(s.iterations) * n + policies * (_f(s.eval_episodes) / EVAL_BATCH + 3.0),
    )


@dataclass(frozen=True)
class _Scales:
    """Each key a part can scale with, as a Scale."""

    size: Scale
    robots: Scale
    samples: Scale
    growth: Scale
    iterations: Scale
    horizon: Scale
    evals: Scale
    boot: Scale
    paths: Scale
    delay: Scale
    rounds: Scale
    resample: Scale


def _scales(s: Sizes, c: _Counts) -> _Scales:
    return _Scales(
        size=(KEYS.world.size, f"[{show(s.width)}, {show(s.height)}]", c.cells / DEFAULTS[KEYS.world.size]),
        robots=(KEYS.team.robots, show(s.robots), c.n / DEFAULTS[KEYS.team.robots]),
        samples=(KEYS.train.samples, show(s.samples), _f(s.samples) / DEFAULTS[KEYS.train.samples]),
        growth=(KEYS.train.samples_growth, f"{s.growth:g}", c.w_last / max(_f(s.samples), 1.0)),
        iterations=(KEYS.train.iterations, show(s.iterations), _f(s.iterations) / DEFAULTS[KEYS.train.iterations]),
        horizon=(KEYS.world.horizon, show(s.horizon), c.k / DEFAULTS[KEYS.world.horizon]),
        evals=(
            KEYS.train.eval_episodes,
            show(s.eval_episodes),
            _f(s.eval_episodes) / DEFAULTS[KEYS.train.eval_episodes],
        ),
        boot=(KEYS.train.bootstrap, show(s.bootstrap), _f(s.bootstrap) / DEFAULTS[KEYS.train.bootstrap]),
        paths=(KEYS.train.paths, show(s.paths), _f(s.paths) / DEFAULTS[KEYS.train.paths]),
        delay=(KEYS.team.delay.max, show(s.delay), _f(s.delay) + 1.0),
        rounds=(KEYS.team.consensus_rounds, show(s.rounds), _f(s.rounds)),
        resample=(KEYS.team.resample, show(s.resample), (_f(s.resample) + 1.0) / DEFAULTS[KEYS.team.resample]),
    )


def _memory(s: Sizes, c: _Counts, on: _Scales) -> list[Part]:
    """The memory parts, in bytes."""
    p, grid = c.p, _grid(s)
    return [
        (_prod(c.cells, 200.0 + 40.0 * c.f), grid, [on.size]),
        (
            _prod(c.cells, c.n, 160.0 if s.tabular else 40.0 + 40.0 * p),
            f"{grid}'s policy tables for {show(s.robots)} robot(s)",
            [on.size, on.robots],
        ),
        (
            _prod(c.n, c.w_last, 48.0 + 16.0 * p),
            f"its training batches ({_num(c.w_last)} episodes per robot in the largest iteration"
            + (f", each with a tabular policy's {_num(p)} scores)" if s.tabular else ")"),
            [on.samples, on.growth, on.robots] + ([on.size] if s.tabular else []),
        ),
        (
            _prod(c.policies, s.eval_episodes, 160.0)
            + (_prod(min(_f(s.eval_episodes), EVAL_BATCH), p, 8.0) if s.tabular else 0.0),
            f"its evaluation ({show(s.eval_episodes)} episodes per policy)",
            [on.evals, on.robots] + ([on.size] if s.tabular else []),
        ),
        (_prod(c.record, 250.0), f"its recorded paths ({_num(c.record)} steps)", [on.paths, on.horizon, on.robots]),
        (
            _prod(s.iterations, c.rows, 2000.0 + 200.0 * p),
            f"its metrics ({_num(_prod(s.iterations, c.rows))} rows)",
            [on.iterations, on.robots],
        ),
        (
            _prod(c.slots, (64.0 + 80.0 * p) * (2.0 if s.tracking else 1.0)),
            f"its consensus message buffers ({_num(c.slots)} slots)",
            [on.delay, on.rounds, on.robots],
        ),
        (_prod(c.pairs, 1000.0 + 400.0 * p), f"its network of {show(s.robots)} robots", [on.robots]),
        (
            _prod(s.bootstrap, 100.0) + _prod(s.eval_episodes, 16.0),
            f"its bootstrap ({show(s.bootstrap)} resamples)",
            [on.boot, on.evals],
        ),
    ]


def _time(s: Sizes, c: _Counts, on: _Scales) -> list[Part]:
    """The time parts, in trajectory steps."""
    p, geometric = c.p, s.geometric and c.team
    return [
        (
            _prod(c.n, c.w_total, c.k),
            f"its training ({_num(_prod(c.n, c.w_total))} episodes of up to {show(s.horizon)} moves)",
            [on.samples, on.iterations, on.growth, on.robots, on.horizon],
        ),
        (
            _prod(c.n, c.w_total, p / 4.0) if s.tabular else 0.0,
            f"its gradients ({_num(_prod(c.n, c.w_total))} episodes' scores of {_num(p)} entries)",
            [on.samples, on.iterations, on.growth, on.robots, on.size],
        ),
        (
            _prod(c.cells, 100.0) + _prod(c.tables, c.cells, 10.0),
            f"{_grid(s)}'s policy tables ({_num(c.tables)} of them)",
            [on.size, on.iterations, on.robots],
        ),
        (
            _prod(s.iterations, ITERATION_STEPS + 2000.0 * c.rows),
            f"its {show(s.iterations)} iterations",
            [on.iterations, on.robots],
        ),
        (
            _prod(c.policies, s.eval_episodes, c.k),
            f"its evaluation ({show(s.eval_episodes)} episodes per policy)",
            [on.evals, on.horizon, on.robots],
        ),
        (
            _prod(s.bootstrap, s.eval_episodes),
            f"its bootstrap ({show(s.bootstrap)} resamples of {show(s.eval_episodes)} episodes)",
            [on.boot, on.evals],
        ),
        (_prod(c.record, 400.0), f"its recorded paths ({_num(c.record)} steps)", [on.paths, on.horizon, on.robots]),
        (
            _prod(s.iterations, s.rounds, c.pairs, p + 1.0, 5.0) if c.team else 0.0,
            f"its consensus rounds ({show(s.rounds)} per iteration)",
            [on.rounds, on.robots, on.iterations],
        ),
        (
            _prod(c.slots, c.checkpoints, 100.0),
            f"its checkpoints of the consensus buffers ({_num(c.slots)} slots)",
            [on.delay, on.rounds, on.robots],
        ),
        (
            _prod(c.pairs, 300.0) + (_prod(_f(s.resample) + 1.0, c.pairs, 5.0) if geometric else 0.0),
            f"its network of {show(s.robots)} robots"
            + (f" (up to {show(s.resample + 1)} random_geometric draws)" if geometric else ""),
            [on.robots] + ([on.resample] if s.geometric else []),
        ),
    ]


def _grid(s: Sizes) -> str:
    return f"the {show(s.width)} x {show(s.height)} grid"


def _culprit(parts: list[Part]) -> tuple[str, str]:
    """(key, what) for the largest part: the key furthest above its default, and the part's description."""
    _amount, description, keys = max(parts, key=lambda part: part[0])
    key, value, _ = max(keys, key=lambda entry: entry[2])
    return key, f"got {value}; the run, mostly {description},"


def _f(value) -> float:
    """A Python number as a float, capped at 1e300 (a 400-digit int is not an OverflowError)."""
    try:
        return min(float(value), 1e300)
    except OverflowError:
        return 1e300


def _prod(*values) -> float:
    """A product of non-negative sizes in floats: 0 when any factor is 0 (never 0 * inf), else possibly inf."""
    floats = [_f(v) for v in values]
    if any(v == 0 for v in floats):
        return 0.0
    return math.prod(floats)


def _last_samples(samples: int, growth: float, iterations: int) -> float:
    """W at the last iteration, ceil(W L^g), computed in logs so that it cannot overflow."""
    log = math.log(_f(samples)) + growth * math.log(max(_f(iterations), 1.0))
    return math.exp(min(log, 690.0))


def _total_samples(samples: int, growth: float, iterations: int) -> float:
    """sum_l W_l for l < L, bounded above by W (L^(g+1) / (g+1) + L^g) + L (the ceilings)."""
    lsize = max(_f(iterations), 1.0)
    log = math.log(_f(samples)) + (growth + 1.0) * math.log(lsize) - math.log(growth + 1.0)
    return math.exp(min(log, 690.0)) + _last_samples(samples, growth, iterations) + lsize


def show(value: int) -> str:
    """A whole number as typed when short, else in float notation (a 10^30 key stays one short line)."""
    if abs(value) < 10**12:
        return str(value)
    return _num(_f(value)) if abs(value) < 10**300 else f"about 2^{value.bit_length()}"


def _num(value: float) -> str:
    """A float count, short."""
    return f"{value:.0f}" if value < 1e12 else f"{value:.3g}"
