"""The numba kernels of the rollouts (riskplan.engine.rollout runs them): the episode loops `_simulate` and
`_simulate_affine`, the helpers they inline, and `Tables`, the world and policy arrays they take as one argument.

numba (parallel, cached on disk) runs the whole episode loop in machine code: policy lookup, move sampling,
reward draws from the compiled distribution programs and score accumulation (eq. 10). Each episode draws from
its own counter-based stream (riskplan.engine.rng), so numbers do not depend on threads or chunking.

Fast paths (docs/benchmarks.md, "What makes the kernel fast"): a move is picked by integer compares of a draw's bits
(`_bins`); a region reward of the form clip(c + w U + s N) is drawn from per-cell coefficients without the program
interpreter or a branch on the region (rollout.affine_form), normals by the ziggurat (riskplan.engine.rng.next_normal);
static worlds of a features policy run `_simulate_affine`, a loop without the other cases (and the only episode
kernel a paper run compiles: its sampled paths too). `reference` runs the interpreter and the inverse-CDF normals
everywhere: the same laws from other numbers, the tests' reference.

Policies: a features policy's moves come from per-policy tables of (cell, move) for static sources (filled only for
the cells its episodes can reach, rollout.reach); with mobile sources `_mobile_policy` computes the signals at each
step and adds the static extra features (risky, stay). A tabular policy's moves come from its table in every case,
and its score, a (C * 5,) vector per episode, is accumulated step by step as e_(c, a) - mu(. | c) straight into the
batch's scores, in `_simulate` (the general loop).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from riskplan.engine import distributions as D
from riskplan.engine.rng import (
    bits_uniform,
    episode_state,
    mul,
    next_bits,
    next_normal,
    next_uniform,
    normal_quantile,
)
from riskplan.engine.world import MAX_STACK

CHUNK = 64  # episodes per parallel work item: amortises the per-item scratch allocations


class Tables(NamedTuple):
    """A world's and its policy's arrays and constants as the episode kernels take them: one typed argument (numba
    types a NamedTuple field by field), read by name, so no argument can slip into another's position. Built once
    per rollout.Kernel (its `tables`); cuda_rollout copies its arrays to the GPU for the GPU kernel. The kernels read
    each field into a local before their loop, so the loop is the one they ran when these were positional arguments."""

    next_cell: np.ndarray  # (C, 5) int64: the cell a move leads to
    region_of: np.ndarray  # (C,) int64: the cell's region, -1 for none
    region_risky: np.ndarray  # (R,) int64: 1 for a risky region
    reg_off: np.ndarray  # the region rewards' programs (distributions.pack_programs): offsets, ops, params
    reg_ops: np.ndarray
    reg_par: np.ndarray
    src_off: np.ndarray  # the source rewards' programs: offsets, ops, params
    src_ops: np.ndarray
    src_par: np.ndarray
    source_at: np.ndarray  # (C,) int64: the (static) source at the cell, -1 for none
    source_cells: np.ndarray  # (S,) int64: the sources' start cells
    source_motion: np.ndarray  # (S,) float64: probability of a random-walk step per time step (0 = static)
    source_amplitude: np.ndarray  # (S,) float64: w / (2 pi sqrt(det Sigma))
    source_precision: np.ndarray  # (S, 3) float64: (P_xx, P_xy, P_yy) of Sigma^-1
    cell_affine: np.ndarray  # (C, 5) float64: the entered cell's reward as clip(c + w U + s N, lo, hi)
    cell_risky: np.ndarray  # (C,) int64: 1 if entering the cell counts a risky step
    extra_at: np.ndarray  # (E,) int64: theta's index of each extra feature (features policies)
    extras: np.ndarray  # (C, 5, E) float64: the extra features
    height: int
    width: int
    horizon: int
    stop_at_source: bool
    mobile: bool
    affine: bool  # every region's reward has the affine form (cell_affine holds it)
    draw_uniform: bool  # some region's form has w != 0
    draw_normal: bool  # some region's form has s != 0
    tabular: bool  # theta is a (C * 5,) table of logits
    signal_at: int  # index in theta of the first signal weight, -1 for none


@njit(cache=True, inline="always")
def _affine_reward(cell_affine, cell, draw_uniform, draw_normal, state):
    """The entered cell's reward clip(c + w U + s N, lo, hi) from its coefficients; (reward, new state). The GPU
    kernel's too (cuda_rollout compiles this source)."""
    u = 0.0
    g = 0.0
    if draw_uniform:
        state, u = next_uniform(state)
    if draw_normal:
        state, g = next_normal(state)
    reward = min(
        max(cell_affine[cell, 0] + mul(cell_affine[cell, 1], u) + mul(cell_affine[cell, 2], g), cell_affine[cell, 3]),
        cell_affine[cell, 4],
    )
    return reward, state


