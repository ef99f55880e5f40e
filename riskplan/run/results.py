"""A finished (or killed) run on disk: load its tables, from parquet or rebuilt from run.mcap."""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass, field
from html import escape
from pathlib import Path

import pandas as pd
import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from riskplan.config.typed import register_metres
from riskplan.run.columns import read_parquet
from riskplan.run.log_reader import read_log
from riskplan.run.run_files import CONFIG, RUN_LOG, SUMMARY, TABLES, is_run_dir, other_output, table_file
from riskplan.util.errors import BadInput
from riskplan.util.paths import shown_bytes, undecoded

SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml's when PyYAML has it: in C, as safe


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

    def headline(self) -> str:
        """What ran and how it ended, in one line: experiment, objective, team, iterations, CVaR with its interval."""
        risk = self.config.get("risk", {})
        robots = self.config.get("team", {}).get("robots", 1)
        what = f"{self.config.get('experiment', '?')}, {risk.get('measure', '?')} beta={risk.get('beta', '?')}"
        what += f", {robots} robots" if robots != 1 else ""
        iterations = int(self.metrics.iteration.max()) + 1 if len(self.metrics) else 0
        if not self.complete or not self.summary:
            return f"{what}, {iterations} iterations, incomplete: {self.problem}"
        cvar = self.summary.get("cvar", {})
        return (
            f"{what}, {iterations} iterations, CVaR {cvar.get('value', float('nan')):.1f} "
            f"[{cvar.get('low', float('nan')):.1f}, {cvar.get('high', float('nan')):.1f}]"
        )

    def __repr__(self) -> str:
        return f"Run('{self.path}': {self.headline()})"

    def _repr_html_(self) -> str:
        """A small table for notebooks: the run, its status and the headline figures with their 95% intervals."""
        rows = [("run", str(self.path)), ("what", self.headline().split(", CVaR")[0])]
        if self.complete and self.summary:
            for name in ("mean", "cvar", "value_at_risk"):
                f = self.summary.get(name, {})
                rows.append(
                    (
                        name,
                        f"{f.get('value', float('nan')):.1f} [{f.get('low', float('nan')):.1f}, "
                        f"{f.get('high', float('nan')):.1f}]",
                    )
                )
            rows.append(("P(risky)", f"{self.summary.get('risky_fraction', float('nan')):.1%}"))
        else:
            rows.append(("status", f"incomplete: {self.problem}"))
        rows.append(("tables", ", ".join(f"{name} {len(getattr(self, name))} rows" for name in TABLES)))
        body = "".join(
            f"<tr><th style='text-align:left'>{escape(k)}</th><td style='text-align:left'>{escape(v)}</td></tr>"
            for k, v in rows
        )
        return f"<table><caption style='text-align:left'><b>riskplan Run</b></caption>{body}</table>"


def find_runs(paths: list[Path]) -> list[Path]:
    """Every run directory at or below the given paths, sorted; BadInput for a path that holds none."""
    found: list[Path] = []
    for root in paths:
        root = Path(root)
        if not root.exists():
            raise BadInput(str(root), "does not exist; give a run, sweep or reproduce directory")
        here = sorted(
            {p.parent for p in root.rglob(RUN_LOG)} | {p.parent.parent for p in root.rglob(CONFIG)}  # .hydra/'s
        )
        if not here:
            raise BadInput(
                str(root),
                "holds no run (no run.mcap or .hydra/config.yaml below it); "
                "give a directory written by riskplan train, sweep or reproduce",
            )
        for path in [p for p in here if undecoded(p)]:  # renamed by hand: such a path cannot go into UTF-8 tables
            warnings.warn(
                f"skipped {shown_bytes(path)}: its name holds bytes this system's locale cannot decode", stacklevel=1
            )
        readable = [p for p in here if not undecoded(p)]
        if not readable:
            raise BadInput(str(root), "holds no run whose folder name this system's locale decodes (see above)")
        found.extend(readable)
    return sorted(dict.fromkeys(found))


