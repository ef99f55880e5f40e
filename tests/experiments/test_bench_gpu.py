"""riskplan bench's GPU rows: skipped with the reason where there is no GPU or no numba-cuda, and their code run on
numba-cuda's simulator at a tiny size (a subprocess: the simulator must be on before numba.cuda is imported), where
every episode is the CPU kernel's."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from riskplan.experiments.bench_gpu import Skipped, bench_gpu
from riskplan.util.checks import installed

needs_numba_cuda = pytest.mark.skipif(not installed("numba_cuda"), reason="numba-cuda is not installed")


def test_without_numba_cuda_the_rows_are_skipped_with_the_install_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "numba_cuda", None)  # as if it were not installed
    with pytest.raises(Skipped, match=r"^numba-cuda is not installed \(pip install 'riskplan\[cuda\]'\)$"):
        bench_gpu(quick=True)


@needs_numba_cuda
def test_without_a_gpu_the_rows_are_skipped_with_the_reason():
    from riskplan.engine import cuda_rollout

    if cuda_rollout.gpu_problem() is None:
        pytest.skip("this machine has a GPU: riskplan bench measures it")
    with pytest.raises(Skipped, match=r"^no GPU numba-cuda can use here \(.+\)$"):
        bench_gpu(quick=True)


SIMULATED = """
import json, warnings
warnings.filterwarnings("ignore", "overflow encountered", RuntimeWarning)
from riskplan.experiments.bench_gpu import bench_gpu
print(json.dumps(bench_gpu(True, runs=3, episodes=6, simulator_ok=True), default=float))
"""


@pytest.mark.slow  # a subprocess on the simulator: a few seconds
@needs_numba_cuda
def test_the_rows_on_the_simulator_find_every_episode_equal_to_the_cpus():
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    done = subprocess.run([sys.executable, "-c", SIMULATED], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    kernel, call, equal = json.loads(done.stdout.splitlines()[-1])
    assert kernel["measure"].startswith("GPU rollout kernel, 3 runs x 6 episodes") and kernel["value"] > 0
    assert call["unit"] == "steps/s" and call["baseline"] == kernel["baseline"] > 0
    assert (equal["value"], equal["ok"], equal["baseline"]) == (1.0, True, 18.0)
