"""`riskplan export`: replay finished runs into MLflow or TensorBoard, or give them a Foxglove layout.

    export_runs([Path("outputs/sweeps/...")], "mlflow", uri=None) -> ExportResult

What one run becomes (the same names in MLflow and TensorBoard):

- per-iteration metrics, one point per iteration (MLflow step and TensorBoard step = `iteration`): every numeric
  column of metrics.parquet but `iteration` and `robot`, as `train/<column>` for the run's headline policy
  (robot 0 of a centralized run, the network average -1 of a team, as in the report), and `robot_<i>/<column>`
  for each robot of a team. A NaN (`consensus_error` of one robot) is not logged;
- the summary, at the step after the last iteration: `summary/<name>` for every number in summary.json, and
  `summary/<name>_low`, `summary/<name>_high` for the `{value, low, high}` figures (`summary/cvar`,
  `summary/cvar_low`, `summary/cvar_high`, ...); nested keys are dotted (`summary/source_reached.safe`);
- the config as parameters: flattened dotted keys (`risk.beta`, `team.graph`, ...), lists as JSON text
  (MLflow params; TensorBoard hparams);
- tags: `riskplan.run_dir` (the absolute run directory), `riskplan.config_sha` (as in a sweep job's
  status.json), `riskplan.group` (the seed group's label, as in the report), `riskplan.group_sha` (the config
  without its seed: the same for every seed of a condition), `riskplan.seed`, `riskplan.headline_robot`,
  `riskplan.fingerprint` and `riskplan.provenance.*` (MLflow tags; TensorBoard: a text summary `riskplan/run`).

Idempotent: MLflow runs are found by their `riskplan.run_dir` tag; one with the same fingerprint (config,
summary and metrics) is left as it is ("unchanged", its group tags refreshed), any other is deleted and
written anew ("replaced"). TensorBoard gets one subdirectory per run, `<run name>-<hash of its path>`, with a
`riskplan-export.json` marker; it is replaced as a whole (written beside it, then renamed into place).

Broken, killed and failed runs are skipped with their reason, as in the report; never fatal. So is a run whose
export fails (a folder in its way, a table riskplan did not write); a full or read-only disk, or an MLflow store's
error, would fail every run the same way and stops the export (ExportFailed).
A run whose config and seed repeat another's (`riskplan.experiments.sweep_worker.run_identity`, as in the report)
is the same sample: it is exported once, as the first of them by path, and the others are listed as duplicates
(`ExportResult.duplicates`), not exported, so that no tracker counts a seed twice.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import json
import math
import os
import re
import socket
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlparse

import numpy as np
import pandas as pd

from riskplan.experiments import ros2_bag
from riskplan.experiments.reporting.collect import Broken, Duplicate, RunInfo, collect, flatten
from riskplan.experiments.sweep_worker import config_sha
from riskplan.run.foxglove_layout import LAYOUT_FILE, layout_for
from riskplan.util import lock
from riskplan.util.checks import require_installed
from riskplan.util.errors import BadInput, did_you_mean, one_line
from riskplan.util.names import mlflow_keys
from riskplan.util.paths import (
    MARKER,
    check_output_dir,
    check_output_file,
    check_outside_runs,
    is_marked,
    replace_marked_dir,
    write_atomic,
)

TARGETS = ("mlflow", "tensorboard", "foxglove", "ros2")
DEFAULT_URI = {"mlflow": Path("outputs") / "mlruns", "tensorboard": Path("outputs") / "tensorboard"}
EXPERIMENT = "riskplan"
EXPORT_VERSION = 2  # part of the fingerprint: a change of what an export writes replaces older exports
EXTRA = {
    "mlflow": ("mlflow", "mlflow-skinny"),
    "tensorboard": ("tensorboard", "tensorboard"),
    "ros2": ("mcap_ros2", "mcap-ros2-support"),
}
URI_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")  # file:, sqlite:, http:, databricks: (not C:\...)


class ExportFailed(Exception):
    """The destination could not be written at run time (one line, exit code 1)."""


class Skip(Exception):
    """This run cannot be exported (one line, the others go on)."""


@dataclass
class Record:
    """One run, in the terms of the export targets."""

    path: Path
    name: str
    config: dict
    params: dict[str, str]
    tags: dict[str, str]
    points: list[tuple[str, int, float, float]]  # (key, step, value, wall time in s)
    start: float  # s since the epoch
    end: float
    fingerprint: str
    group: str
    trajectories: pd.DataFrame  # as loaded: rebuilt from run.mcap when trajectories.parquet is damaged


@dataclass
class Exported:
    """What happened to one run: `action` is exported, replaced or unchanged; `where` names it there."""

    path: Path
    action: str
    where: str


@dataclass
class ExportResult:
    target: str
    destination: str
    done: list[Exported] = field(default_factory=list)
    skipped: list[Broken] = field(default_factory=list)
    duplicates: list[Duplicate] = field(default_factory=list)  # the same config and seed as an exported run

    def count(self, action: str) -> int:
        return sum(1 for d in self.done if d.action == action)


# ------------------------------------------------------------------------------------------- what a run is
def param_value(value: Any) -> str:
    """A flattened config value as text: strings as they are, everything else as JSON (0.1, true, null)."""
    return value if isinstance(value, str) else json.dumps(value)


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def summary_figures(summary: dict | None) -> dict[str, float]:
    """Every finite number in summary.json by dotted key; a {value, low, high} figure gives key, key_low, key_high.

    `provenance` and `schema_version` are not figures (provenance becomes tags)."""
    out: dict[str, float] = {}

    def walk(key: str, value: Any) -> None:
        if isinstance(value, dict):
            if {"value", "low", "high"} <= set(value):
                for suffix, part in (("", "value"), ("_low", "low"), ("_high", "high")):
                    number = _number(value[part])
                    if number is not None:
                        out[f"{key}{suffix}"] = number
                return
            for k, v in value.items():
                walk(f"{key}.{k}" if key else str(k), v)
        elif isinstance(value, (list, tuple)):
            for i, v in enumerate(value):
                walk(f"{key}.{i}", v)
        else:
            number = _number(value)
            if number is not None:
                out[key] = number

    for key, value in (summary or {}).items():
        if key not in ("provenance", "schema_version"):
            walk(str(key), value)
    return out


def metric_prefix(robot: int, headline: int) -> str:
    """train for the headline policy, robot_<i> for a team's robots (team for an average that is not the headline)."""
    if robot == headline:
        return "train"
    return "team" if robot < 0 else f"robot_{robot}"


