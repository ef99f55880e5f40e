"""engine.device=cuda against the CPU kernel, bit for bit, on numba-cuda's simulator (NUMBA_ENABLE_CUDASIM=1).

The simulator must be on before numba.cuda is first imported, so the GPU side runs in a subprocess
(tests/engine/cuda_sim.py, and `riskplan train` for a whole run) with the variable set; the CPU side runs here. The
simulator runs each GPU thread as Python: tiny worlds, few episodes. Without numba-cuda (the cuda or test extra)
these tests are skipped.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from numba import njit

from riskplan.engine import rng
from riskplan.engine.rollout import simulate
from riskplan.engine.step import batched_rollouts, rollouts
from riskplan.util.checks import installed

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import cuda_sim  # noqa: E402  (beside this file; imports no numba.cuda)

pytestmark = [
    pytest.mark.slow,  # subprocesses on the simulator: a few seconds
    pytest.mark.skipif(
        not installed("numba_cuda"), reason="numba-cuda is not installed (pip install 'riskplan[cuda]')"
    ),
]


def simulator_env() -> dict[str, str]:
    """The GPU side's environment: numba-cuda's simulator, or with RISKPLAN_CUDA_TESTS=gpu the machine's real GPU
    (the same comparisons, for a session with a GPU: `RISKPLAN_CUDA_TESTS=gpu pytest tests/engine/test_cuda_rollout.py`)."""
    if os.environ.get("RISKPLAN_CUDA_TESTS") == "gpu":
        return {k: v for k, v in os.environ.items() if k != "NUMBA_ENABLE_CUDASIM"}
    return {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}


@pytest.fixture(scope="module")
def gpu(tmp_path_factory) -> dict[str, np.ndarray]:
    """What the GPU kernels returned for every case of cuda_sim, on the simulator."""
    out = tmp_path_factory.mktemp("cuda") / "gpu.npz"
    done = subprocess.run(
        [sys.executable, str(HERE / "cuda_sim.py"), str(out)], env=simulator_env(), capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-3000:]
    with np.load(out) as saved:
        return {name: saved[name] for name in saved.files}


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal shapes, dtypes and bytes (so -0.0 != 0.0 and every NaN payload counts)."""
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("name", list(cuda_sim.CASES))
def test_every_output_of_the_gpu_kernel_is_the_cpu_kernels_bit_for_bit(gpu, name):
    setup, thetas, cells, keys, episodes = cuda_sim.case_inputs(name, "cpu")
    cpu = simulate(setup.world, setup.kernel, thetas, cells, keys, episodes)
    for field in cuda_sim.FIELDS:
        assert same_bits(gpu[f"{name}.{field}"], getattr(cpu, field)), field
    assert bool(gpu[f"{name}.ported"]) == (name not in ("mobile", "tabular"))  # those fall back to the CPU kernel
    assert len(np.unique(cpu.total_reward)) > len(cpu.total_reward) // 2  # episodes that differ, not one repeated


def test_a_batch_of_runs_on_the_gpu_is_each_run_on_the_cpu(gpu):
    setups, thetas = cuda_sim.batch_setups("cpu")
    for i, (setup, theta) in enumerate(zip(setups, thetas)):
        z, scores = rollouts(setup, cuda_sim.ITERATION, theta)
        assert same_bits(gpu[f"batch{i}.z"], z) and same_bits(gpu[f"batch{i}.scores"], scores)
    cpu = batched_rollouts(setups, cuda_sim.ITERATION, thetas)
    assert same_bits(gpu["batch0.z"], cpu[0][0]) and not same_bits(gpu["batch0.z"], gpu["batch1.z"])


@njit
def cpu_normals(states, draws):
    """rng.next_normal `draws` times from each state, as the CPU kernel calls it: (values, end states)."""
    values = np.empty((len(states), draws))
    ends = np.empty_like(states)
    for s in range(len(states)):
        state = states[s]
        for k in range(draws):
            state, values[s, k] = rng.next_normal(state)
        ends[s] = state
    return values, ends


def test_the_ziggurats_tail_wedges_and_fast_path_draw_the_cpus_numbers(gpu):
    states = cuda_sim.ziggurat_states()
    assert len(states) == 36  # 12 each: tail, wedge, fast path
    values, ends = cpu_normals(states, cuda_sim.DRAWS)
    assert same_bits(gpu["normals.values"], values) and same_bits(gpu["normals.ends"], ends)
    assert np.all(np.abs(values[:12, 0]) > rng.ZIG_R)  # the tail's draws lie beyond r


TRAIN = [
    "train.iterations=3",
    "train.samples=24",
    "train.eval_episodes=40",
    "train.paths=2",
    "train.bootstrap=40",
    "train.checkpoint_every=2",
    "seed=4",
]


def train(out: Path, device: str, env: dict[str, str]) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "riskplan", "train", *TRAIN, f"engine.device={device}", f"hydra.run.dir={out}"],
        env=env,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr[-3000:]


CPU_RUN = """
import sys
from typer.testing import CliRunner
from riskplan.cli import app
result = CliRunner().invoke(app, ["train", *sys.argv[2:], "engine.device=cpu", f"hydra.run.dir={sys.argv[1]}"])
assert result.exit_code == 0, result.output
print(sorted(m for m in sys.modules if m.startswith(("numba.cuda", "numba_cuda", "riskplan.engine.cuda"))))
"""


@pytest.fixture(scope="module")
def cpu_run(tmp_path_factory) -> tuple[Path, str]:
    """The CPU run of TRAIN in a new process (the GPU run's reference), and the numba-cuda modules it imported."""
    out = tmp_path_factory.mktemp("cpu") / "run"
    done = subprocess.run([sys.executable, "-c", CPU_RUN, str(out), *TRAIN], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return out, done.stdout.splitlines()[-1]


def test_a_run_on_the_gpu_is_the_run_on_the_cpu(tmp_path, cpu_run):
    runs = {"gpu": tmp_path / "gpu", "cpu": cpu_run[0]}
    train(runs["gpu"], "cuda", simulator_env())
    assert "device: cuda" in (runs["gpu"] / ".hydra" / "config.yaml").read_text()
    for table in ("eval", "trajectories"):
        gpu, cpu = (pd.read_parquet(runs[d] / f"{table}.parquet") for d in ("gpu", "cpu"))
        pd.testing.assert_frame_equal(gpu, cpu, check_exact=True)
    gpu, cpu = (pd.read_parquet(runs[d] / "metrics.parquet") for d in ("gpu", "cpu"))
    pd.testing.assert_frame_equal(gpu.drop(columns="seconds"), cpu.drop(columns="seconds"), check_exact=True)
    gpu, cpu = (json.loads((runs[d] / "summary.json").read_text()) for d in ("gpu", "cpu"))
    timed = ("wall_time", "throughput_episodes_per_s", "provenance")
    assert {k: v for k, v in gpu.items() if k not in timed} == {k: v for k, v in cpu.items() if k not in timed}
    assert gpu["theta_final"] == cpu["theta_final"] and cpu["theta_final"] != [[20.0, 20.0]]


def test_a_run_on_the_cpu_never_imports_numba_cuda(cpu_run):
    assert cpu_run[1] == "[]"
