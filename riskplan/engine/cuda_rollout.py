"""engine.device=cuda: `riskplan.engine.rollout.simulate` on an NVIDIA GPU through numba-cuda, one thread per
(policy, episode), with the same draws from the same counter-based streams (riskplan.engine.rng), so a GPU run's
episodes are the CPU run's.

Ported: static sources and a features policy without recording (training's and evaluation's case, the paper's
worlds): the loop of `rollout_kernels._simulate_affine` for affine region rewards, and the program interpreter
(`dynamics._draw`) for any other region reward, with source rewards always through the interpreter.
Everything else runs on the CPU kernel, unchanged: a tabular policy, mobile sources, recorded paths (`record=True`)
and the reference sampler (`reference=True`). The policy tables and move bins (riskplan.engine.policy.tables,
rollout.move_bins) are computed on the CPU and copied over; the outputs come back as the `rollout.EpisodeBatch` the CPU
kernel returns.

One source. The device functions are the CPU kernel's helpers compiled again from their own Python (`on_gpu`):
the random stream and the ziggurat, the reward interpreter, the affine reward, the move pick, what entering a cell
pays (`_entered`) and the whole episode (`_static_episode`, `_simulate_affine`'s). Only the launch is the GPU's
own: one thread per episode, local arrays in place of the CPU kernel's chunks and scratch arrays.

Numbers. The stream is integer arithmetic, the same on both. Every product that a sum takes is written `mul(a, b)`
(riskplan.engine.rng.mul), bound here to libdevice's dmul_rn, which the compiler never fuses into an FMA, so the
float arithmetic is IEEE's, step for step, as numba's on the CPU. Under numba-cuda's simulator
(NUMBA_ENABLE_CUDASIM=1, the tests) the kernels agree with the CPU kernel bit for bit. On a GPU, `math.exp` and
`math.log` are CUDA's (libdevice, within an ulp or two of the CPU's libm): they enter only the ziggurat's rare
edges (`_normal_edge`: its tail, about 3 normal draws in 10,000, and its wedges' accept test), so an episode that
draws in the tail can differ from the CPU's in the last bits (docs/sweeps.md says how to check).

This module imports numba.cuda at the top: only `engine.device=cuda` imports it (riskplan.engine.step.simulator).
"""

from __future__ import annotations

import functools
import types

import numpy as np
from numba import config as numba_config
from numba import cuda, float64, int64

from riskplan.engine import dynamics, rng
from riskplan.engine.rollout import EpisodeBatch, KernelArrays, policy_tables
from riskplan.engine.rollout import simulate as cpu_simulate
from riskplan.engine.rollout_kernels import KernelTables
from riskplan.engine.world import MAX_STACK, World
from riskplan.util.errors import BadInput

THREADS = 128  # threads per block
SIMULATOR = bool(numba_config.ENABLE_CUDASIM)  # numba-cuda's simulator: Python threads, for the tests


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


def ported(kernel: KernelArrays, record: bool = False, reference: bool = False) -> bool:
    """Whether `simulate` runs these episodes on the GPU (else on the CPU kernel, as `rollout.simulate`)."""
    return not (kernel.tables.tabular or kernel.tables.mobile or record or reference)