def iteration_points(info: RunInfo, start: float) -> list[tuple[str, int, float, float]]:
    """(key, iteration, value, wall time) for every finite value of metrics.parquet but iteration and robot."""
    m = info.run.metrics.sort_values(["iteration", "robot"], kind="stable")
    columns = [
        c
        for c in m.columns
        if c not in ("iteration", "robot")
        and pd.api.types.is_numeric_dtype(m[c])
        and not pd.api.types.is_bool_dtype(m[c])
    ]
    headline = info.headline
    clock: dict[int, float] = {}
    if "seconds" in m.columns:
        own = m.loc[m.robot == headline, ["iteration", "seconds"]].drop_duplicates("iteration")
        elapsed = np.cumsum(np.nan_to_num(own.seconds.to_numpy(dtype=float), nan=0.0))
        clock = {int(i): start + float(s) for i, s in zip(own.iteration, elapsed)}
    points = []
    for robot, rows in m.groupby("robot", sort=True):
        prefix = metric_prefix(int(robot), headline)
        iterations = rows.iteration.to_numpy()
        for c in columns:
            values = rows[c].to_numpy(dtype=float)
            for it, v in zip(iterations, values):
                if math.isfinite(v):
                    points.append((f"{prefix}/{c}", int(it), float(v), clock.get(int(it), start)))
    return points


def _sha(data: Any) -> str:
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _start_time(path: Path) -> float:
    """When the run started, as far as its files tell: its .hydra/config.yaml, else the directory."""
    for candidate in (path / ".hydra" / "config.yaml", path):
        with contextlib.suppress(OSError):
            return candidate.stat().st_mtime
    return 0.0


