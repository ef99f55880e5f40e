"""Limits that keep a run inside the machine: estimates of memory and time, checked before anything runs.

Every limit names the environment variable that raises it. Defaults: memory, 80% of the memory available when the
check runs; time, 24 hours of estimated simulation per run; sweeps, 10,000 jobs.
"""

from __future__ import annotations

import math
import os

from riskplan.util.errors import BadInput

MEMORY_ENV = "RISKPLAN_MEMORY_GB"
HOURS_ENV = "RISKPLAN_MAX_HOURS"
JOBS_ENV = "RISKPLAN_MAX_JOBS"
NUMBA_THREADS_ENV = "NUMBA_NUM_THREADS"
DEFAULT_HOURS = 24.0
DEFAULT_JOBS = 10_000
STEPS_PER_SECOND = 20e6  # conservative trajectory-steps/s of the kernel on 2 cores, below riskplan bench's rollout row


def _env_number(name: str, default: float) -> float:
    """A positive number from the environment, or the default; BadInput naming the variable otherwise."""
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise BadInput(name, f"got '{text}'; expected a positive number")
    return value


def check_numba_threads() -> None:
    """NUMBA_NUM_THREADS, which numba reads when it loads: 0 or -1 failed every command with numba's traceback, and
    'abc' printed a warning holding one. A whole number >= 1, or unset (numba then takes every core)."""
    text = os.environ.get(NUMBA_THREADS_ENV)
    if text is not None and not (text.strip().isascii() and text.strip().isdigit() and int(text) >= 1):
        raise BadInput(
            NUMBA_THREADS_ENV, f"got '{text}'; expected a whole number of threads >= 1, or unset it (every core)"
        )


def cpu_count() -> int:
    """Cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def available_memory() -> float:
    """Bytes of memory available now (MemAvailable), or the physical memory where /proc/meminfo is missing."""
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def memory_budget() -> tuple[float, str]:
    """(bytes a run may use, how that limit was set)."""
    text = os.environ.get(MEMORY_ENV, "").strip()
    if text:
        gigabytes = _env_number(MEMORY_ENV, 0)
        if gigabytes < 1e-9:  # below one byte: a limit no run could meet, shown as "1e-311 B"
            raise BadInput(MEMORY_ENV, f"got '{text}'; expected at least 1e-9 GB (one byte), or unset it")
        return gigabytes * 1e9, f"{MEMORY_ENV}"
    return 0.8 * available_memory(), "80% of this machine's available memory"


def time_budget() -> float:
    """Seconds of estimated work a run may take."""
    return _env_number(HOURS_ENV, DEFAULT_HOURS) * 3600.0


def job_budget() -> int:
    """Jobs a sweep may hold."""
    value = _env_number(JOBS_ENV, DEFAULT_JOBS)
    if value != int(value):  # 0.5 jobs would read as 0, 1.9 as 1
        raise BadInput(JOBS_ENV, f"got '{os.environ[JOBS_ENV].strip()}'; expected a whole number of jobs >= 1")
    return int(value)


def size(value: float) -> str:
    """Bytes as a short human string."""
    value = float(min(value, 1e300))
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if value < 1000 or unit == "PB":
            return f"{value:.3g} {unit}"
        value /= 1000
    return f"{value:.3g} PB"


def duration(seconds: float) -> str:
    """Seconds as a short human string."""
    seconds = float(min(seconds, 1e300))
    if seconds < 1:
        return f"{seconds:.2g} s"  # a limit of 1e-7 hours is 0.00036 s, not "0 s"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 3 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.3g} days"


def check_memory(key: str, need: float, what: str) -> None:
    """BadInput naming `key` when `what` needs more than the memory budget."""
    budget, source = memory_budget()
    if not need <= budget:
        raise BadInput(
            key,
            f"{what} needs about {size(need)} of memory, more than the {size(budget)} allowed "
            f"({source}); lower it, or raise the limit with {MEMORY_ENV}=<GB>",
        )


def check_time(key: str, seconds: float, what: str) -> None:
    """BadInput naming `key` when `what` is estimated to take longer than the time budget."""
    budget = time_budget()
    if not seconds <= budget:
        raise BadInput(
            key,
            f"{what} would take about {duration(seconds)} (at {STEPS_PER_SECOND / 1e6:.0f}M "
            f"trajectory-steps/s), more than the {duration(budget)} allowed; lower it, or raise the "
            f"limit with {HOURS_ENV}=<hours>",
        )


def check_jobs(key: str, jobs: int) -> None:
    """BadInput naming `key` when a sweep would hold more jobs than the job budget."""
    budget = job_budget()
    if jobs > budget:
        raise BadInput(
            key,
            f"expands to {jobs if jobs < 10**15 else f'about 10^{len(str(jobs)) - 1}'} jobs, more than the {budget} allowed; sweep fewer "
            f"values, or raise "
            f"the limit with {JOBS_ENV}=<jobs>",
        )