@njit(cache=True)
def _draw(ops, params, first, last, stack, state, inverse_normal=False):
    """Run one postfix reward program (riskplan.engine.distributions) and return (value, state).

    Normal draws come from the ziggurat (riskplan.engine.rng.next_normal), or with `inverse_normal` from the inverse CDF
    of one uniform (the slower sampler used before; kept as the tests' reference).

    A call for a source's reward (once per episode): inlined there too, it would multiply `_simulate`'s compile
    time (the first run after an install). Every kernel passes `inverse_normal`, so one specialisation serves all.
    The GPU kernel's too (cuda_rollout compiles this source; it never passes `inverse_normal`).
    """
    top = 0
    for i in range(first, last):
        op = ops[i, 0]
        if op == D.OP_CONST:
            stack[top] = params[i, 0]
            top += 1
        elif op == D.OP_UNIFORM:
            state, u = next_uniform(state)
            stack[top] = params[i, 0] + mul(params[i, 1] - params[i, 0], u)
            top += 1
        elif op == D.OP_NORMAL:
            if inverse_normal:
                state, u = next_uniform(state)
                g = normal_quantile(u)
            else:
                state, g = next_normal(state)
            stack[top] = params[i, 0] + mul(params[i, 1], g)
            top += 1
        elif op == D.OP_BERNOULLI:
            state, u = next_uniform(state)
            stack[top] = 1.0 if u < params[i, 0] else 0.0
            top += 1
        elif op == D.OP_SCALE:
            stack[top - 1] = mul(stack[top - 1], params[i, 0])
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
def _entered(tables, affine, cell, stack, state, reference):
    """What entering `cell` pays and counts, in every kernel's step (`_simulate`'s, `step_robots`'): its region's reward
    and whether the step is risky (no region: 0 and 0); (reward, risky, state). `affine`: the world's region rewards
    from their coefficients (no branch on the region: both draws every step, the cell's coefficients pick the law)."""
    if affine:
        reward, state = _affine_reward(tables.cell_affine, cell, tables.draw_uniform, tables.draw_normal, state)
        return reward, tables.cell_risky[cell], state
    region = tables.region_of[cell]
    if region < 0:
        return 0.0, np.int64(0), state
    ops, params, first, last = tables.reg_ops, tables.reg_par, tables.reg_off[region], tables.reg_off[region + 1]
    reward, state = _draw_inline(ops, params, first, last, stack, state, reference)
    return reward, tables.region_risky[region], state


@njit(cache=True, inline="always")
def _pick(cum, u):
    """The move whose bin of the cumulative probabilities (cum[4] = 1) holds u: counted without branches.

    Counting the bins below u gives the index a linear search would, but a random move is no longer a branch the
    CPU mispredicts.
    """
    return (u > cum[0]) + (u > cum[1]) + (u > cum[2]) + (u > cum[3])


@njit(cache=True)
def _bins(cum, bins):
    """Cumulative move probabilities as integer bounds on a draw's 53 bits m: bits_uniform(m) > cum[a] exactly
    when m >= bins[a], so `_pick_bits` picks the move `_pick` would, by integer compares (a shorter dependency
    chain from one cell to the next than converting and comparing floats).

    The least such m in closed form, without branches (a search mispredicts half its steps, and a 1000-robot
    team has 576,000 bounds). With X = c 2^53 (exact): below 2^52, m + 0.5 is exact, so m = floor(X - 0.5) + 1;
    from 2^52 on, X is whole and m + 0.5 rounds to the even neighbour, so m = X | 1; capped at 2^53.
    tests/engine/test_kernel_fast_paths.py checks it against the search on random and edge probabilities."""
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
    """`_pick` on the integer bounds of `_bins` (the GPU kernel's too; int() as numpy's bools would add as `or`
    under numba-cuda's simulator)."""
    return int(m >= bins[0]) + int(m >= bins[1]) + int(m >= bins[2]) + int(m >= bins[3])


# Twin of policy._fill_tabular's softmax (same arithmetic): that one fills every cell's tables at once, this one a
# single cell in place at each step of a mobile world, inlined into the episode loop.
@njit(cache=True, inline="always")
def _cumulative_softmax(cum, best):
    """The five logits in `cum` (their largest `best`) made cumulative move probabilities in place, cum[4] = 1."""
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
    _cumulative_softmax(cum, best)


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
    _cumulative_softmax(cum, best)


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