def _table_sha(table: pd.DataFrame | None) -> str:
    """A table's columns and every value (pandas' row hashes): a number changed by hand is a change to export; its
    row count and last iteration alone said "unchanged"."""
    if table is None:
        return ""
    rows = pd.util.hash_pandas_object(table, index=False).to_numpy()
    return hashlib.sha256(json.dumps([str(c) for c in table.columns]).encode() + rows.tobytes()).hexdigest()


def run_record(info: RunInfo) -> Record:
    """A loaded, complete run as metrics, params and tags."""
    run = info.run
    path = Path(os.path.abspath(run.path))
    start = _start_time(path)
    points = iteration_points(info, start)
    last = int(run.metrics.iteration.max()) + 1 if len(run.metrics) else 0
    end = max([p[3] for p in points], default=start)
    points += [(f"summary/{k}", last, v, end) for k, v in summary_figures(run.summary).items()]
    flat = flatten(run.config)
    params = {k: param_value(v) for k, v in flat.items()}
    group = info.group.label if info.group is not None else ""
    fingerprint = _sha(
        {
            "version": EXPORT_VERSION,
            "config": run.config,
            "summary": run.summary,
            "metrics": _table_sha(run.metrics),
            "trajectories": _table_sha(run.trajectories),  # the ROS 2 bags' paths
        }
    )
    tags = {
        "riskplan.run_dir": str(path),
        "riskplan.config_sha": config_sha(run.config),
        "riskplan.group": group,
        "riskplan.group_sha": _sha({k: v for k, v in run.config.items() if k != "seed"}),
        "riskplan.seed": str(info.seed),
        "riskplan.headline_robot": str(info.headline),
        "riskplan.fingerprint": fingerprint,
    }
    provenance = (run.summary or {}).get("provenance")
    if isinstance(provenance, dict):
        tags.update({f"riskplan.provenance.{k}": param_value(v) for k, v in flatten(provenance).items()})
    return Record(path, path.name, run.config, params, tags, points, start, end, fingerprint, group, run.trajectories)


# ------------------------------------------------------------------------------------------- destinations
def check_target(to: str | None) -> str:
    """--to: one of TARGETS."""
    if to is None or not str(to).strip():
        raise BadInput("--to", f"missing; expected one of {', '.join(TARGETS)}, e.g. --to mlflow")
    name = str(to).strip().lower()
    if name not in TARGETS:
        raise BadInput("--to", f"got '{to}'; expected one of {', '.join(TARGETS)}{did_you_mean(to, TARGETS)}")
    return name


def check_uri(to: str, uri: str | None) -> str:
    """--uri for a target: an MLflow tracking URI or store directory, a TensorBoard log directory, nothing for
    foxglove, the bags' folder for ros2 (the command's --out). Returns the destination: a tracking URI (mlflow) or a
    directory (tensorboard, ros2), '' for foxglove and for ros2 into each run directory."""
    if to == "ros2":
        return "" if uri is None else str(check_output_dir(uri, "--out").expanduser().absolute())
    if to == "foxglove":
        if uri is not None:
            raise BadInput(
                "--uri", "--to foxglove writes foxglove_layout.json into each run directory and takes no --uri"
            )
        return ""
    if uri is None:
        uri = str(DEFAULT_URI[to])
    text = str(uri)
    if URI_SCHEME.match(text) and not text.startswith("file:"):
        if to == "tensorboard":  # its writer takes any text for a folder: http://x/tb became ./http:/x/tb
            raise BadInput(
                "--uri", f"{text}: TensorBoard writes a local folder, not a URI: give its path, e.g. /data/tb"
            )
        return check_tracking_uri(text)
    if text.startswith("file:"):  # a file URI names a directory, for TensorBoard as for MLflow
        text = _file_uri_path(text)
    check_output_dir(text, "--uri")
    directory = Path(os.path.abspath(os.path.expanduser(text)))
    ours, what, example = {
        "mlflow": (_is_mlflow_store, "an MLflow file store", "an MLflow store (e.g. outputs/mlruns)"),
        "tensorboard": (
            _is_tensorboard_export,
            "a TensorBoard export",
            "one riskplan export wrote (e.g. outputs/tensorboard)",
        ),
    }[to]
    if directory.is_dir() and any(p.name != lock.LOCK for p in directory.iterdir()) and not ours(directory):
        raise BadInput("--uri", f"{uri} holds files that are not {what}; give a new or empty directory, or {example}")
    return str(directory) if to == "tensorboard" else directory.as_uri()


