"""Batched Monte Carlo rollouts: many policies x many episodes in one numba kernel.

numba (parallel, cached on disk) runs the whole episode loop in machine code: policy lookup, move sampling,
reward draws from the compiled distribution programs and score accumulation (eq. 10). Each episode draws from
its own counter-based stream (riskplan.engine.rng), so numbers do not depend on threads or chunking.

Fast paths (about 2x the interpreter-only kernel): a move is picked by integer compares of a draw's bits
(`_bins`); a region reward of the form clip(c + w U + s N) is drawn from per-cell coefficients without the program
interpreter or a branch on the region (`affine_form`), normals by the ziggurat (riskplan.engine.rng.next_normal); static
worlds of a features policy run `_simulate_affine`, a loop without the other cases (and the only episode kernel a
paper run compiles: its sampled paths too). `simulate(..., reference=True)`
runs the interpreter and the inverse-CDF normals everywhere: the same laws from other numbers, the tests' reference.

Policies (riskplan.engine.policy.Policy, packed by `make_kernel`): a features policy's moves come from per-policy
tables of (cell, move) for static sources, whatever its features, filled only for the cells its episodes can reach
(`reach`: a 256 x 256 map costs what the few hundred cells within the horizon cost); with mobile sources `_mobile_policy` computes the
signals at each step and adds the static extra features (risky, stay). A tabular policy's moves come from its table
in every case (it ignores where the sources are, so mobile sources need nothing else), and its score, a (C * 5,)
vector per episode, is accumulated step by step as e_(c, a) - mu(. | c) straight into the batch's scores, in
`_simulate` (the general loop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from riskplan.engine import distributions as D
from riskplan.engine.policy import Policy, make_policy, tables, tabular_tables
from riskplan.engine.rng import bits_uniform, episode_state, next_bits, next_normal, next_uniform, normal_quantile
from riskplan.engine.world import MAX_STACK, World

CHUNK = 64  # episodes per parallel work item: amortises the per-item scratch allocations


@dataclass(frozen=True)
class Batch:
    """Outcome of P policies x W episodes, flattened policy-major (episode e of policy p at p * W + e)."""

    total_reward: np.ndarray  # (P*W,) float64
    score: np.ndarray  # (P*W, len(theta)) float64: d log f(xi) / d theta (M for the paper's policy, C*5 for tabular)
    risky_steps: np.ndarray  # (P*W,) int64
    source_reached: np.ndarray  # (P*W,) int64, -1 for none
    steps: np.ndarray  # (P*W,) int64: moves made
    path_cells: np.ndarray | None = None  # (P*W, K+1) int64 when recorded; -1 after the episode ended
    path_rewards: np.ndarray | None = None  # (P*W, K+1) float64 when recorded


@dataclass(frozen=True)
class Kernel:
    """World arrays in the layout the kernel takes, built once per run."""

    next_cell: np.ndarray
    region_of: np.ndarray
    region_risky: np.ndarray
    region_programs: tuple[np.ndarray, np.ndarray, np.ndarray]
    source_programs: tuple[np.ndarray, np.ndarray, np.ndarray]
    source_at: np.ndarray
    source_cells: np.ndarray
    source_motion: np.ndarray
    source_amplitude: np.ndarray
    source_precision: np.ndarray
    height: int
    width: int
    horizon: int
    stop_at_source: bool
    mobile: bool
    cell_affine: np.ndarray  # (C, 5): the entered cell's reward as clip(c + w U + s N, lo, hi), rows (c, w, s, lo, hi)
    cell_risky: np.ndarray  # (C,) int64: 1 if entering the cell counts a risky step
    affine: bool  # every region's reward has that form: the kernel draws it without the program interpreter
    draw_uniform: bool  # some region's form has w != 0
    draw_normal: bool  # some region's form has s != 0
    features: np.ndarray  # (C, 5, F): the policy's move features (a tabular policy's: its seed's), for policy.tables
    tabular: bool = False  # theta is a (C * 5,) table of logits (policy.kind=tabular)
    signal_at: int = 0  # index in theta of the first signal weight, -1 for none (features policies)
    extra_at: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (E,) theta index per extra
    extras: np.ndarray = field(default_factory=lambda: np.zeros((0, 5, 0)))  # (C, 5, E): the extra features
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


def make_kernel(world: World, policy: Policy | None = None) -> Kernel:
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
    return Kernel(
        next_cell=world.next_cell,
        region_of=world.region_of,
        region_risky=world.region_risky,
        region_programs=D.pack_programs(list(world.region_rewards)),
        source_programs=D.pack_programs(list(world.source_rewards)),
        source_at=source_at,
        source_cells=world.source_cells,
        source_motion=world.source_motion,
        source_amplitude=world.source_amplitude,
        source_precision=world.source_precision,
        height=world.height,
        width=world.width,
        horizon=world.horizon,
        stop_at_source=world.stop_at_source,
        mobile=world.mobile,
        cell_affine=cell_affine,
        cell_risky=cell_risky,
        affine=affine,
        draw_uniform=affine and bool(np.any(cell_affine[:, 1] != 0.0)),
        draw_normal=affine and bool(np.any(cell_affine[:, 2] != 0.0)),
        features=policy.move_features(world),
        tabular=policy.tabular,
        signal_at=policy.signal_at,
        extra_at=policy.extra_at,
        extras=np.ascontiguousarray(policy.extras, dtype=np.float64),
    )


def simulate(
    world: World,
    kernel: Kernel,
    thetas: np.ndarray,
    starts: np.ndarray,
    keys: np.ndarray,
    episodes: int,
    record: bool = False,
    reference: bool = False,
    scores: bool = True,
) -> Batch:
    """Run `episodes` episodes for each policy p (theta thetas[p], start cell starts[p], stream key keys[p]).

    thetas is (P, len(theta)) for the kernel's policy (`make_kernel`); a tabular policy's scores are (P*W, C*5).
    `scores=False` skips a tabular policy's scores (Batch.score is then (P*W, 0): evaluation has no use for W C 5
    floats); a features policy's few are always filled.

    `reference` runs every region reward through the program interpreter and normals by the inverse CDF of one
    uniform (no fast path). The same distributions from other numbers, slower; kept as the
    reference of tests/test_kernel_speed_paths.py.
    """
    thetas = np.ascontiguousarray(thetas, dtype=np.float64)
    policies, size = thetas.shape
    if kernel.tabular:
        cum, probs = tabular_tables(thetas, world.cells)
        score = np.empty((0, 0, 0, 0))
        bins = move_bins(cum)
    else:  # the tables of the cells episodes can reach (none with mobile sources: their moves are computed)
        cells = reach(kernel, starts)
        cum, score = tables(world, thetas, kernel.features, cells)
        probs = np.empty((0, 0, 5))
        bins = move_bins(cum, cells)
    total = policies * episodes
    out_z = np.empty(total)
    if kernel.tabular:  # accumulated in place by the kernel, from zeros
        out_score = np.zeros((total, size if scores else 0))
    else:
        out_score = np.empty((total, size))
    out_risky = np.empty(total, dtype=np.int64)
    out_reached = np.empty(total, dtype=np.int64)
    out_steps = np.empty(total, dtype=np.int64)
    width = kernel.horizon + 1 if record else 0
    path_cells = np.full((total if record else 0, width), -1, dtype=np.int64)
    path_rewards = np.zeros((total if record else 0, width))
    paths = (path_cells, path_rewards) if record else (None, None)
    if kernel.affine and not (kernel.mobile or reference or kernel.tabular):
        _simulate_affine(
            bins,
            score,
            np.asarray(starts, np.int64),
            np.asarray(keys, np.uint64),
            episodes,
            kernel.next_cell,
            kernel.cell_affine,
            kernel.cell_risky,
            kernel.draw_uniform,
            kernel.draw_normal,
            *kernel.source_programs,
            kernel.source_at,
            kernel.horizon,
            kernel.stop_at_source,
            out_z,
            out_score,
            out_risky,
            out_reached,
            out_steps,
            record,
            path_cells,
            path_rewards,
        )
        return Batch(out_z, out_score, out_risky, out_reached, out_steps, *paths)
    _simulate(
        bins,
        score,
        probs,
        kernel.tabular,
        thetas,
        kernel.signal_at,
        kernel.extra_at,
        kernel.extras,
        np.asarray(starts, np.int64),
        np.asarray(keys, np.uint64),
        episodes,
        kernel.next_cell,
        kernel.region_of,
        kernel.region_risky,
        *kernel.region_programs,
        *kernel.source_programs,
        kernel.source_at,
        kernel.source_cells,
        kernel.source_motion,
        kernel.source_amplitude,
        kernel.source_precision,
        kernel.height,
        kernel.width,
        kernel.horizon,
        kernel.stop_at_source,
        kernel.mobile,
        record,
        reference,
        kernel.affine and not reference,
        kernel.cell_affine,
        kernel.cell_risky,
        kernel.draw_uniform,
        kernel.draw_normal,
        out_z,
        out_score,
        out_risky,
        out_reached,
        out_steps,
        path_cells,
        path_rewards,
    )
    return Batch(out_z, out_score, out_risky, out_reached, out_steps, *paths)


@njit(cache=True, inline="always")
def _affine_reward(cell_affine, cell, draw_uniform, draw_normal, state):
    """The entered cell's reward clip(c + w U + s N, lo, hi) from its coefficients; (reward, new state)."""
    u = 0.0
    g = 0.0
    if draw_uniform:
        state, u = next_uniform(state)
    if draw_normal:
        state, g = next_normal(state)
    reward = min(
        max(cell_affine[cell, 0] + cell_affine[cell, 1] * u + cell_affine[cell, 2] * g, cell_affine[cell, 3]),
        cell_affine[cell, 4],
    )
    return reward, state


