"""Batched Monte Carlo rollouts: many policies x many episodes in one numba kernel.

This module is the Python side: `make_kernel` packs a World and its Policy once per run (`KernelArrays`, whose `tables`
the kernels take as one argument), `simulate` computes each call's policy tables and move bins and runs the episode
kernel of riskplan.engine.rollout_kernels on them, and returns the outcomes as an `EpisodeBatch`.

Each episode draws from its own counter-based stream (riskplan.engine.rng), so numbers do not depend on threads or
chunking. Static worlds of a features policy with affine region rewards (`affine_form`) run
`rollout_kernels._simulate_affine` (the only episode kernel a paper run compiles: its sampled paths too); the rest
(a tabular policy, mobile sources, other rewards, `reference=True`) run `rollout_kernels._simulate`, the general loop.

Policies (riskplan.engine.policy.Policy, packed by `make_kernel`): a features policy's moves come from per-policy
tables of (cell, move) for static sources, whatever its features, filled only for the cells its episodes can reach
(`reach`: a 256 x 256 map costs what the few hundred cells within the horizon cost); with mobile sources the kernel
computes the signals at each step. A tabular policy's moves come from its table in every case (it ignores where the
sources are, so mobile sources need nothing else), and its score, a (C * 5,) vector per episode, is accumulated by
the kernel straight into the batch's scores.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from riskplan.engine import distributions as D
from riskplan.engine.policy import Policy, make_policy, tables, tabular_tables
from riskplan.engine.reachability import distances
from riskplan.engine.rollout_kernels import KernelTables, _bins, _simulate, _simulate_affine
from riskplan.engine.world import World


@dataclass(frozen=True)
class EpisodeBatch:
    """Outcome of P policies x W episodes, flattened policy-major (episode e of policy p at p * W + e)."""

    total_reward: np.ndarray  # (P*W,) float64
    score: np.ndarray  # (P*W, len(theta)) float64: d log f(xi) / d theta (M for the paper's policy, C*5 for tabular)
    risky_steps: np.ndarray  # (P*W,) int64
    source_reached: np.ndarray  # (P*W,) int64, -1 for none
    steps: np.ndarray  # (P*W,) int64: moves made
    path_cells: np.ndarray | None = None  # (P*W, K+1) int64 when recorded; -1 after the episode ended
    path_rewards: np.ndarray | None = None  # (P*W, K+1) float64 when recorded


@dataclass(frozen=True)
class KernelArrays:
    """A run's world and policy packed once: the arrays the episode kernels take (`tables`), and what the policy's
    per-iteration tables read (`features`)."""

    tables: KernelTables  # the world's and policy's arrays and flags, as the numba (and CUDA) kernels take them
    features: np.ndarray  # (C, 5, F): the policy's move features (a tabular policy's: its seed's), for policy.tables
    reached: dict = field(default_factory=dict, compare=False, repr=False)  # `reach` by start cells, remembered


def affine_form(dist: D.Dist) -> tuple[float, float, float, float, float] | None:
    """(c, w, s, lo, hi) with dist = clip(c + w U + s N, lo, hi) in law, U ~ U(0, 1) and N ~ N(0, 1) independent.

    Constants, one uniform, any number of normals (independent normals sum to one normal), scales and sums, with at
    most one clip at the root; None for anything else (a bernoulli, a mixture, two uniforms, an inner clip).
    """
    lo, hi = -math.inf, math.inf
    if dist.kind == "clip":
        (lo, hi), dist = dist.params, dist.children[0]

    def linear(node: D.Dist) -> tuple[float, float, float, int] | None:  # (c, w, variance of the normal, uniforms)
        if node.kind == "constant":
            return node.params[0], 0.0, 0.0, 0
        if node.kind == "uniform":
            return node.params[0], node.params[1] - node.params[0], 0.0, 1
        if node.kind == "normal":
            return node.params[0], 0.0, node.params[1] ** 2, 0
        if node.kind == "scale":
            inner = linear(node.children[0])
            k = node.params[0]
            return None if inner is None else (k * inner[0], k * inner[1], k * k * inner[2], inner[3])
        if node.kind == "sum":
            parts = [linear(child) for child in node.children]
            if any(part is None for part in parts):
                return None
            return tuple(sum(part[i] for part in parts) for i in range(4))  # type: ignore[return-value]
        return None

    form = linear(dist)
    if form is None or form[3] > 1:
        return None
    return form[0], form[1], math.sqrt(form[2]), lo, hi


def make_kernel(world: World, policy: Policy | None = None) -> KernelArrays:
    """Pack a World and its Policy (default: the paper's, theta weighting the M signals) for `simulate`."""
    policy = make_policy(world) if policy is None else policy
    source_at = np.full(world.cells, -1, dtype=np.int64)
    for j in range(world.sources - 1, -1, -1):  # the first source listed wins a shared cell
        source_at[world.source_cells[j]] = j
    forms = [affine_form(dist) for dist in world.region_rewards]
    affine = all(form is not None for form in forms)
    cell_affine = np.tile(np.array([0.0, 0.0, 0.0, -math.inf, math.inf]), (world.cells, 1))  # no region: reward 0
    cell_risky = np.zeros(world.cells, dtype=np.int64)
    for cell, region in enumerate(world.region_of):
        if region >= 0:
            cell_risky[cell] = world.region_risky[region]
            if affine:
                cell_affine[cell] = forms[region]
    region_off, region_ops, region_par = D.pack_programs(list(world.region_rewards))
    source_off, source_ops, source_par = D.pack_programs(list(world.source_rewards))
    tables = KernelTables(  # field by field, by name: no array can slip into another's place
        next_cell=world.next_cell,
        region_of=world.region_of,
        region_risky=world.region_risky,
        reg_off=region_off,
        reg_ops=region_ops,
        reg_par=region_par,
        src_off=source_off,
        src_ops=source_ops,
        src_par=source_par,
        source_at=source_at,
        source_cells=world.source_cells,
        source_motion=world.source_motion,
        source_amplitude=world.source_amplitude,
        source_precision=world.source_precision,
        cell_affine=cell_affine,
        cell_risky=cell_risky,
        extra_at=policy.extra_at,
        extras=np.ascontiguousarray(policy.extras, dtype=np.float64),
        height=int(world.height),
        width=int(world.width),
        horizon=int(world.horizon),
        stop_at_source=bool(world.stop_at_source),
        mobile=bool(world.mobile),
        affine=bool(affine),
        draw_uniform=affine and bool(np.any(cell_affine[:, 1] != 0.0)),
        draw_normal=affine and bool(np.any(cell_affine[:, 2] != 0.0)),
        tabular=bool(policy.tabular),
        signal_at=int(policy.signal_at),
    )
    return KernelArrays(tables=tables, features=policy.move_features(world))


def simulate(
    world: World,
    kernel: KernelArrays,
    thetas: np.ndarray,
    starts: np.ndarray,
    keys: np.ndarray,
    episodes: int,
    record: bool = False,
    reference: bool = False,
    scores: bool = True,
) -> EpisodeBatch:
    """Run `episodes` episodes for each policy p (theta thetas[p], start cell starts[p], stream key keys[p]).

    thetas is (P, len(theta)) for the kernel's policy (`make_kernel`); a tabular policy's scores are (P*W, C*5).
    `scores=False` skips a tabular policy's scores (EpisodeBatch.score is then (P*W, 0): evaluation has no use for W C 5
    floats); a features policy's few are always filled.

    `reference` runs every region reward through the program interpreter and normals by the inverse CDF of one
    uniform (no fast path). The same distributions from other numbers, slower; kept as the
    reference of tests/engine/test_kernel_fast_paths.py.
    """
    thetas = np.ascontiguousarray(thetas, dtype=np.float64)
    bins, score, probs = policy_tables(world, kernel, thetas, starts)
    outputs, path_cells, path_rewards = _outputs(kernel, thetas.shape[0] * episodes, thetas.shape[1], record, scores)
    paths = (path_cells, path_rewards) if record else (None, None)
    starts = np.asarray(starts, np.int64)
    keys = np.asarray(keys, np.uint64)
    arrays = (bins, score, starts, keys, episodes, record, *outputs, path_cells, path_rewards)  # either kernel's
    if kernel.tables.affine and not (kernel.tables.mobile or reference or kernel.tables.tabular):
        _simulate_affine(kernel.tables, *arrays)
    else:
        _simulate(kernel.tables, probs, thetas, reference, *arrays)
    return EpisodeBatch(*outputs, *paths)


def policy_tables(world: World, kernel: KernelArrays, thetas: np.ndarray, starts: np.ndarray):
    """What the episode kernels read of the policies: (move bins (P, C, 4), scores (P, C, 5, F), probabilities
    (P, C, 5)), a tabular policy's from its table (no scores: the kernel accumulates them), a features policy's for
    the cells its episodes can reach (none with mobile sources: their moves are computed at each step)."""
    if kernel.tables.tabular:
        cum, probs = tabular_tables(thetas, world.cells)
        return move_bins(cum), np.empty((0, 0, 0, 0)), probs
    cells = reach(kernel, starts)
    cum, score = tables(world, thetas, kernel.features, cells)
    return move_bins(cum, cells), score, np.empty((0, 0, 5))


def _outputs(kernel: KernelArrays, total: int, size: int, record: bool, scores: bool):
    """The kernels' output arrays for `total` episodes: (z, score, risky, reached, steps), then the paths' cells and
    rewards ((0, 0) unless `record`). A tabular policy's scores start at zero (the kernel adds into them)."""
    if kernel.tables.tabular:
        out_score = np.zeros((total, size if scores else 0))
    else:
        out_score = np.empty((total, size))
    counts = tuple(np.empty(total, dtype=np.int64) for _ in range(3))  # risky steps, source reached, steps
    width = kernel.tables.horizon + 1 if record else 0
    path_cells = np.full((total if record else 0, width), -1, dtype=np.int64)
    path_rewards = np.zeros((total if record else 0, width))
    return (np.empty(total), out_score, *counts), path_cells, path_rewards


def move_bins(cum: np.ndarray, cells: np.ndarray | None = None) -> np.ndarray:
    """`_bins` of every policy's (P, C, 5) cumulative move probabilities: (P, C, 4) integer bounds (of the listed
    `cells` only, the other rows unset, when given)."""
    bins = np.empty((cum.shape[0], cum.shape[1], 4), dtype=np.int64)
    cells = np.arange(cum.shape[1]) if cells is None else np.ascontiguousarray(cells, dtype=np.int64)
    _bins(cum, bins, cells)
    return bins


def reach(kernel: KernelArrays, starts: np.ndarray) -> np.ndarray:
    """The cells at which an episode from `starts` can pick a move (sorted): those within horizon - 1 moves of a
    start through next_cell. The kernel reads the policy tables at these cells only, so `simulate` fills only
    theirs (a 256 x 256 map whose episodes see a few hundred cells costs what those cost). Empty with mobile
    sources, whose moves the kernel computes at each step. Remembered per start cells."""
    if kernel.tables.mobile:
        return np.zeros(0, dtype=np.int64)
    key = np.unique(np.asarray(starts, dtype=np.int64)).tobytes()
    found = kernel.reached.get(key)
    if found is None:
        within = distances(kernel.tables.next_cell, np.frombuffer(key, dtype=np.int64), kernel.tables.horizon - 1)
        found = np.flatnonzero(within >= 0).astype(np.int64)
        found.flags.writeable = False
        if len(kernel.reached) >= REACH_MEMO:
            kernel.reached.clear()
        kernel.reached[key] = found
    return found


REACH_MEMO = 64  # start sets remembered per kernel (a team's, an environment's resets)