def simulate(  # rollout.simulate's signature, twinned: engine.step.simulator hands out either (test_backends checks)
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
    """`riskplan.engine.rollout.simulate` on the GPU where it is ported (`ported`), else on the CPU: the same
    arguments, the same EpisodeBatch, the same numbers."""
    if not ported(kernel, record, reference):
        return cpu_simulate(world, kernel, thetas, starts, keys, episodes, record, reference, scores)
    return Launch(world, kernel, thetas, starts, keys, episodes).run().batch()


class Launch:
    """One kernel call, its inputs on the device: `run()` launches it (again, for a benchmark), `batch()` copies
    the outputs back. The policy tables and move bins are the CPU kernel's (rollout.policy_tables)."""

    def __init__(self, world: World, kernel: KernelArrays, thetas, starts, keys, episodes: int):
        thetas = np.ascontiguousarray(thetas, dtype=np.float64)
        policies, self.size = thetas.shape
        bins, score, _ = policy_tables(world, kernel, thetas, starts)
        self.total = policies * episodes
        self.inputs = (
            _on_device(kernel),
            cuda.to_device(bins),
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

    def batch(self) -> EpisodeBatch:
        """The outputs, copied to the host as the CPU kernel's EpisodeBatch."""
        return EpisodeBatch(*(array.copy_to_host()[: self.total] for array in self.outputs))


_DEVICE_MEMO: dict[int, tuple[KernelArrays, KernelTables]] = {}  # id(kernel) -> (kernel, its tables on the device)


def _on_device(kernel: KernelArrays) -> KernelTables:
    """The kernel's KernelTables with their arrays on the GPU (the constants as they are), copied once per KernelArrays (a
    run's, a batch's): the one argument the episode kernel takes them as, as the CPU kernels do."""
    held = _DEVICE_MEMO.get(id(kernel))
    if held is not None and held[0] is kernel:
        return held[1]
    if len(_DEVICE_MEMO) >= 8:
        _DEVICE_MEMO.clear()
    on_device = KernelTables(
        *(cuda.to_device(np.ascontiguousarray(v)) if isinstance(v, np.ndarray) else v for v in kernel.tables)
    )
    _DEVICE_MEMO[id(kernel)] = (kernel, on_device)
    return on_device


# ------------------------------------------------------------------------------------------ device functions
# The CPU kernel's helpers, compiled from their own source: the random stream and the ziggurat (riskplan.engine.rng),
# the reward program interpreter, the affine reward, the move pick and the episode (riskplan.engine.dynamics).
SHARED = (
    rng.mix,
    rng.episode_state,
    rng.next_bits,
    rng.bits_uniform,
    rng.next_uniform,
    rng.next_normal,
    rng._normal_edge,
    rng.normal_quantile,
    rng._quantile_tail,
    dynamics._affine_reward,
    dynamics._draw,
    dynamics._pick_bits,
    dynamics._entered,
    dynamics._static_episode,
)

if SIMULATOR:  # the simulator runs device functions as Python, where libdevice's stubs return nothing
    _mul = cuda.jit(device=True)(rng.mul.py_func)
else:
    from numba.cuda import libdevice

    _mul = libdevice.dmul_rn  # a * b rounded on its own: the compiler never fuses it into an FMA


def on_gpu(helpers=SHARED) -> dict[str, object]:
    """Device functions of the CPU helpers, by name: each one's own Python source (numba's py_func) with its
    module's globals, where the other helpers' names (and `mul`) are bound to their device functions. numba-cuda
    cannot call an @njit function, but it compiles the same Python function as a device function."""
    bound: dict[str, object] = {"mul": _mul}
    namespaces = []
    for helper in helpers:
        source = helper.py_func
        namespace = dict(source.__globals__)
        namespaces.append(namespace)
        twin = types.FunctionType(source.__code__, namespace, source.__name__, source.__defaults__)
        bound[source.__name__] = cuda.jit(device=True)(twin)
    bound["_draw_inline"] = bound["_draw"]  # the CPU kernels' inlined `_draw`: one device function serves both
    bound["_entered_by_call"] = bound["_entered"]  # likewise `_entered` with `_draw` as a call
    for namespace in namespaces:  # bound after all are made: calls resolve when the kernel compiles
        namespace.update(bound)
    return bound


_GPU = on_gpu()
_episode_state, _next_normal, _static_episode = _GPU["episode_state"], _GPU["next_normal"], _GPU["_static_episode"]


@functools.cache
def _episode_kernel(size: int):
    """The episode kernel for a theta of `size` entries (the score kept in `size` registers per thread): one thread
    an episode, and the episode is `_simulate_affine`'s (dynamics._static_episode), with the interpreter for
    region rewards without the affine form."""

    @cuda.jit
    def episodes_kernel(
        tables, bins, score, starts, keys, episodes, out_z, out_score, out_risky, out_reached, out_steps
    ):
        """Episode e of policy p = e // episodes, one per thread. `tables` is the KernelArrays's, on the device, its
        fields passed one by one as `_simulate_affine` passes them (that kernel reads them into locals first, for its
        parallel loop; a thread here has none)."""
        e = cuda.grid(1)
        if e >= out_z.shape[0]:
            return
        stack = cuda.local.array(MAX_STACK, float64)
        acc = cuda.local.array(size, float64)
        no_cells = cuda.local.array((1, 1), int64)  # no path is recorded on the GPU
        no_rewards = cuda.local.array((1, 1), float64)
        p = e // episodes
        state = _episode_state(keys[p], e - p * episodes)
        for j in range(size):
            acc[j] = 0.0
        # the arrays one by one, not KernelTables (riskplan.engine.dynamics says why)
        out_z[e], out_risky[e], out_reached[e], out_steps[e] = _static_episode(
            tables.next_cell,
            tables.source_at,
            tables.src_off,
            tables.src_ops,
            tables.src_par,
            tables.horizon,
            tables.stop_at_source,
            tables.affine,
            tables.cell_affine,
            tables.cell_risky,
            tables.draw_uniform,
            tables.draw_normal,
            tables.region_of,
            tables.region_risky,
            tables.reg_off,
            tables.reg_ops,
            tables.reg_par,
            bins,
            score,
            p,
            e,
            starts[p],
            state,
            acc,
            stack,
            False,
            no_cells,
            no_rewards,
        )
        for j in range(size):
            out_score[e, j] = acc[j]

    return episodes_kernel