def _parsed(uri: str):
    """urlparse of --uri, and its port read: BadInput for what it refuses (an unclosed '[', a port past 65535)."""
    try:
        parts = urlparse(uri)
        parts.port  # noqa: B018 - read to check it
    except ValueError as err:
        raise BadInput(
            "--uri", f"{uri} is not a valid URI ({err}); e.g. http://localhost:5000 or file:///data/mlruns"
        ) from None
    return parts


def _file_uri_path(uri: str) -> str:
    """The local path of a file: URI; BadInput for one naming another host, whose path would be written here."""
    parts = _parsed(uri)
    if not uri.startswith("file://"):
        return uri[len("file:") :]
    if parts.netloc not in ("", "localhost"):
        raise BadInput(
            "--uri", f"{uri} names the host {parts.netloc}; give a local path, e.g. file:///data/mlruns (three slashes)"
        )
    return unquote(parts.path)


# MLflow's own tracking URI schemes (its tracking store registry); a database's may add a driver: mysql+pymysql
DATABASES = ("sqlite", "postgresql", "mysql", "mssql")
TRACKING_SCHEMES = ("http", "https", "databricks", "databricks-uc", "uc", *DATABASES)
CONNECT_TIMEOUT = 5.0  # s: a server that does not accept a connection in this long is taken for absent


def check_tracking_uri(uri: str) -> str:
    """An MLflow tracking URI other than a file store, checked before MLflow gets it (which would retry for minutes,
    or take any text): a scheme MLflow or a plugin knows, a server that accepts a connection, a SQLite database file
    that can be written."""
    parts = _parsed(uri)
    scheme = parts.scheme.lower()
    schemes = {*TRACKING_SCHEMES, *(e.name for e in entry_points(group="mlflow.tracking_store"))}
    if scheme not in schemes and scheme.split("+")[0] not in DATABASES:
        raise BadInput(
            "--uri",
            f"{uri}: MLflow knows no scheme '{scheme}'; give a folder, http://host:5000 or sqlite:///mlflow.db"
            f"{did_you_mean(scheme, schemes)}",
        )
    if scheme in ("http", "https"):
        _check_reachable(uri, parts)
    elif scheme.split("+")[0] == "sqlite":
        database = parts.path[1:]  # SQLAlchemy's sqlite:///relative.db, sqlite:////absolute.db
        if database in ("", ":memory:"):
            raise BadInput(
                "--uri", f"{uri} is a database in memory, gone when the export ends; give a file: sqlite:///mlflow.db"
            )
        check_output_file(database, "--uri", "in .db")
    return uri


def _check_reachable(uri: str, parts) -> None:
    """BadInput unless the server of an http(s) URI accepts a TCP connection within CONNECT_TIMEOUT."""
    if not parts.hostname:
        raise BadInput("--uri", f"{uri} names no server; e.g. http://localhost:5000")
    port = parts.port or (443 if parts.scheme.lower() == "https" else 80)
    try:
        socket.create_connection((parts.hostname, port), timeout=CONNECT_TIMEOUT).close()
    except OSError as err:
        raise BadInput(
            "--uri",
            f"{uri}: no server answers at {parts.hostname}:{port} ({err.strerror or err}); start the MLflow server "
            f"(mlflow server --port {port}) or give another --uri",
        ) from None


def check_experiment(name: str) -> None:
    """--experiment: a name MLflow takes (at most its MAX_EXPERIMENT_NAME_LENGTH printable characters), checked
    before the store is opened: MLflow would refuse it after making the store's folder."""
    from mlflow.utils.validation import MAX_EXPERIMENT_NAME_LENGTH  # optional: the mlflow extra

    if len(name) > MAX_EXPERIMENT_NAME_LENGTH:
        raise BadInput(
            "--experiment",
            f"is {len(name)} characters long; MLflow takes a name of at most {MAX_EXPERIMENT_NAME_LENGTH}",
        )
    if not name.isprintable():
        raise BadInput("--experiment", f"got {name!r}; give a name of printable characters, e.g. riskplan")


