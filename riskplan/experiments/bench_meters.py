"""The meters `riskplan bench`'s rows read: the best time of a call, a command's wall time in a new process, and this
process's resident memory."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path


def rss_mb(field: str = "VmRSS") -> float:
    """Resident (VmRSS) or peak resident (VmHWM) memory of this process, in MB (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def reset_peak() -> None:
    """Reset VmHWM to the current RSS (Linux >= 4.0), so the next peak is this section's own."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def best_time(fn, repeats: int, inner: int) -> float:
    """Best mean seconds per call over `repeats` rounds of `inner` calls (noise-robust)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(inner):
            fn()
        best = min(best, (time.perf_counter() - start) / inner)
    return best


def user_env() -> dict[str, str]:
    """The environment a user's shell gives a command: Python writes and reads its bytecode caches (a machine
    that sets PYTHONDONTWRITEBYTECODE would compile every module from source at every start)."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def wall(argv: list[str], cwd: Path, marker: str | None = None, env: dict[str, str] | None = None) -> float:
    """Seconds from starting `argv` to its end, or to the wall-clock time it prints after `marker`; `env`: variables
    set on top of the user's environment."""
    start = time.time()
    done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, check=True, env={**user_env(), **(env or {})})
    end = time.time()
    if marker is None:
        return end - start
    stamps = [float(line.split()[1]) for line in done.stderr.splitlines() if line.startswith(marker)]
    if not stamps:
        raise RuntimeError(f"no {marker} line from {argv[:3]}: {done.stderr[-300:]}")
    return stamps[0] - start


def riskplan_command() -> list[str]:
    """The console script beside this interpreter, or the module."""
    script = Path(sys.executable).with_name("riskplan")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "riskplan"]
