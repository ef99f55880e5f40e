"""engine.device=cuda: `riskplan.engine.rollout.simulate` on an NVIDIA GPU through numba-cuda, one thread per
(policy, episode), with the same draws from the same counter-based streams (riskplan.engine.rng), so a GPU run's
episodes are the CPU run's.

Ported: static sources and a features policy without recording (training's and evaluation's case, the paper's
worlds): the loop of `rollout_kernels._simulate_affine` for affine region rewards, and the program interpreter
(`rollout_kernels._draw`) for any other region reward, with source rewards always through the interpreter.
Everything else runs on the CPU kernel, unchanged: a tabular policy, mobile sources, recorded paths (`record=True`)
and the reference sampler (`reference=True`). The policy tables and move bins (riskplan.engine.policy.tables,
rollout.move_bins) are computed on the CPU and copied over; the outputs come back as the `rollout.Batch` the CPU
kernel returns.

Numbers. The stream is integer arithmetic, the same on both. Every product that a sum takes is rounded on its own
(`_mul`: libdevice's dmul_rn, which the compiler never fuses into an FMA), so the float arithmetic is IEEE's, step
for step, as numba's on the CPU. Under numba-cuda's simulator (NUMBA_ENABLE_CUDASIM=1, the tests) the kernels agree
with the CPU kernel bit for bit. On a GPU, `math.exp` and `math.log` are CUDA's (libdevice, within an ulp or two of
the CPU's libm): they enter only the ziggurat's rare edges (`_normal_edge`: its tail, about 3 normal draws in
10,000, and its wedges' accept test), so an episode that draws in the tail can differ from the CPU's in the last
bits (docs/sweeps.md says how to check).

This module imports numba.cuda at the top: only `engine.device=cuda` imports it (riskplan.engine.step.simulator).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import config as numba_config
from numba import cuda, float64

from riskplan.engine import distributions as D
from riskplan.engine.policy import tables
from riskplan.engine.rng import GOLDEN, ZIG_R, ZIG_RATIO, ZIG_X
from riskplan.engine.rollout import Batch, Kernel, move_bins, reach
from riskplan.engine.rollout import simulate as cpu_simulate
from riskplan.engine.rollout_kernels import Tables
from riskplan.engine.world import MAX_STACK, World
from riskplan.util.errors import BadInput

THREADS = 128  # threads per block
SIMULATOR = bool(numba_config.ENABLE_CUDASIM)  # numba-cuda's simulator: Python threads, for the tests
_X = np.ascontiguousarray(ZIG_X)
_RATIO = np.ascontiguousarray(ZIG_RATIO)
_MIX1, _MIX2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(GOLDEN)


def gpu_problem() -> str | None:
    """Why this process cannot run kernels on a GPU (None when it can): no CUDA driver or no NVIDIA GPU."""
    return _gpu_problem()


@functools.cache
def _gpu_problem() -> str | None:
    if SIMULATOR:
        return None
    try:
        if cuda.is_available() and len(cuda.gpus) > 0:
            return None
        len(cuda.gpus)  # raises the driver's own reason when there is one
    except Exception as err:  # no driver library, a driver that fails to load, an unsupported GPU
        lines = [line.strip(" :") for line in str(err).splitlines() if line.strip(" :")]
        reason = next((line for line in lines if not line.startswith("Error at driver init")), type(err).__name__)
        return f"no GPU numba-cuda can use here ({reason.rstrip('.')})"
    return "no GPU numba-cuda can use here (no NVIDIA GPU found)"


def check_gpu() -> None:
    """BadInput naming engine.device=cuda unless a GPU can run the kernels here (riskplan.run.build checks it)."""
    problem = gpu_problem()
    if problem is not None:
        raise BadInput("engine.device=cuda", f"{problem}; use engine.device=cpu (the same numbers, on the CPU)")


def ported(kernel: Kernel, record: bool = False, reference: bool = False) -> bool:
    """Whether `simulate` runs these episodes on the GPU (else on the CPU kernel, as `rollout.simulate`)."""
    return not (kernel.tables.tabular or kernel.tables.mobile or record or reference)


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
    """`riskplan.engine.rollout.simulate` on the GPU where it is ported (`ported`), else on the CPU: the same
    arguments, the same Batch, the same numbers."""
    if not ported(kernel, record, reference):
        return cpu_simulate(world, kernel, thetas, starts, keys, episodes, record, reference, scores)
    return Launch(world, kernel, thetas, starts, keys, episodes).run().batch()


class Launch:
    """One kernel call, its inputs on the device: `run()` launches it (again, for a benchmark), `batch()` copies
    the outputs back. The policy tables and move bins are the CPU kernel's (`rollout.simulate` computes the same)."""

    def __init__(self, world: World, kernel: Kernel, thetas, starts, keys, episodes: int):
        thetas = np.ascontiguousarray(thetas, dtype=np.float64)
        policies, self.size = thetas.shape
        cells = reach(kernel, starts)
        cum, score = tables(world, thetas, kernel.features, cells)
        self.total = policies * episodes
        self.inputs = (
            _on_device(kernel),
            cuda.to_device(move_bins(cum, cells)),
            cuda.to_device(np.ascontiguousarray(score)),
            cuda.to_device(np.ascontiguousarray(starts, dtype=np.int64)),
            cuda.to_device(np.ascontiguousarray(keys, dtype=np.uint64)),
            np.int64(episodes),
        )
        total = max(self.total, 1)  # a launch of no episodes still gets arrays (of one row it never writes)
        self.outputs = (
            cuda.device_array(total),
            cuda.device_array((total, self.size)),
            cuda.device_array(total, dtype=np.int64),
            cuda.device_array(total, dtype=np.int64),
            cuda.device_array(total, dtype=np.int64),
        )

    def run(self) -> Launch:
        """Launch the kernel (asynchronous: `batch()` or cuda.synchronize() waits for it)."""
        if self.total:
            blocks = (self.total + THREADS - 1) // THREADS
            _episode_kernel(self.size)[blocks, THREADS](*self.inputs, *self.outputs)
        return self

    def batch(self) -> Batch:
        """The outputs, copied to the host as the CPU kernel's Batch."""
        return Batch(*(array.copy_to_host()[: self.total] for array in self.outputs))


