"""Not riskplan: the baselines `riskplan bench` measures riskplan against, written without it.

Each module here imports numpy, numba and the standard library only, never riskplan (tests/experiments/
test_baselines.py checks it), so a baseline gains nothing from what it is compared with. That is why each one
writes out again what riskplan already has: the episode dynamics, the counter-based random stream and the ziggurat
(riskplan.engine.rng, riskplan.engine.rollout_kernels), the softmax policy and the CVaR gradient. They are twins
on purpose; their tests check that they keep riskplan's semantics.

- `one_kernel`: bench's first-run baseline, run as a script: numba and one plain rollout kernel.
- `plain_loop`: bench's loop baseline: Algorithm 1 as a plain loop on one_kernel's kernel.
- `python_loop`: bench's rollout baseline: episodes one by one in plain Python.

They live inside the package, not in the repository's bench/ folder, because `riskplan bench` runs them from an
installed riskplan too, and a wheel installs only the riskplan and hydra_plugins packages.
"""
