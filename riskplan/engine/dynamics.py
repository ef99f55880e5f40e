"""One definition of the episode dynamics: what a step pays and counts, where a mobile source walks, and a whole
episode of a static world, as every kernel runs them: the CPU kernels (riskplan.engine.rollout_kernels), the GPU
kernel (riskplan.engine.cuda_rollout compiles these functions from their own source) and the Gymnasium and
PettingZoo environments (`step_robots`, one time step of many robots).

A move is picked by integer compares of a draw's bits against the policy's bins (`_pick_bits`; `_pick` on floats,
for the moves computed at each step with mobile sources), its probabilities a softmax of the policy's logits
(`_cumulative_softmax`, also every policy table's); the entered cell pays its region's reward (`_entered`:
from per-cell coefficients for affine laws, `_affine_reward`, else the reward program's interpreter `_draw`) and
a source's reward (`_draw`); mobile sources walk after the step (`_walk`). Every draw comes from the episode's own
counter-based stream (riskplan.engine.rng). Products that a sum takes are written rng.mul (the GPU rounds them
alone).

The world's arrays are passed one by one, not as the kernels' KernelTables: a tuple of them read inside numba's parallel
loop cost the paper batch 12% more CPU time.
"""

from __future__ import annotations

import math
import types

import numpy as np
from numba import njit

from riskplan.engine import distributions as D
from riskplan.engine.rng import mul, next_bits, next_normal, next_uniform, normal_quantile
from riskplan.engine.world import MAX_STACK


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
def _entered(
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
):
    """What entering `cell` pays and counts, in every kernel's step: its region's reward and whether the step is
    risky (no region: 0 and 0); (reward, risky, state). With `affine` (the world's region rewards have the affine
    form) from the cell's coefficients, without a branch on the region (both draws every step, the cell's
    coefficients pick the law); else through the region's reward program. The arrays come one by one, not as
    KernelTables (the module docstring says why), so every caller lists them."""
    if affine:
        reward, state = _affine_reward(cell_affine, cell, draw_uniform, draw_normal, state)
        return reward, cell_risky[cell], state
    region = region_of[cell]
    if region < 0:
        return 0.0, np.int64(0), state
    reward, state = _draw_inline(reg_ops, reg_par, reg_off[region], reg_off[region + 1], stack, state, reference)
    return reward, region_risky[region], state


# `_entered` with the interpreter as a call (`_draw`), for `_static_episode`: the paper run's episode kernel then
# compiles without the interpreter inlined into it (a first run after an install took 10 s, not 7 s). The same
# source, its `_draw_inline` bound to `_draw`, as cuda_rollout binds the GPU's names.
_entered_by_call = njit(inline="always")(
    types.FunctionType(_entered.py_func.__code__, {**_entered.py_func.__globals__, "_draw_inline": _draw})
)


@njit(cache=True, inline="always")
def _pick(cum, u):
    """The move whose bin of the cumulative probabilities (cum[4] = 1) holds u: counted without branches.

    Counting the bins below u gives the index a linear search would, but a random move is no longer a branch the
    CPU mispredicts.
    """
    return (u > cum[0]) + (u > cum[1]) + (u > cum[2]) + (u > cum[3])


@njit(cache=True, inline="always")
def _pick_bits(bins, m):
    """`_pick` on the integer bounds of `_bins` (the GPU kernel's too; int() as numpy's bools would add as `or`
    under numba-cuda's simulator)."""
    return int(m >= bins[0]) + int(m >= bins[1]) + int(m >= bins[2]) + int(m >= bins[3])


@njit(cache=True, inline="always")
def _cumulative_softmax(mu, best, cum):
    """The five logits in `mu` (their largest `best`) made move probabilities in place and their running sums
    written to `cum`, cum[4] = 1 (so a draw always lands): the one arithmetic of every policy's tables
    (riskplan.engine.policy) and of the mobile kernel's step, which passes one array as both."""
    total = 0.0
    for a in range(5):
        mu[a] = math.exp(mu[a] - best)  # max-shift: no overflow for large theta
        total += mu[a]
    running = 0.0
    for a in range(5):
        mu[a] /= total
        running += mu[a]
        cum[a] = running
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
        paid, counted, state = _entered(  # the arrays one by one, not KernelTables (the module docstring says why)
            tables.affine,
            tables.cell_affine,
            tables.draw_uniform,
            tables.draw_normal,
            tables.cell_risky,
            tables.region_of,
            tables.region_risky,
            tables.reg_off,
            tables.reg_ops,
            tables.reg_par,
            cell,
            stack,
            states[b],
            False,
        )
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


@njit(cache=True, inline="always")
def _static_episode(
    next_cell,
    source_at,
    src_off,
    src_ops,
    src_par,
    horizon,
    stop_at_source,
    affine,
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
    cell,
    state,
    acc,
    stack,
    record,
    path_cells,
    path_rewards,
):
    """Episode e of policy p in a static world under a features policy, from `cell` on the stream `state`: each
    move picked by the bins (P, C, 4), its score (P, C, 5, M) added into `acc`, the entered cell paid (`_entered`)
    and a source's reward, the path into row e of path_cells and path_rewards with `record`. (z, risky steps,
    source reached, steps). The episode of `_simulate_affine` and of the GPU kernel (cuda_rollout compiles this
    source): one definition for both devices. The arrays come one by one, as `_entered`'s do: hence its length,
    most of it their list (a split would list them again)."""
    z = 0.0
    risky = 0
    reached = -1
    steps = 0
    if record:
        path_cells[e, 0] = cell
    for k in range(horizon):
        state, m = next_bits(state)
        a = _pick_bits(bins[p, cell], np.int64(m))
        for j in range(acc.shape[0]):
            acc[j] += score[p, cell, a, j]
        cell = next_cell[cell, a]
        steps += 1
        reward, counted, state = (
            _entered_by_call(  # the arrays one by one, not KernelTables (the module docstring says why)
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
                False,
            )
        )
        risky += counted
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
    return z, risky, reached, steps