_DEVICE_MEMO: dict[int, tuple[Kernel, Tables]] = {}  # id(kernel) -> (kernel, its tables on the device)


def _on_device(kernel: Kernel) -> Tables:
    """The kernel's Tables with their arrays on the GPU (the constants as they are), copied once per Kernel (a
    run's, a batch's): the one argument the episode kernel takes them as, as the CPU kernels do."""
    held = _DEVICE_MEMO.get(id(kernel))
    if held is not None and held[0] is kernel:
        return held[1]
    if len(_DEVICE_MEMO) >= 8:
        _DEVICE_MEMO.clear()
    on_device = Tables(
        *(cuda.to_device(np.ascontiguousarray(v)) if isinstance(v, np.ndarray) else v for v in kernel.tables)
    )
    _DEVICE_MEMO[id(kernel)] = (kernel, on_device)
    return on_device


# ------------------------------------------------------------------------------------------ device functions
# Each mirrors its CPU namesake in riskplan.engine.rng or riskplan.engine.rollout_kernels, operation for operation.

if SIMULATOR:  # the simulator runs device functions as Python, where libdevice's stubs return nothing

    @cuda.jit(device=True)
    def _mul(a, b):
        """a * b, rounded on its own (never fused into an FMA)."""
        return a * b

else:
    from numba.cuda import libdevice

    _mul = libdevice.dmul_rn


@cuda.jit(device=True)
def _mix(z):
    """rng.mix: the splitmix64 finaliser."""
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))


@cuda.jit(device=True)
def _episode_state(key, episode):
    """rng.episode_state."""
    return _mix(key ^ _mix(np.uint64(episode) + _GOLD))


@cuda.jit(device=True)
def _next_bits(state):
    """rng.next_bits: (new state, 53 random bits)."""
    state = state + _GOLD
    return state, _mix(state) >> np.uint64(11)


@cuda.jit(device=True)
def _next_uniform(state):
    """rng.next_uniform: (new state, (m + 0.5) / 2^53)."""
    state, m = _next_bits(state)
    return state, (m + 0.5) * (1.0 / 9007199254740992.0)


@cuda.jit(device=True)
def _next_normal(state):
    """rng.next_normal: the ziggurat's fast path, `_normal_edge` for the rest."""
    state = state + _GOLD
    bits = _mix(state)
    i = np.int64(bits & np.uint64(255))
    u = _mul((bits >> np.uint64(12)) + 0.5, 1.0 / 2251799813685248.0) - 1.0
    if abs(u) < _RATIO[i]:
        return state, _mul(u, _X[i])
    return _normal_edge(state, i, u)


@cuda.jit(device=True)
def _normal_edge(state, i, u):
    """rng._normal_edge: the tail beyond r and the wedges (exp and log are CUDA's here)."""
    while True:
        if i == 0:
            while True:
                state, a = _next_uniform(state)
                state, b = _next_uniform(state)
                t = -math.log(a) / ZIG_R
                if _mul(-2.0, math.log(b)) >= _mul(t, t):
                    return state, ZIG_R + t if u > 0.0 else -(ZIG_R + t)
        z = _mul(u, _X[i])
        f0 = math.exp(_mul(-0.5, _mul(_X[i], _X[i]) - _mul(z, z)))
        f1 = math.exp(_mul(-0.5, _mul(_X[i + 1], _X[i + 1]) - _mul(z, z)))
        state, c = _next_uniform(state)
        if f1 + _mul(c, f0 - f1) < 1.0:
            return state, z
        state = state + _GOLD
        bits = _mix(state)
        i = np.int64(bits & np.uint64(255))
        u = _mul((bits >> np.uint64(12)) + 0.5, 1.0 / 2251799813685248.0) - 1.0
        if abs(u) < _RATIO[i]:
            return state, _mul(u, _X[i])


