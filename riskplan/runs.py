"""A finished (or killed) run on disk: load its tables, from parquet or rebuilt from run.mcap."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
import yaml

from riskplan.errors import BadInput

TABLES = ("metrics", "eval", "trajectories")


@dataclass
class Run:
    """One run: its config, tables and summary; `complete` is False for a killed or partial run."""

    path: Path
    config: dict
    metrics: pd.DataFrame
    eval: pd.DataFrame
    trajectories: pd.DataFrame
    summary: dict | None
    complete: bool
    problem: str | None = field(default=None)


def is_run_dir(path: Path) -> bool:
    """A run directory holds a run.mcap or a .hydra/config.yaml."""
    return (path / "run.mcap").is_file() or (path / ".hydra" / "config.yaml").is_file()


def find_runs(paths: list[Path]) -> list[Path]:
    """Every run directory at or below the given paths, sorted; BadInput for a path that holds none."""
    found: list[Path] = []
    for root in paths:
        root = Path(root)
        if not root.exists():
            raise BadInput(str(root), "does not exist; give a run, sweep or reproduce directory")
        here = sorted({p.parent for p in root.rglob("run.mcap")}
                      | {p.parent.parent for p in root.rglob(".hydra/config.yaml")})
        if not here:
            raise BadInput(str(root), "holds no run (no run.mcap or .hydra/config.yaml below it); "
                                      "give a directory written by riskplan train, sweep or reproduce")
        found.extend(here)
    return sorted(dict.fromkeys(found))


def load_run(path: str | Path) -> Run:
    """Load a run: parquet tables when all are there, else rebuilt from run.mcap (a killed run included)."""
    path = Path(path)
    if not path.is_dir() or not is_run_dir(path):
        raise BadInput(str(path), "holds no run (no run.mcap or .hydra/config.yaml); give a run directory")
    config = _config(path)
    summary_file = path / "summary.json"
    if all((path / f"{name}.parquet").is_file() for name in TABLES) and summary_file.is_file():
        try:
            tables = {name: pd.read_parquet(path / f"{name}.parquet") for name in TABLES}
            summary = json.loads(summary_file.read_text())
            return Run(path, config, tables["metrics"], tables["eval"], tables["trajectories"], summary, True)
        except (OSError, ValueError) as err:  # a damaged table: fall back to the log of record
            damaged = f"unreadable tables ({err}); rebuilt from run.mcap"
    else:
        damaged = None
    if not (path / "run.mcap").is_file():
        return Run(path, config, pd.DataFrame(), pd.DataFrame(), pd.DataFrame(), None, False,
                   "no run.mcap and no tables: the run never started or its files were removed")
    from riskplan.record import read_log

    log = read_log(path / "run.mcap")
    problem = log.problem or damaged
    return Run(path, config or log.metadata.get("config", {}), log.metrics, log.eval, log.trajectories,
               log.summary, log.complete, problem)


def _config(path: Path) -> dict:
    """The run's resolved config from .hydra/config.yaml (empty when missing)."""
    file = path / ".hydra" / "config.yaml"
    if not file.is_file():
        return {}
    return yaml.safe_load(file.read_text()) or {}
