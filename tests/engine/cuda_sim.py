"""The GPU kernels of riskplan.engine.cuda_rollout on numba-cuda's simulator, for tests/engine/test_cuda_rollout.py.

`python tests/engine/cuda_sim.py OUT.npz` runs every case of `CASES` through engine.device=cuda (the simulator must
be on before numba.cuda is imported: the test sets NUMBA_ENABLE_CUDASIM=1 in this process's environment) and saves
what the kernels returned; the test compares it with the CPU kernel in its own process. Importing this module
imports no numba.cuda: the cases and the choice of ziggurat states are plain numpy, shared by both sides.
"""

from __future__ import annotations

import sys
import warnings

import numpy as np

from riskplan.engine import rng

FIELDS = ("total_reward", "score", "risky_steps", "source_reached", "steps")

# name -> (overrides, theta rows (one per policy, or None: the team's theta0), episodes per policy). Tiny worlds and
# few episodes: the simulator runs each thread as Python.
CASES = {
    "paper_single": ([], [[20.0, 20.0], [5.0, -3.0], [0.0, 0.0]], 24),
    "paper_team": (["experiment=paper_team"], None, 8),
    "features": (["policy.features=[signals,risky,stay]"], [[20.0, 20.0, -2.0, 0.5], [1.0, 3.0, 4.0, -1.0]], 16),
    "interpreter": (  # a mixture region reward: every region's reward through the program interpreter
        ["world.regions.1.reward={mixture:[{weight:0.7,of:{uniform:[0,100]}},{weight:0.3,of:{bernoulli:0.5}}]}"],
        [[20.0, 20.0], [2.0, 1.0]],
        16,
    ),
    "long": (["world.stop_at_source=false", "world.horizon=40"], [[3.0, 1.0], [0.0, 0.0]], 12),
    "mobile": (["world.sources.0.motion={kind:random_walk,prob:0.5}"], [[20.0, 20.0]], 8),  # the CPU kernel
    "tabular": (["policy.kind=tabular"], None, 8),  # the CPU kernel
}
BATCH_SEEDS = (3, 11)  # engine.step.batched_rollouts over two runs of the paper world
ITERATION = 2  # the iteration whose streams every case draws from


def case_inputs(name: str, device: str):
    """(setup, thetas, start cells, keys, episodes) of a case, with engine.device=`device`."""
    from riskplan.engine.step import starts
    from riskplan.run.build import build_setup
    from riskplan.run.compose import compose

    overrides, rows, episodes = CASES[name]
    setup = build_setup(compose([*overrides, "seed=5", f"engine.device={device}"], validate=False))
    thetas = np.tile(setup.theta0, (setup.robots, 1)) if rows is None else np.array(rows)
    cells = starts(setup)
    cells = cells if len(cells) == len(thetas) else np.repeat(cells[:1], len(thetas))
    keys = rng.robot_keys(5, rng.TRAIN, ITERATION, len(thetas))
    return setup, thetas, cells, keys, episodes


def batch_setups(device: str):
    """Two runs of the paper world (seeds BATCH_SEEDS) for engine.step.batched_rollouts, with their thetas."""
    from riskplan.run.build import build_setup
    from riskplan.run.compose import compose

    setups = [
        build_setup(compose([f"seed={seed}", "train.samples=20", f"engine.device={device}"], validate=False))
        for seed in BATCH_SEEDS
    ]
    return setups, [np.array([[20.0, 20.0]]), np.array([[4.0, 9.0]])]


def _mix(z: np.ndarray) -> np.ndarray:
    """riskplan.engine.rng.mix on uint64 arrays (numpy wraps modulo 2^64)."""
    with np.errstate(over="ignore"):
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def ziggurat_states(count: int = 12) -> np.ndarray:
    """Stream states whose next normal draw takes each path of rng.next_normal: `count` each into the tail beyond
    r (strip 0), into a wedge (rng._normal_edge), and straight through the fast path."""
    with np.errstate(over="ignore"):
        states = _mix(np.arange(1, 4_000_001, dtype=np.uint64))
        bits = _mix(states + np.uint64(rng.GOLDEN))
    strip = (bits & np.uint64(255)).astype(np.int64)
    u = ((bits >> np.uint64(12)) + 0.5) * (1.0 / 2251799813685248.0) - 1.0
    edge = np.abs(u) >= rng.ZIG_RATIO[strip]
    tail, wedge, fast = edge & (strip == 0), edge & (strip > 0), ~edge
    return np.concatenate([states[tail][:count], states[wedge][:count], states[fast][:count]])


DRAWS = 3  # normal draws from each ziggurat state
cuda = None  # numba.cuda once `gpu_normals` imports it (never on import)


def gpu_normals(states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """DRAWS normals from each state by cuda_rollout._next_normal on the device: (values (S, DRAWS), end states)."""
    global cuda  # a module global, as the simulator swaps a kernel's global `cuda` for its own
    from numba import cuda

    from riskplan.engine import cuda_rollout

    @cuda.jit
    def draw(states, values, ends):
        s = cuda.grid(1)
        if s < states.shape[0]:
            state = states[s]
            for k in range(values.shape[1]):
                state, values[s, k] = cuda_rollout._next_normal(state)
            ends[s] = state

    values = np.zeros((len(states), DRAWS))
    ends = np.zeros(len(states), dtype=np.uint64)
    draw[(len(states) + 31) // 32, 32](states, values, ends)
    return values, ends


def main(out: str) -> None:
    warnings.filterwarnings("ignore", "overflow encountered", RuntimeWarning)  # uint64 wraps, as on the device
    from riskplan.engine import cuda_rollout
    from riskplan.engine.step import batched_rollouts, simulator

    assert cuda_rollout.gpu_problem() is None, "run with NUMBA_ENABLE_CUDASIM=1, or on a machine with a GPU"
    saved = {}
    for name in CASES:
        setup, thetas, cells, keys, episodes = case_inputs(name, "cuda")
        assert simulator(setup) is cuda_rollout.simulate
        batch = simulator(setup)(setup.world, setup.kernel, thetas, cells, keys, episodes)
        saved |= {f"{name}.{field}": getattr(batch, field) for field in FIELDS}
        saved[f"{name}.ported"] = np.array(cuda_rollout.ported(setup.kernel))
    setups, thetas = batch_setups("cuda")
    for i, (z, scores) in enumerate(batched_rollouts(setups, ITERATION, thetas)):
        saved[f"batch{i}.z"], saved[f"batch{i}.scores"] = z, scores
    saved["normals.values"], saved["normals.ends"] = gpu_normals(ziggurat_states())
    np.savez(out, **saved)


if __name__ == "__main__":
    main(sys.argv[1])