def _is_mlflow_store(directory: Path) -> bool:
    """An MLflow file store: experiment folders with a meta.yaml, or its .trash."""
    return (directory / ".trash").is_dir() or any(p.is_file() for p in directory.glob("*/meta.yaml"))


def _is_tensorboard_export(directory: Path) -> bool:
    """A TensorBoard log directory: riskplan's run folders (with their marker), or another writer's event files."""
    return any(
        p.is_file()
        for pattern in (f"*/{MARKER}", "events.out.tfevents.*", "*/events.out.tfevents.*")
        for p in directory.glob(pattern)
    )


def check_installed(to: str) -> None:
    """The optional package a target needs; MissingExtra (bad input) naming the pip install when it is missing."""
    if to in EXTRA:
        module, package = EXTRA[to]
        require_installed(module, f"--to {to}", f"the {package} package", to)


def _mlflow_settings(uri: str) -> dict[str, str]:
    """MLflow's settings for an export to `uri`: its file store allowed (MLflow >= 3.7 refuses it otherwise), and a
    server that stops answering given up on in about a minute (MLflow's defaults retry for minutes, silently)."""
    if uri.startswith("file:"):
        return {"MLFLOW_ALLOW_FILE_STORE": "true"}
    if uri.startswith(("http:", "https:")):
        return {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "1", "MLFLOW_HTTP_REQUEST_TIMEOUT": "30"}
    return {}