@cuda.jit(device=True)
def _affine_reward(cell_affine, cell, draw_uniform, draw_normal, state):
    """rollout_kernels._affine_reward: clip(c + w U + s N, lo, hi) from the entered cell's coefficients."""
    u = 0.0
    g = 0.0
    if draw_uniform:
        state, u = _next_uniform(state)
    if draw_normal:
        state, g = _next_normal(state)
    reward = min(
        max(cell_affine[cell, 0] + _mul(cell_affine[cell, 1], u) + _mul(cell_affine[cell, 2], g), cell_affine[cell, 3]),
        cell_affine[cell, 4],
    )
    return reward, state


@cuda.jit(device=True)
def _draw(ops, params, first, last, stack, state):
    """rollout_kernels._draw (ziggurat normals): one postfix reward program, (value, state)."""
    top = 0
    for i in range(first, last):
        op = ops[i, 0]
        if op == D.OP_CONST:
            stack[top] = params[i, 0]
            top += 1
        elif op == D.OP_UNIFORM:
            state, u = _next_uniform(state)
            stack[top] = params[i, 0] + _mul(params[i, 1] - params[i, 0], u)
            top += 1
        elif op == D.OP_NORMAL:
            state, g = _next_normal(state)
            stack[top] = params[i, 0] + _mul(params[i, 1], g)
            top += 1
        elif op == D.OP_BERNOULLI:
            state, u = _next_uniform(state)
            stack[top] = 1.0 if u < params[i, 0] else 0.0
            top += 1
        elif op == D.OP_SCALE:
            stack[top - 1] = _mul(stack[top - 1], params[i, 0])
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
        else:  # OP_MIXTURE
            n = ops[i, 1]
            state, u = _next_uniform(state)
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


@cuda.jit(device=True)
def _pick_bits(bins, p, cell, m):
    """rollout_kernels._pick_bits: the move whose integer bin holds the draw's bits m (counted, as integers)."""
    a = 0
    for b in range(4):
        if m >= bins[p, cell, b]:
            a += 1
    return a


@functools.cache
def _episode_kernel(size: int):
    """The episode kernel for a theta of `size` entries (the score kept in `size` registers per thread)."""

    @cuda.jit
    def episodes_kernel(
        tables, bins, score, starts, keys, episodes, out_z, out_score, out_risky, out_reached, out_steps
    ):
        """rollout_kernels._simulate_affine (affine) or the static features case of rollout_kernels._simulate (the
        interpreter): episode e of policy p = e // episodes, one per thread. `tables` is the Kernel's, on the device."""
        next_cell = tables.next_cell
        cell_affine = tables.cell_affine
        cell_risky = tables.cell_risky
        region_of = tables.region_of
        region_risky = tables.region_risky
        reg_off = tables.reg_off
        reg_ops = tables.reg_ops
        reg_par = tables.reg_par
        src_off = tables.src_off
        src_ops = tables.src_ops
        src_par = tables.src_par
        source_at = tables.source_at
        affine = tables.affine
        draw_uniform = tables.draw_uniform
        draw_normal = tables.draw_normal
        horizon = tables.horizon
        stop_at_source = tables.stop_at_source
        e = cuda.grid(1)
        if e >= out_z.shape[0]:
            return
        stack = cuda.local.array(MAX_STACK, float64)
        acc = cuda.local.array(size, float64)
        p = e // episodes
        state = _episode_state(keys[p], e - p * episodes)
        cell = starts[p]
        z = 0.0
        risky = 0
        reached = -1
        steps = 0
        for j in range(size):
            acc[j] = 0.0
        for _ in range(horizon):
            state, m = _next_bits(state)
            a = _pick_bits(bins, p, cell, np.int64(m))
            for j in range(size):
                acc[j] += score[p, cell, a, j]
            cell = next_cell[cell, a]
            steps += 1
            reward = 0.0
            if affine:
                reward, state = _affine_reward(cell_affine, cell, draw_uniform, draw_normal, state)
                risky += cell_risky[cell]
            else:
                region = region_of[cell]
                if region >= 0:
                    reward, state = _draw(reg_ops, reg_par, reg_off[region], reg_off[region + 1], stack, state)
                    risky += region_risky[region]
            hit = source_at[cell]
            if hit >= 0:
                value, state = _draw(src_ops, src_par, src_off[hit], src_off[hit + 1], stack, state)
                reward += value
                if reached < 0:
                    reached = hit
            z += reward
            if hit >= 0 and stop_at_source:
                break
        out_z[e] = z
        for j in range(size):
            out_score[e, j] = acc[j]
        out_risky[e] = risky
        out_reached[e] = reached
        out_steps[e] = steps

    return episodes_kernel
