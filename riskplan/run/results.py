"""A finished (or killed) run on disk: load its tables, from parquet or rebuilt from run.mcap."""

from __future__ import annotations

import errno
import io
import json
import os
import re
import stat
import warnings
from dataclasses import dataclass, field
from html import escape
from pathlib import Path

import pandas as pd
import yaml
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Footer, Metadata, MetadataIndex, SummaryOffset
from mcap.stream_reader import StreamReader
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from riskplan.config.typed import register_metres
from riskplan.run.columns import read_parquet
from riskplan.run.log_reader import read_log
from riskplan.run.record import MAGIC
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
            raise BadInput(str(root), f"{_absent(root)}; give a run, sweep or reproduce directory")
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


def _absent(root: Path) -> str:
    """Why a path given to read does not exist: a symbolic link on it that loops or leads nowhere, or nothing."""
    for part in (root, *root.parents):
        if part.is_symlink() and not part.exists():
            where = "is" if part == root else f"passes through {part},"
            try:
                os.stat(part)
            except OSError as err:
                if err.errno == errno.ELOOP:
                    return f"{where} a symbolic link in a loop"
            return f"{where} a symbolic link to {os.readlink(part)}, which does not exist"
    return "does not exist"


FILE_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a pipe"),
    (stat.S_ISSOCK, "a socket"),
)


def _not_a_file(path: Path) -> str:
    """What a path that should be a file is instead: 'a symbolic link to /dev/zero, a character device'."""
    try:
        mode = os.stat(path).st_mode
    except OSError as err:
        what = "in a loop" if err.errno == errno.ELOOP else "to nothing"
        return f"a symbolic link {what}"
    kind = next((name for test, name in FILE_KINDS if test(mode)), "not a regular file")
    return f"a symbolic link to {os.readlink(path)}, {kind}" if path.is_symlink() else kind


def load_run(path: str | Path) -> Run:
    """Load a run: parquet tables when all are there, else rebuilt from run.mcap (a killed run included)."""
    path = Path(path)
    other = other_output(path) if path.is_dir() else None
    if other is not None:
        raise BadInput(str(path), f"holds {other}, not a run; give a run directory")
    if not path.is_dir() or not is_run_dir(path):
        raise BadInput(str(path), "holds no run (no run.mcap or .hydra/config.yaml); give a run directory")
    log_file = path / RUN_LOG
    if (log_file.exists() or log_file.is_symlink()) and not log_file.is_file():
        raise BadInput(str(log_file), f"is {_not_a_file(log_file)}; a run's log is a regular file")
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
    if data is None:  # Hydra writes it in place: a full disk or a kill as the run began left it empty
        raise BadInput(str(file), "is empty: the run never started; remove the directory and train again")
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


def logged_config(path: Path) -> dict | None:
    """The config run.mcap recorded last (an extended run records its new one after the first), read through the
    summary section's index of its metadata: the footer, the summary offsets, the metadata index group and that one
    record, a few small reads whatever the log's size. None for a log without that index (a killed run's has no
    footer: read_log reads it whole), without a config record, or that is not a regular file."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a pipe would block the open
            return None
        with open(path, "rb") as f:
            footer_at = f.seek(0, io.SEEK_END) - len(MAGIC) - FOOTER_BYTES
            footer = _record_at(f, footer_at)
            if not isinstance(footer, Footer) or f.read() != MAGIC:
                return None
            start, end = footer.summary_start, footer.summary_offset_start or footer_at
            for offset in _records(f, footer.summary_offset_start, footer_at):  # the index's group, if listed
                if isinstance(offset, SummaryOffset) and offset.group_opcode == Opcode.METADATA_INDEX:
                    start, end = offset.group_start, offset.group_start + offset.group_length
            indexed = [r.offset for r in _records(f, start, end) if isinstance(r, MetadataIndex) and r.name == "config"]
            record = _record_at(f, max(indexed)) if indexed else None
            data = json.loads(record.metadata["json"]) if isinstance(record, Metadata) else None
    except (OSError, ValueError, KeyError, RuntimeError, McapError):  # damaged: as if it had no index
        return None
    return data if isinstance(data, dict) else None


def log_cut_short(path: Path) -> bool:
    """Whether a run's log lacks the MCAP magic that ends every closed log: a finished run's log cut short since (a
    copy or a disk that failed), whose tables still hold the run but which Foxglove cannot open whole."""
    try:
        with open(path, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode) or f.seek(0, io.SEEK_END) < len(MAGIC):
                return True
            f.seek(-len(MAGIC), io.SEEK_END)
            return f.read() != MAGIC
    except FileNotFoundError:  # a run reported from its tables alone: no log to open
        return False
    except OSError:
        return True


FOOTER_BYTES = 29  # the footer record: its opcode, length and three fields


def _record_at(f, offset: int):
    """The MCAP record that starts at byte `offset` of the open file."""
    f.seek(offset)
    return next(StreamReader(f, skip_magic=True).records)


def _records(f, start: int, end: int):
    """The MCAP records from byte `start` to byte `end` of the open file (none for a `start` of 0: no section)."""
    position = start
    while start and position < end:
        record = _record_at(f, position)
        position = f.tell()
        yield record


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