@njit(cache=True)
def _draw(ops, params, first, last, stack, state, inverse_normal=False):
    """Run one postfix reward program (riskplan.engine.distributions) and return (value, state).

    Normal draws come from the ziggurat (riskplan.engine.rng.next_normal), or with `inverse_normal` from the inverse CDF
    of one uniform (the slower sampler used before; kept as the tests' reference).

    A call for a source's reward (once per episode): inlined there too, it tripled `_simulate`'s compile time (the
    first run after an install). Every kernel passes `inverse_normal`, so one specialisation serves them all.
    """
    top = 0
    for i in range(first, last):
        op = ops[i, 0]
        if op == D.OP_CONST:
            stack[top] = params[i, 0]
            top += 1
        elif op == D.OP_UNIFORM:
            state, u = next_uniform(state)
            stack[top] = params[i, 0] + (params[i, 1] - params[i, 0]) * u
            top += 1
        elif op == D.OP_NORMAL:
            if inverse_normal:
                state, u = next_uniform(state)
                g = normal_quantile(u)
            else:
                state, g = next_normal(state)
            stack[top] = params[i, 0] + params[i, 1] * g
            top += 1
        elif op == D.OP_BERNOULLI:
            state, u = next_uniform(state)
            stack[top] = 1.0 if u < params[i, 0] else 0.0
            top += 1
        elif op == D.OP_SCALE:
            stack[top - 1] *= params[i, 0]
        elif op == D.OP_CLIP:
            stack[top - 1] = min(max(stack[top - 1], params[i, 0]), params[i, 1])
        elif op == D.OP_SUM:
            n = ops[i, 1]
            acc = 0.0
            for k in range(n):
                acc += stack[top - 1 - k]
            top -= n
            stack[top] = acc
            top += 1
        else:  # OP_MIXTURE: n values, then their n normalised weights, on the stack
            n = ops[i, 1]
            state, u = next_uniform(state)
            pick = n - 1
            acc = 0.0
            for k in range(n):
                acc += stack[top - n + k]
                if u < acc:
                    pick = k
                    break
            value = stack[top - 2 * n + pick]
            top -= 2 * n
            stack[top] = value
            top += 1
    return stack[0 if top == 0 else top - 1], state


