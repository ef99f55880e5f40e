"""riskplan.experiments.baselines: not riskplan. Each baseline imports nothing of riskplan's, ships with the package
(riskplan bench runs them from an installed riskplan), and its twins of riskplan's random stream keep its numbers."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np
import pytest
from numba import njit

from riskplan.engine import rng
from riskplan.experiments import baselines
from riskplan.experiments.baselines import one_kernel

FOLDER = Path(baselines.__file__).parent
ALLOWED = {"numpy", "numba"} | set(sys.stdlib_module_names)


def imported(path: Path) -> list[str]:
    """The top-level packages a module imports ("." for a relative import within its own package)."""
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [alias.name.split(".")[0] for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            names.append("." if node.level else node.module.split(".")[0])
    return names


def test_every_baseline_imports_nothing_of_riskplan():
    modules = sorted(p.name for p in FOLDER.glob("*.py"))
    assert modules == ["__init__.py", "one_kernel.py", "plain_loop.py", "python_loop.py"]
    for name in modules:
        outside = {n for n in imported(FOLDER / name) if n not in ALLOWED and n != "."}
        assert not outside, f"{name} imports {outside}"
    assert "." in imported(FOLDER / "plain_loop.py")  # one_kernel's kernel, relatively: no riskplan path


@njit
def _normals(module_normal, states):
    """Three normal draws from each state by a stream's next_normal: (values, end states)."""
    values, ends = np.empty((len(states), 3)), np.empty_like(states)
    for s in range(len(states)):
        state = states[s]
        for k in range(3):
            state, values[s, k] = module_normal(state)
        ends[s] = state
    return values, ends


@pytest.mark.slow  # about a second
def test_one_kernels_stream_and_ziggurat_are_riskplans_bit_for_bit():
    """The first-run baseline writes riskplan's stream out again (it may not import it): the same strips, and the
    same normals and end states from states that take the ziggurat's tail, its wedges and its fast path."""
    x, ratio = one_kernel.ziggurat()
    assert np.array_equal(x, rng.ZIG_X) and np.array_equal(ratio, rng.ZIG_RATIO)
    states = rng.episode_states(np.uint64(rng.stream_key(3, rng.TRAIN)), 20_000)
    ours, theirs = _normals(rng.next_normal, states), _normals(one_kernel.next_normal, states)
    assert np.array_equal(ours[0], theirs[0]) and np.array_equal(ours[1], theirs[1])
    assert (np.abs(ours[0]) > rng.ZIG_R).any()  # the tail was drawn