@njit(cache=True)
def step_robots(tables, cells, moves, active, group, sources, states, walk_states, reward, risky, hit):
    """One time step of B robots in G copies of the world, for the environments (riskplan.experiments.environments):
    `_simulate`'s step once its move is chosen, each robot drawing from its own stream (`states`, (B,)) and each
    copy's mobile sources from theirs (`walk_states`, (G,)). An active robot b moves by moves[b] from cells[b], is paid
    the entered cell (`_entered`) and the first source of its copy group[b] on it; then the sources (G, S) of every
    copy with an active robot walk once. Updates cells, sources and the states; writes reward, risky and hit (B,)."""
    stack = np.empty(MAX_STACK)
    moving = np.zeros(sources.shape[0], dtype=np.bool_)
    for b in range(cells.shape[0]):
        reward[b], risky[b], hit[b] = 0.0, 0, -1
        if not active[b]:
            continue
        moving[group[b]] = True
        cell = tables.next_cell[cells[b], moves[b]]
        cells[b] = cell
        paid, counted, state = _entered(tables, tables.affine, cell, stack, states[b], False)
        src = sources[group[b]]
        for j in range(src.shape[0]):
            if src[j] == cell:
                hit[b] = j
                break
        if hit[b] >= 0:
            first, last = tables.src_off[hit[b]], tables.src_off[hit[b] + 1]
            value, state = _draw(tables.src_ops, tables.src_par, first, last, stack, state, False)
            paid += value
        reward[b], risky[b], states[b] = paid, counted, state
    for g in range(sources.shape[0]):
        if moving[g]:
            walk_states[g] = _walk(sources[g], tables.source_motion, tables.height, tables.width, walk_states[g])


# Twin of `_simulate`'s loop, its static-features-affine case alone: the loop without the other cases' branches is
# the paper run's speed and the only episode kernel it compiles; test_kernel_fast_paths.py holds the two equal.
@njit(parallel=True, cache=True, error_model="numpy")
def _simulate_affine(
    tables,
    bins,
    score,
    starts,
    keys,
    episodes,
    record,
    out_z,
    out_score,
    out_risky,
    out_reached,
    out_steps,
    path_cells,
    path_rewards,
):
    """`_simulate` for static sources, affine region rewards and a features policy (training's, evaluation's and
    the sampled paths' case): the same draws in the same order, hence the same numbers, from a loop without the
    other cases' branches (tests/engine/test_kernel_fast_paths.py checks the two agree). With `record`
    it fills path_cells and path_rewards as `_simulate` does, so the paths of a paper run need no second kernel
    (`_simulate` takes much longer to compile)."""
    next_cell = tables.next_cell
    cell_affine = tables.cell_affine
    cell_risky = tables.cell_risky
    draw_uniform = tables.draw_uniform
    draw_normal = tables.draw_normal
    src_off = tables.src_off
    src_ops = tables.src_ops
    src_par = tables.src_par
    source_at = tables.source_at
    horizon = tables.horizon
    stop_at_source = tables.stop_at_source
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
    tables,
    bins,
    score,
    probs,
    thetas,
    starts,
    keys,
    episodes,
    record,
    reference,
    out_z,
    out_score,
    out_risky,
    out_reached,
    out_steps,
    path_cells,
    path_rewards,
):
    """Episode loop; see rollout.simulate. A tabular policy's score goes straight into out_score (zeros on entry).
    `reference` runs every region reward through the interpreter and normals by the inverse CDF.

    Long on purpose: the loop inside numba's parallel chunks is the kernel's speed (the episode as one inlined
    function cost `_simulate_affine` 5-7% more CPU time), so only the steps' parts are helpers (`_entered`,
    `_draw`, `_walk`, `_mobile_policy`), and every case stays in this one loop."""
    tabular = tables.tabular
    signal_at = tables.signal_at
    extra_at = tables.extra_at
    extras = tables.extras
    next_cell = tables.next_cell
    src_off = tables.src_off
    src_ops = tables.src_ops
    src_par = tables.src_par
    source_at = tables.source_at
    source_cells = tables.source_cells
    motion = tables.source_motion
    amplitude = tables.source_amplitude
    precision = tables.source_precision
    height = tables.height
    width = tables.width
    horizon = tables.horizon
    stop_at_source = tables.stop_at_source
    mobile = tables.mobile
    affine = tables.affine and not reference
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
                reward, counted, state = _entered(tables, affine, cell, stack, state, reference)
                risky += counted
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