# `_draw` inlined, for `_simulate`'s region reward of a non-affine world, drawn at every step: a call there halves
# the kernel's speed. Not cached itself: its code is compiled into the kernel's.
_draw_inline = njit(inline="always")(_draw.py_func)


@njit(cache=True, inline="always")
def _pick(cum, u):
    """The move whose bin of the cumulative probabilities (cum[4] = 1) holds u: counted without branches.

    Counting the bins below u gives the index a linear search would, but a random move is no longer a branch the
    CPU mispredicts: ~20% faster rollouts.
    """
    return (u > cum[0]) + (u > cum[1]) + (u > cum[2]) + (u > cum[3])


def move_bins(cum: np.ndarray, cells: np.ndarray | None = None) -> np.ndarray:
    """`_bins` of every policy's (P, C, 5) cumulative move probabilities: (P, C, 4) integer bounds (of the listed
    `cells` only, the other rows unset, when given)."""
    bins = np.empty((cum.shape[0], cum.shape[1], 4), dtype=np.int64)
    if cells is None:
        _bins(cum, bins)
    else:
        _bins_at(cum, bins, np.ascontiguousarray(cells, dtype=np.int64))
    return bins


def reach(kernel: Kernel, starts: np.ndarray) -> np.ndarray:
    """The cells at which an episode from `starts` can pick a move (sorted): those within horizon - 1 moves of a
    start through next_cell. The kernel reads the policy tables at these cells only, so `simulate` fills only
    theirs (a 256 x 256 map whose episodes see a few hundred cells costs what those cost). Empty with mobile
    sources, whose moves the kernel computes at each step. Remembered per start cells."""
    if kernel.mobile:
        return np.zeros(0, dtype=np.int64)
    key = np.unique(np.asarray(starts, dtype=np.int64)).tobytes()
    found = kernel.reached.get(key)
    if found is None:
        found = _reach(kernel.next_cell, np.frombuffer(key, dtype=np.int64), kernel.horizon - 1)
        found.flags.writeable = False
        if len(kernel.reached) >= REACH_MEMO:
            kernel.reached.clear()
        kernel.reached[key] = found
    return found


