"""Where a run's numbers came from: riskplan's version, the git SHA, the main packages' versions, the host."""

from __future__ import annotations

import copy
import functools
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

from riskplan.version import __version__

PACKAGES = ("numpy", "numba", "pandas", "pyarrow", "hydra-core", "omegaconf", "mcap", "orjson", "matplotlib", "typer")


def provenance() -> dict:
    """Versions, host and git revision, for summary.json and the MCAP metadata (a copy the caller may change)."""
    return copy.deepcopy(_provenance())


@functools.cache
def _provenance() -> dict:
    """`provenance`, looked up once per process: the code that runs is the code imported at its start, whatever
    happens to the checkout or the environment later (a run asks twice: the log's header and summary.json)."""
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "riskplan": __version__,
        "git_sha": _git_sha(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "host": platform.node(),
        "cpus": os.cpu_count(),
        "packages": versions,
    }


def _git_sha() -> str | None:
    """HEAD of the repository riskplan runs from, if any."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent, capture_output=True, text=True, timeout=5
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None
