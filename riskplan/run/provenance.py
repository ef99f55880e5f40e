"""Where a run's numbers came from: riskplan's version, the git SHA, the main packages' versions, the host."""

from __future__ import annotations

import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

from riskplan.version import __version__

PACKAGES = ("numpy", "numba", "pandas", "pyarrow", "hydra-core", "omegaconf", "mcap", "matplotlib", "typer")


def provenance() -> dict:
    """Versions, host and git revision, for summary.json and the MCAP metadata."""
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