REACH_MEMO = 64  # start sets remembered per kernel (a team's, an environment's resets)


def _reach(next_cell: np.ndarray, starts: np.ndarray, moves: int) -> np.ndarray:
    """Cells within `moves` moves of any start (breadth first over next_cell, a level at a time), sorted. In numpy:
    once per start set, and no kernel for a first run to compile."""
    seen = np.zeros(next_cell.shape[0], dtype=bool)
    seen[starts] = True
    frontier = np.unique(starts)
    for _ in range(moves):
        ahead = next_cell[frontier].ravel()
        ahead = np.unique(ahead[~seen[ahead]])
        if ahead.size == 0:
            break
        seen[ahead] = True
        frontier = ahead
    return np.flatnonzero(seen).astype(np.int64)


@njit(cache=True)
def _bins(cum, bins):
    """Cumulative move probabilities as integer bounds on a draw's 53 bits m: bits_uniform(m) > cum[a] exactly
    when m >= bins[a], so `_pick_bits` picks the move `_pick` would, by integer compares (a shorter dependency
    chain from one cell to the next than converting and comparing floats).

    The least such m in closed form, without branches (a search mispredicted half its steps: 10x slower at a
    1000-robot team's 576,000 bounds). With X = c 2^53 (exact): below 2^52, m + 0.5 is exact, so m = floor(X -
    0.5) + 1; from 2^52 on, X is whole and m + 0.5 rounds to the even neighbour, so m = X | 1; capped at 2^53.
    tests/test_kernel_speed_paths.py checks it against the search on random and edge probabilities."""
    top = np.int64(9007199254740992)  # 2^53: one past the largest m
    for p in range(cum.shape[0]):
        for c in range(cum.shape[1]):
            for a in range(4):
                scaled = cum[p, c, a] * 9007199254740992.0
                below = np.int64(math.floor(scaled - 0.5)) + 1
                above = np.int64(min(scaled, 9007199254740992.0)) | 1
                bins[p, c, a] = min(max(below if scaled < 4503599627370496.0 else above, 0), top)


