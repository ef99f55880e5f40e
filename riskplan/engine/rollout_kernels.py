"""The numba kernels of the rollouts (riskplan.engine.rollout runs them): the episode loops `_simulate` and
`_simulate_affine`, the helpers they inline, and `KernelTables`, the world and policy arrays they take as one argument.

The dynamics have one definition, riskplan.engine.dynamics: what entering a cell pays, a source's reward and walk,
the move pick, and the whole episode `_simulate_affine` runs (the GPU kernel runs it too).

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

from riskplan.engine.dynamics import _cumulative_softmax, _draw, _entered, _pick, _pick_bits, _static_episode, _walk
from riskplan.engine.rng import bits_uniform, episode_state, next_bits
from riskplan.engine.world import MAX_STACK

CHUNK = 64  # episodes per parallel work item: amortises the per-item scratch allocations


class KernelTables(NamedTuple):
    """A world's and its policy's arrays and constants as the episode kernels take them: one typed argument (numba
    types a NamedTuple field by field), read by name, so no argument can slip into another's position. Built once
    per rollout.KernelArrays (its `tables`); cuda_rollout copies its arrays to the GPU for the GPU kernel. The kernels read
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


@njit(cache=True)
def _bins(cum, bins, cells):
    """Cumulative move probabilities as integer bounds on a draw's 53 bits m, at the listed cells (the other rows
    left as they are): bits_uniform(m) > cum[a] exactly when m >= bins[a], so `_pick_bits` picks the move `_pick`
    would, by integer compares (a shorter dependency chain from one cell to the next than converting and comparing
    floats).

    The least such m in closed form, without branches (a search mispredicts half its steps, and a 1000-robot
    team has 576,000 bounds). With X = c 2^53 (exact): below 2^52, m + 0.5 is exact, so m = floor(X - 0.5) + 1;
    from 2^52 on, X is whole and m + 0.5 rounds to the even neighbour, so m = X | 1; capped at 2^53.
    tests/engine/test_kernel_fast_paths.py checks it against the search on random and edge probabilities."""
    top = np.int64(9007199254740992)  # 2^53: one past the largest m
    for p in range(cum.shape[0]):
        for c in cells:
            for a in range(4):
                scaled = cum[p, c, a] * 9007199254740992.0
                below = np.int64(math.floor(scaled - 0.5)) + 1
                above = np.int64(min(scaled, 9007199254740992.0)) | 1
                bins[p, c, a] = min(max(below if scaled < 4503599627370496.0 else above, 0), top)


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
    _cumulative_softmax(cum, best, cum)


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
    _cumulative_softmax(cum, best, cum)


# Twin of `_simulate`'s chunk loop, for its static-features-affine case alone (`_static_episode`): the paper run's
# speed and the only episode kernel it compiles; test_kernel_fast_paths.py holds the two equal.
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
    (`_simulate` takes much longer to compile). Long for its arrays alone: read into locals and passed one by one
    (riskplan.engine.dynamics says why)."""
    # KernelTables' fields into locals before the parallel loop, in every kernel: read from the tuple inside it, slower
    next_cell = tables.next_cell
    source_at = tables.source_at
    src_off = tables.src_off
    src_ops = tables.src_ops
    src_par = tables.src_par
    horizon = tables.horizon
    stop_at_source = tables.stop_at_source
    cell_affine = tables.cell_affine
    cell_risky = tables.cell_risky
    draw_uniform = tables.draw_uniform
    draw_normal = tables.draw_normal
    region_of = tables.region_of
    region_risky = tables.region_risky
    reg_off = tables.reg_off
    reg_ops = tables.reg_ops
    reg_par = tables.reg_par
    total = bins.shape[0] * episodes
    chunks = (total + CHUNK - 1) // CHUNK
    for chunk in prange(chunks):
        stack = np.empty(MAX_STACK)
        acc = np.empty(score.shape[3])
        for e in range(chunk * CHUNK, min(total, (chunk + 1) * CHUNK)):
            p = e // episodes
            state = episode_state(keys[p], e - p * episodes)
            acc[:] = 0.0
            # the arrays one by one, not KernelTables (riskplan.engine.dynamics says why)
            out_z[e], out_risky[e], out_reached[e], out_steps[e] = _static_episode(
                next_cell,
                source_at,
                src_off,
                src_ops,
                src_par,
                horizon,
                stop_at_source,
                True,
                cell_affine,
                cell_risky,
                draw_uniform,
                draw_normal,
                region_of,
                region_risky,
                reg_off,
                reg_ops,
                reg_par,
                bins,
                score,
                p,
                e,
                starts[p],
                state,
                acc,
                stack,
                record,
                path_cells,
                path_rewards,
            )
            out_score[e, :] = acc


@njit(parallel=True, cache=True, error_model="numpy")
def _simulate(
    tables,
    probs,
    thetas,
    reference,
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
    """Episode loop; see rollout.simulate. A tabular policy's score goes straight into out_score (zeros on entry).
    `reference` runs every region reward through the interpreter and normals by the inverse CDF. After its own
    three, its parameters are `_simulate_affine`'s, so that rollout.simulate hands either one list of arrays.

    Long on purpose: every case (tabular, mobile, features, reference) interleaves step by step in this one loop
    inside numba's parallel chunks; the parts they share are helpers (`_entered`, `_draw`, `_walk`,
    `_mobile_policy`). A case split out would take a dozen arrays one by one: bundled in a tuple inside the
    parallel loop they cost the paper batch 12% more CPU time. Its static-features step is `_static_episode`'s,
    written out among the other cases (tests/engine/test_kernel_fast_paths.py holds the two equal)."""
    tabular = tables.tabular
    signal_at = tables.signal_at
    extra_at = tables.extra_at
    extras = tables.extras
    # KernelTables' fields into locals before the parallel loop, in every kernel: read from the tuple inside it, slower
    next_cell = tables.next_cell
    region_of = tables.region_of
    region_risky = tables.region_risky
    reg_off = tables.reg_off
    reg_ops = tables.reg_ops
    reg_par = tables.reg_par
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
    cell_affine = tables.cell_affine
    cell_risky = tables.cell_risky
    draw_uniform = tables.draw_uniform
    draw_normal = tables.draw_normal
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
                reward, counted, state = (
                    _entered(  # the arrays one by one, not KernelTables (riskplan.engine.dynamics says why)
                        affine,
                        cell_affine,
                        draw_uniform,
                        draw_normal,
                        cell_risky,
                        region_of,
                        region_risky,
                        reg_off,
                        reg_ops,
                        reg_par,
                        cell,
                        stack,
                        state,
                        reference,
                    )
                )
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