@contextlib.contextmanager
def mlflow_settings(uri: str):
    """_mlflow_settings in the environment while an export writes, each where the user set none."""
    added = {k: v for k, v in _mlflow_settings(uri).items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for key in added:
            os.environ.pop(key, None)


# ------------------------------------------------------------------------------------------- MLflow
class MlflowTarget:
    """An MLflow tracking store: one experiment, one MLflow run per riskplan run."""

    def __init__(self, uri: str, experiment: str = EXPERIMENT) -> None:
        self.uri = uri
        self.by_dir: dict[str, list] = {}
        try:
            self._open(experiment)
        except Exception as err:
            if not uri.startswith("file:") or isinstance(err, OSError):  # a server's, a disk's: ExportFailed
                raise
            raise BadInput(  # its files are the user's to mend: MLflow reads them as it goes, any way they break
                "--uri",
                f"{unquote(urlparse(uri).path)} is a damaged MLflow file store ({_error_text(err)}); repair or move "
                f"it, or give another --uri",
            ) from None

    def _open(self, experiment: str) -> None:
        """The experiment (made, or restored from deleted) and its runs by their riskplan.run_dir tag."""
        from mlflow.tracking import MlflowClient  # optional: the mlflow extra

        self.client = MlflowClient(tracking_uri=self.uri)
        found = self.client.get_experiment_by_name(experiment)
        if found is not None and found.lifecycle_stage != "active":
            self.client.restore_experiment(found.experiment_id)
        self.experiment_id = found.experiment_id if found is not None else self.client.create_experiment(experiment)
        token = None
        while True:
            page = self.client.search_runs([self.experiment_id], max_results=1000, page_token=token)
            for run in page:
                run_dir = run.data.tags.get("riskplan.run_dir")
                if run_dir:
                    self.by_dir.setdefault(run_dir, []).append(run)
            token = page.token
            if not token:
                break

    def write(self, rec: Record) -> Exported:
        from mlflow.entities import Metric, Param  # optional: the mlflow extra
        from mlflow.exceptions import MlflowException  # optional: the mlflow extra
        from mlflow.utils.validation import (  # optional: the mlflow extra
            MAX_METRICS_PER_BATCH,
            MAX_PARAM_VAL_LENGTH,
            MAX_PARAMS_TAGS_PER_BATCH,
            MAX_TAG_VAL_LENGTH,
        )

        old = self.by_dir.get(rec.tags["riskplan.run_dir"], [])
        same = [
            r for r in old if r.data.tags.get("riskplan.fingerprint") == rec.fingerprint and r.info.status == "FINISHED"
        ]
        if same:
            keep = same[0]
            for r in old:
                if r is not keep:
                    self.client.delete_run(r.info.run_id)
            for key in ("riskplan.group",):  # depends on which runs were exported together
                if keep.data.tags.get(key) != rec.tags[key]:
                    self.client.set_tag(keep.info.run_id, key, rec.tags[key])
            self.by_dir[rec.tags["riskplan.run_dir"]] = [keep]
            return Exported(rec.path, "unchanged", f"mlflow run {keep.info.run_id}")
        for r in old:
            self.client.delete_run(r.info.run_id)
        tags = {k: v[:MAX_TAG_VAL_LENGTH] for k, v in rec.tags.items() if k != "riskplan.fingerprint"}
        run = self.client.create_run(self.experiment_id, start_time=int(rec.start * 1000), tags=tags, run_name=rec.name)
        run_id = run.info.run_id
        try:
            params = [Param(key, rec.params[k][:MAX_PARAM_VAL_LENGTH]) for k, key in mlflow_keys(rec.params).items()]
            for i in range(0, len(params), MAX_PARAMS_TAGS_PER_BATCH):
                self.client.log_batch(run_id, params=params[i : i + MAX_PARAMS_TAGS_PER_BATCH])
            keys = mlflow_keys(dict.fromkeys(key for key, *_ in rec.points))
            metrics = [Metric(keys[key], value, round(t * 1000), step) for key, step, value, t in rec.points]
            for i in range(0, len(metrics), MAX_METRICS_PER_BATCH):
                self.client.log_batch(run_id, metrics=metrics[i : i + MAX_METRICS_PER_BATCH])
            # the fingerprint last: a run cut short by an error is never taken for a finished export
            self.client.set_tag(run_id, "riskplan.fingerprint", rec.fingerprint)
        except MlflowException as err:
            if err.error_code != "INVALID_PARAMETER_VALUE":  # the store's fault (disk, server): the export stops
                self._failed(run_id)
                raise
            with contextlib.suppress(Exception):  # this run's values MLflow refuses: the run alone is skipped
                self.client.delete_run(run_id)
            raise Skip(f"MLflow refused its values: {one_line(str(err).strip().splitlines()[0])}") from None
        except BaseException:
            self._failed(run_id)
            raise
        self.client.set_terminated(run_id, "FINISHED", end_time=round(rec.end * 1000))
        self.by_dir[rec.tags["riskplan.run_dir"]] = []
        return Exported(rec.path, "replaced" if old else "exported", f"mlflow run {run_id}")

    def _failed(self, run_id: str) -> None:
        """A run cut short: not left RUNNING, but marked failed, and replaced by the next export."""
        with contextlib.suppress(Exception):
            self.client.set_terminated(run_id, "FAILED")


# ------------------------------------------------------------------------------------------- TensorBoard
def tensorboard_name(path: Path) -> str:
    """The run's subdirectory of the log directory: its name (file-name safe) and a hash of its full path."""
    safe = re.sub(r"[^A-Za-z0-9._=,+-]", "_", path.name).strip(".") or "run"
    digest = hashlib.sha256(str(path).encode()).hexdigest()[:8]
    return f"{safe[:100]}-{digest}"


def _text_table(tags: dict[str, str]) -> str:
    rows = "\n".join(f"| {k} | {v.replace('|', '/')} |" for k, v in tags.items())
    return f"| tag | value |\n| --- | --- |\n{rows}\n"


FLOAT32_MAX = float(np.finfo(np.float32).max)


class TensorboardTarget:
    """A TensorBoard log directory: one subdirectory of event files per run."""

    def __init__(self, logdir: str) -> None:
        self.logdir = Path(logdir)

    def write(self, rec: Record) -> Exported:
        name = tensorboard_name(rec.path)
        target = self.logdir / name
        marker = {
            "run_dir": str(rec.path),
            "fingerprint": rec.fingerprint,
            "group": rec.group,
            "version": EXPORT_VERSION,
        }
        if is_marked(
            target,
            marker,
            lambda: Skip(f"{target} exists and is not a TensorBoard log of riskplan export's; move it away"),
        ):
            return Exported(rec.path, "unchanged", str(target))
        beyond = sorted({key for key, _, value, _ in rec.points if abs(value) > FLOAT32_MAX})
        if beyond:  # a scalar is a float32 in TensorBoard: these would read as inf
            kept = " and ".join(
                sorted({"summary.json" if k.startswith("summary/") else "metrics.parquet" for k in beyond})
            )
            warnings.warn(
                f"{rec.path}: {', '.join(beyond)} left out of TensorBoard at the steps beyond float32's range "
                f"(±3.4e38), which it would show as inf; the exact values stay in {kept}",
                stacklevel=2,
            )
            rec = dataclasses.replace(rec, points=[p for p in rec.points if abs(p[2]) <= FLOAT32_MAX])
        status = replace_marked_dir(target, marker, lambda tmp: self._events(tmp, name, rec))
        return Exported(rec.path, status, str(target))

    @staticmethod
    def _events(directory: Path, name: str, rec: Record) -> None:
        from tensorboard.compat.proto.event_pb2 import Event  # optional: the tensorboard extra
        from tensorboard.compat.proto.summary_pb2 import Summary  # optional: the tensorboard extra
        from tensorboard.plugins.hparams import summary_v2 as hparams  # optional: the tensorboard extra
        from tensorboard.plugins.text import summary_v2 as text  # optional: the tensorboard extra
        from tensorboard.summary.writer.event_file_writer import EventFileWriter  # optional: the tensorboard extra

        writer = EventFileWriter(str(directory), max_queue_size=1024, flush_secs=3600)
        try:
            values = {
                k: (v if isinstance(v, (bool, int, float, str)) else json.dumps(v))
                for k, v in flatten(rec.config).items()
            }
            values["riskplan.group"] = rec.group
            writer.add_event(
                Event(
                    wall_time=rec.start,
                    step=0,
                    summary=hparams.hparams_pb(values, trial_id=name, start_time_secs=int(rec.start)),
                )
            )
            writer.add_event(
                Event(wall_time=rec.start, step=0, summary=text.text_pb("riskplan/run", _text_table(rec.tags)))
            )
            by_step: dict[int, list] = {}
            for key, step, value, t in rec.points:
                by_step.setdefault(step, []).append((key, value, t))
            for step in sorted(by_step):
                items = by_step[step]
                writer.add_event(
                    Event(
                        wall_time=max(t for _, _, t in items),
                        step=step,
                        summary=Summary(value=[Summary.Value(tag=key, simple_value=value) for key, value, _ in items]),
                    )
                )
        finally:
            writer.close()


# ------------------------------------------------------------------------------------------- Foxglove
class FoxgloveTarget:
    """foxglove_layout.json in each run directory."""

    def write(self, rec: Record) -> Exported:
        path = rec.path / LAYOUT_FILE
        text = json.dumps(layout_for(rec.config), indent=2) + "\n"
        with contextlib.suppress(OSError):
            if path.read_text(encoding="utf-8") == text:
                return Exported(rec.path, "unchanged", str(path))
        existed = path.exists()
        write_atomic(path, text)
        return Exported(rec.path, "replaced" if existed else "exported", str(path))


# ------------------------------------------------------------------------------------------- ROS 2
class Ros2Target:
    """One rosbag2 directory per run (riskplan.experiments.ros2_bag): in `out`, or in each run directory."""

    def __init__(self, out: str) -> None:
        self.out = Path(out) if out else None

    def write(self, rec: Record) -> Exported:
        try:
            action, where = ros2_bag.write_run(
                rec.path, rec.config, rec.trajectories, self.out, rec.start, rec.fingerprint
            )
        except BadInput as err:  # its world cannot be rebuilt (a map moved), or the bag's folder is someone else's
            raise Skip(str(err)) from None
        return Exported(rec.path, action, str(where))


# ------------------------------------------------------------------------------------------- the command's work
def _store_errors(target: str) -> tuple[type[BaseException], ...]:
    """What a failure of the whole destination raises: a full or read-only disk, and MLflow's own exception (a
    server, a damaged store)."""
    if target == "mlflow":
        from mlflow.exceptions import MlflowException  # optional: the mlflow extra

        return OSError, MlflowException, ImportError  # ImportError: a store that needs the full mlflow
    return (OSError,)


# a disk that cannot take any more: every other run would fail the same way, so the export stops
WHOLE_DISK = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)


