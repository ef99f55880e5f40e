"""The algorithm: worlds, policies, the episode kernels, the estimators and measures, the step and the loop."""

from riskplan.engine import kernel_cache

kernel_cache.clear_stale()  # before any cached kernel loads: numba alone would keep a stale one