@njit(cache=True)
def _bins_at(cum, bins, cells):
    """`_bins` for the listed cells only: the same arithmetic, row by row."""
    top = np.int64(9007199254740992)  # 2^53: one past the largest m
    for p in range(cum.shape[0]):
        for c in cells:
            for a in range(4):
                scaled = cum[p, c, a] * 9007199254740992.0
                below = np.int64(math.floor(scaled - 0.5)) + 1
                above = np.int64(min(scaled, 9007199254740992.0)) | 1
                bins[p, c, a] = min(max(below if scaled < 4503599627370496.0 else above, 0), top)


@njit(cache=True, inline="always")
def _pick_bits(bins, m):
    """`_pick` on the integer bounds of `_bins`."""
    return (m >= bins[0]) + (m >= bins[1]) + (m >= bins[2]) + (m >= bins[3])


@njit(cache=True)
def _mobile_signals(cell, theta, src, next_cell, amplitude, precision, height, cum, feats):
    """`_mobile_policy` of the paper's policy (theta weights the signals alone): its loop without the extras' cases
    (the mobile kernel's speed as before them; the same numbers as `_mobile_policy`)."""
    best = -np.inf
    for a in range(5):
        nc = next_cell[cell, a]
        x, y = nc // height, nc % height
        logit = 0.0
        for j in range(len(src)):
            dx = x - src[j] // height
            dy = y - src[j] % height
            q = precision[j, 0] * dx * dx + 2.0 * precision[j, 1] * dx * dy + precision[j, 2] * dy * dy
            feats[a, j] = amplitude[j] * math.exp(-0.5 * q)
            logit += theta[j] * feats[a, j]
        cum[a] = logit
        best = max(best, logit)
    total = 0.0
    for a in range(5):
        cum[a] = math.exp(cum[a] - best)
        total += cum[a]
    acc = 0.0
    for a in range(5):
        acc += cum[a] / total
        cum[a] = acc
    cum[4] = 1.0


@njit(cache=True)
def _mobile_policy(cell, theta, src, next_cell, amplitude, precision, height, signal_at, extra_at, extras, cum, feats):
    """Move probabilities (cumulative) and features (5, len(theta)) at `cell` for sources at `src` (mobile sources).

    The signals (when signal_at >= 0) fill theta's columns signal_at.., the static extras (C, 5, E) columns extra_at
    (ascending); the logit sums theta_i f_i in theta's order, each term as its feature is computed (the paper's
    policy: the signals' terms alone, in the order and arithmetic of the kernel before the extras).
    """
    extra = len(extra_at)
    before = 0  # the extras that come before the signals in theta
    while before < extra and signal_at >= 0 and extra_at[before] < signal_at:
        before += 1
    if signal_at < 0:
        before = extra
    best = -np.inf
    for a in range(5):
        nc = next_cell[cell, a]
        x, y = nc // height, nc % height
        logit = 0.0
        for e in range(before):
            feats[a, extra_at[e]] = extras[cell, a, e]
            logit += theta[extra_at[e]] * feats[a, extra_at[e]]
        if signal_at >= 0:
            for j in range(len(src)):
                dx = x - src[j] // height
                dy = y - src[j] % height
                q = precision[j, 0] * dx * dx + 2.0 * precision[j, 1] * dx * dy + precision[j, 2] * dy * dy
                feats[a, signal_at + j] = amplitude[j] * math.exp(-0.5 * q)
                logit += theta[signal_at + j] * feats[a, signal_at + j]
        for e in range(before, extra):
            feats[a, extra_at[e]] = extras[cell, a, e]
            logit += theta[extra_at[e]] * feats[a, extra_at[e]]
        cum[a] = logit
        best = max(best, logit)
    total = 0.0
    for a in range(5):
        cum[a] = math.exp(cum[a] - best)
        total += cum[a]
    acc = 0.0
    for a in range(5):
        acc += cum[a] / total
        cum[a] = acc
    cum[4] = 1.0