def _stops_export(err: Exception, target: str) -> bool:
    """Whether a failure to export one run is the destination's, which stops the export; any other (a folder in
    the way, a table not written by riskplan) is that run's own, which is skipped."""
    if isinstance(err, OSError):
        return err.errno in WHOLE_DISK
    return isinstance(err, _store_errors(target))


def _error_text(err: BaseException) -> str:
    """'Type: its first line', as one line."""
    text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return f"{type(err).__name__}: {one_line(text)}"


def _failure(err: BaseException) -> str:
    return f"could not be written ({_error_text(err)})"


def prepare(to: str | None, uri: str | None) -> tuple[str, str]:
    """Check --to, --uri and the optional package, writing nothing: (target, destination)."""
    target = check_target(to)
    destination = check_uri(target, uri)
    check_installed(target)
    return target, destination


def _written_path(target: str, destination: str) -> Path | None:
    """The local folder (or SQLite file) an export writes into; None for each run directory or a server."""
    if target in ("tensorboard", "ros2"):
        return Path(destination) if destination else None
    parts = urlparse(destination)
    if parts.scheme == "file":
        return Path(unquote(parts.path))
    return Path(parts.path[1:]) if parts.scheme.split("+")[0] == "sqlite" else None


def _one_writer(target: str, destination: str) -> contextlib.AbstractContextManager:
    """The destination directory's writers' lock, held while the runs are exported (a TensorBoard log directory, the
    bags' folder, an MLflow file store): two exports at once made two experiments of one name in a store, or failed
    on each other's temp folders. A server or database store locks itself; each run directory has its own lock."""
    directory = _written_path(target, destination)
    if directory is None or (target == "mlflow" and not destination.startswith("file:")):
        return contextlib.nullcontext()
    return lock.hold_lock(directory, f"{target} export destination", make=True)


