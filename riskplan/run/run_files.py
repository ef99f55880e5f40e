"""The files that make a run directory: what marks a directory as a run's, and the tables and summary a finished
run has (no pandas: `riskplan train` checks its directory with these before it starts)."""

from __future__ import annotations

from pathlib import Path

TABLES = ("metrics", "eval", "trajectories")  # <name>.parquet
FINISHED = ("summary.json", *(f"{name}.parquet" for name in TABLES))  # written when a run ends


def is_run_dir(path: Path) -> bool:
    """A run directory holds a run.mcap or a .hydra/config.yaml."""
    return (path / "run.mcap").is_file() or (path / ".hydra" / "config.yaml").is_file()


def has_finished(out: Path) -> bool:
    """Whether the run's final tables and summary are all there."""
    return all((out / name).is_file() for name in FINISHED)