@njit(cache=True)
def _walk(src, motion, height, width, state):
    """One random-walk step of each mobile source (stays on the grid); returns the stream state."""
    for j in range(len(src)):
        if motion[j] > 0.0:
            state, u = next_uniform(state)
            if u < motion[j]:
                state, v = next_uniform(state)
                a = min(int(v * 4.0), 3)
                move = (0, 1, 3, 4)[a]  # E, W, N, S (never Stay)
                x = src[j] // height + (1, -1, 0, 0, 0)[move]
                y = src[j] % height + (0, 0, 0, 1, -1)[move]
                if 0 <= x < width and 0 <= y < height:
                    src[j] = x * height + y
    return state


@njit(parallel=True, cache=True, error_model="numpy")
def _simulate_affine(
    bins,
    score,
    starts,
    keys,
    episodes,
    next_cell,
    cell_affine,
    cell_risky,
    draw_uniform,
    draw_normal,
    src_off,
    src_ops,
    src_par,
    source_at,
    horizon,
    stop_at_source,
    out_z,
    out_score,
    out_risky,
    out_reached,
    out_steps,
    record,
    path_cells,
    path_rewards,
):
    """`_simulate` for static sources, affine region rewards and a features policy (training's, evaluation's and
    the sampled paths' case): the same draws in the same order, hence the same numbers, from a loop without the
    other cases' branches (about 20% faster: tests/test_kernel_fast_paths.py checks the two agree). With `record`
    it fills path_cells and path_rewards as `_simulate` does, so the paths of a paper run need no second kernel
    (`_simulate` took three times this kernel's compile time)."""
    policies = bins.shape[0]
    sources = score.shape[3]
    total = policies * episodes
    chunks = (total + CHUNK - 1) // CHUNK
    for chunk in prange(chunks):
        stack = np.empty(MAX_STACK)
        acc = np.empty(sources)
        for e in range(chunk * CHUNK, min(total, (chunk + 1) * CHUNK)):
            p = e // episodes
            state = episode_state(keys[p], e - p * episodes)
            cell = starts[p]
            z = 0.0
            risky = 0
            reached = -1
            steps = 0
            acc[:] = 0.0
            if record:
                path_cells[e, 0] = cell
            for k in range(horizon):
                state, m = next_bits(state)
                a = _pick_bits(bins[p, cell], np.int64(m))
                for j in range(sources):
                    acc[j] += score[p, cell, a, j]
                cell = next_cell[cell, a]
                steps += 1
                reward, state = _affine_reward(cell_affine, cell, draw_uniform, draw_normal, state)
                risky += cell_risky[cell]
                hit = source_at[cell]
                if hit >= 0:
                    value, state = _draw(src_ops, src_par, src_off[hit], src_off[hit + 1], stack, state, False)
                    reward += value
                    if reached < 0:
                        reached = hit
                z += reward
                if record:
                    path_cells[e, k + 1] = cell
                    path_rewards[e, k + 1] = reward
                if hit >= 0 and stop_at_source:
                    break
            out_z[e] = z
            out_score[e, :] = acc
            out_risky[e] = risky
            out_reached[e] = reached
            out_steps[e] = steps