def export_runs(
    paths: list[Path],
    to: str | None,
    uri: str | None = None,
    *,
    experiment: str = EXPERIMENT,
    echo: Callable[[Exported], None] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ExportResult:
    """Export every run under `paths`. BadInput (nothing written) for a bad --to or --uri, a missing package or a
    path without runs; ExportFailed when the destination cannot be written. `echo`: each run as it is exported;
    `progress(done, total)`: the runs loaded so far, before."""
    target, destination = prepare(to, uri)
    if target == "mlflow":
        check_experiment(experiment)
    if not paths:
        raise BadInput(
            "DIRS",
            f"give one or more run, sweep or reproduce directories, e.g. riskplan export outputs/runs --to {target}",
        )
    collected = collect([Path(p) for p in paths], progress)
    written = _written_path(target, destination)
    if written is not None:
        found = [*collected.runs, *collected.broken, *collected.duplicates, *collected.landscapes]
        check_outside_runs(written, [Path(r.path) for r in found], "--out" if target == "ros2" else "--uri")
    result = ExportResult(target, destination or "each run directory")
    result.skipped = list(collected.broken) + [
        Broken(Path(scan.path), "a landscape, not a training run") for scan in collected.landscapes
    ]
    result.duplicates = list(collected.duplicates)  # one sample: exported once, as the run each repeats
    if not collected.runs:
        return result
    try:
        with mlflow_settings(destination), _one_writer(target, destination):
            writer = {
                "mlflow": lambda: MlflowTarget(destination, experiment),
                "tensorboard": lambda: TensorboardTarget(destination),
                "foxglove": FoxgloveTarget,
                "ros2": lambda: Ros2Target(destination),
            }[target]()
            for info in collected.runs:
                try:
                    done = writer.write(run_record(info))
                except Skip as err:
                    result.skipped.append(Broken(info.path, str(err)))
                    continue
                except Exception as err:  # one run's failure is reported, the others go on
                    if _stops_export(err, target):
                        raise
                    result.skipped.append(Broken(info.path, _failure(err)))
                    continue
                result.done.append(done)
                if echo is not None:
                    echo(done)
    except _store_errors(target) as err:  # the store failed (disk full, permissions, a server): one line
        raise ExportFailed(f"{' '.join(filter(None, (target, destination)))}: {_failure(err)}") from None
    return result