def load_run(path: str | Path) -> Run:
    """Load a run: parquet tables when all are there, else rebuilt from run.mcap (a killed run included)."""
    path = Path(path)
    other = other_output(path) if path.is_dir() else None
    if other is not None:
        raise BadInput(str(path), f"holds {other}, not a run; give a run directory")
    if not path.is_dir() or not is_run_dir(path):
        raise BadInput(str(path), "holds no run (no run.mcap or .hydra/config.yaml); give a run directory")
    config = run_config(path)
    summary_file = path / SUMMARY
    if all((path / table_file(name)).is_file() for name in TABLES) and summary_file.is_file():
        try:
            summary = json.loads(summary_file.read_text())
            if not isinstance(summary, dict):  # `NaN`, a list: not what riskplan writes
                raise ValueError(f"{SUMMARY} holds a {type(summary).__name__}, not an object")
            return finished_run(path, config, summary)
        except (OSError, ValueError) as err:  # a damaged table: fall back to the log of record
            damaged = f"unreadable tables ({err}); rebuilt from run.mcap"
    else:
        damaged = None
    if not (path / RUN_LOG).is_file():
        return Run(
            path,
            config,
            pd.DataFrame(),
            pd.DataFrame(),
            pd.DataFrame(),
            None,
            False,
            "no run.mcap and no tables: the run never started or its files were removed",
        )
    log = read_log(path / RUN_LOG)
    problem = log.problem or damaged
    return Run(
        path,
        config or log.metadata.get("config", {}),
        log.metrics,
        log.eval,
        log.trajectories,
        log.summary,
        log.complete,
        problem,
    )


def finished_run(path: Path, config: dict, summary: dict) -> Run:
    """The Run of a finished run directory: its config and summary as given, its tables from the parquet files."""
    tables = {name: read_parquet(path / table_file(name)) for name in TABLES}
    return Run(path, config, tables["metrics"], tables["eval"], tables["trajectories"], summary, True)


def run_config(path: Path) -> dict:
    """The run's config from .hydra/config.yaml, interpolations resolved (empty when the file is missing).

    BadInput naming the file when it cannot be a config: unreadable, not valid YAML, not a mapping of keys, too
    large, or with an interpolation that does not resolve (${oc.env:UNSET}, a missing key, a self-reference).
    """
    file = path / CONFIG
    if not file.is_file():
        return {}
    try:
        if file.stat().st_size > CONFIG_BYTES:
            raise BadInput(
                str(file),
                f"is {file.stat().st_size} bytes, too large for a run's config "
                f"(at most {CONFIG_BYTES}); it was not written by riskplan",
            )
        data = yaml.load(file.read_text(encoding="utf-8"), Loader=SAFE_LOADER)
    except OSError as err:
        raise BadInput(str(file), f"cannot be read ({err.strerror or err})") from None
    except UnicodeDecodeError:
        raise BadInput(str(file), "is not text (not UTF-8); expected the YAML riskplan writes") from None
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        at = f" at line {where.line + 1}, column {where.column + 1}" if where is not None else ""
        problem = getattr(err, "problem", None) or type(err).__name__
        raise BadInput(str(file), f"is not valid YAML ({problem}{at})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise BadInput(str(file), f"holds a {_yaml_kind(data)}, not a mapping of config keys")
    if _nodes(data) > CONFIG_NODES:
        raise BadInput(
            str(file), f"expands to more than {CONFIG_NODES} values (YAML aliases?); it was not written by riskplan"
        )
    if _plain(data):  # nothing to resolve: OmegaConf would give the same dict back (10 ms a run)
        return data
    register_metres()  # a run placed in metres saved ${metres:x,y}
    try:
        resolved = OmegaConf.to_container(OmegaConf.create(data), resolve=True)
    except (OmegaConfBaseException, ValueError, TypeError, KeyError, RecursionError) as err:
        text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        unset = re.search(r"Environment variable '(.*?)' not found", text)
        if unset:
            text = f"the environment variable {unset.group(1)} is not set"
        key = getattr(err, "full_key", None)
        raise BadInput(
            str(file), f"has a value that cannot be resolved{f' at {key}' if key else ''} ({text})"
        ) from None
    return resolved if isinstance(resolved, dict) else {}


CONFIG_BYTES = 1_000_000  # a run's config is a few KB
CONFIG_NODES = 100_000  # values in a config, counting each use of a YAML alias


def _yaml_kind(data) -> str:
    """'list', 'string', 'number', ... for a YAML document that is not a mapping."""
    if isinstance(data, list):
        return "list"
    if isinstance(data, str):
        return "string"
    if isinstance(data, bool):
        return "boolean"
    if isinstance(data, (int, float)):
        return "number"
    return type(data).__name__


def _plain(data) -> bool:
    """Whether a YAML document holds only string keys and plain values (strings without an interpolation,
    numbers, booleans, nulls), in mappings and lists: what OmegaConf.create then to_container gives back as it is."""
    stack = [data]
    while stack:
        node = stack.pop()
        if isinstance(node, dict):
            if not all(isinstance(key, str) for key in node):
                return False
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
        elif isinstance(node, str):
            if "${" in node:
                return False
        elif node is not None and not isinstance(node, (bool, int, float)):
            return False
    return True


def _nodes(data, limit: int = CONFIG_NODES) -> int:
    """Values in a nested structure (aliases counted at each use), counting stops just past `limit`."""
    count, stack = 0, [data]
    while stack and count <= limit:
        node = stack.pop()
        count += 1
        if isinstance(node, dict):
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
    return count