@njit(parallel=True, cache=True, error_model="numpy")
def _simulate(
    bins,
    score,
    probs,
    tabular,
    thetas,
    signal_at,
    extra_at,
    extras,
    starts,
    keys,
    episodes,
    next_cell,
    region_of,
    region_risky,
    reg_off,
    reg_ops,
    reg_par,
    src_off,
    src_ops,
    src_par,
    source_at,
    source_cells,
    motion,
    amplitude,
    precision,
    height,
    width,
    horizon,
    stop_at_source,
    mobile,
    record,
    reference,
    affine,
    cell_affine,
    cell_risky,
    draw_uniform,
    draw_normal,
    out_z,
    out_score,
    out_risky,
    out_reached,
    out_steps,
    path_cells,
    path_rewards,
):
    """Episode loop; see `simulate`. A tabular policy's score goes straight into out_score (zeros on entry)."""
    policies = bins.shape[0]
    sources = source_cells.shape[0]
    size = 0 if tabular else thetas.shape[1]  # the score kept in `acc` (a tabular policy's is written in place)
    signals_only = signal_at == 0 and extra_at.shape[0] == 0  # the paper's policy: `_mobile_signals`
    total = policies * episodes
    chunks = (total + CHUNK - 1) // CHUNK
    for chunk in prange(chunks):
        stack = np.empty(MAX_STACK)
        src = np.empty(sources, dtype=np.int64)
        local_cum = np.empty(5)
        feats = np.empty((5, size))
        expect = np.empty(size)
        acc = np.empty(size)  # the episode's score, kept local: one store per episode, not per step
        for e in range(chunk * CHUNK, min(total, (chunk + 1) * CHUNK)):
            p = e // episodes
            state = episode_state(keys[p], e - p * episodes)
            cell = starts[p]
            z = 0.0
            risky = 0
            reached = -1
            steps = 0
            for j in range(size):
                acc[j] = 0.0
            for j in range(sources):
                src[j] = source_cells[j]
            if record:
                path_cells[e, 0] = cell
            for k in range(horizon):
                state, m = next_bits(state)
                if tabular:  # the table, wherever the sources are; score e_(cell, a) - mu(. | cell)
                    a = _pick_bits(bins[p, cell], np.int64(m))
                    if out_score.shape[1] > 0:
                        for b in range(5):
                            out_score[e, cell * 5 + b] -= probs[p, cell, b]
                        out_score[e, cell * 5 + a] += 1.0
                elif mobile:
                    u = bits_uniform(m)
                    if signals_only:
                        _mobile_signals(cell, thetas[p], src, next_cell, amplitude, precision, height, local_cum, feats)
                    else:
                        _mobile_policy(
                            cell,
                            thetas[p],
                            src,
                            next_cell,
                            amplitude,
                            precision,
                            height,
                            signal_at,
                            extra_at,
                            extras,
                            local_cum,
                            feats,
                        )
                    a = _pick(local_cum, u)
                    expect[:] = 0.0
                    prev = 0.0
                    for b in range(5):
                        for j in range(size):
                            expect[j] += (local_cum[b] - prev) * feats[b, j]
                        prev = local_cum[b]
                    for j in range(size):
                        acc[j] += feats[a, j] - expect[j]
                else:
                    a = _pick_bits(bins[p, cell], np.int64(m))
                    for j in range(size):
                        acc[j] += score[p, cell, a, j]
                cell = next_cell[cell, a]
                steps += 1
                reward = 0.0
                if affine:  # no branch on the region: both draws every step, the cell's coefficients pick the law
                    reward, state = _affine_reward(cell_affine, cell, draw_uniform, draw_normal, state)
                    risky += cell_risky[cell]
                else:
                    region = region_of[cell]
                    if region >= 0:
                        reward, state = _draw_inline(
                            reg_ops, reg_par, reg_off[region], reg_off[region + 1], stack, state, reference
                        )
                        risky += region_risky[region]
                hit = -1
                if mobile:
                    for j in range(sources):
                        if src[j] == cell:
                            hit = j
                            break
                    state = _walk(src, motion, height, width, state)
                else:
                    hit = source_at[cell]
                if hit >= 0:
                    value, state = _draw(src_ops, src_par, src_off[hit], src_off[hit + 1], stack, state, reference)
                    reward += value
                    if reached < 0:
                        reached = hit
                z += reward
                if record:
                    path_cells[e, k + 1] = cell
                    path_rewards[e, k + 1] = reward
                if hit >= 0 and stop_at_source:
                    break
            out_z[e] = z
            if not tabular:
                out_score[e, :] = acc
            out_risky[e] = risky
            out_reached[e] = reached
            out_steps[e] = steps
