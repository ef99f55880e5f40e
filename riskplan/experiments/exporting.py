"""`riskplan export`: replay finished runs into MLflow or TensorBoard, or give them a Foxglove layout (where it
writes is checked first, by riskplan.experiments.export_destinations).

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
import hashlib
import json
import math
import os
import re
import shutil
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from riskplan.experiments import ros2_bag
from riskplan.experiments.export_destinations import (
    check_experiment,
    check_installed,
    check_target,
    check_uri,
    file_store,
    mlflow_settings,
    one_writer,
    stops_export,
    store_errors,
    written_path,
)
from riskplan.experiments.reporting.collect import Broken, Duplicate, RunInfo, collect, flatten
from riskplan.experiments.sweep_worker import recorded_sha
from riskplan.run.foxglove_layout import LAYOUT_FILE, layout_for
from riskplan.util import lock
from riskplan.util.errors import BadInput, one_line
from riskplan.util.names import mlflow_keys
from riskplan.util.paths import (
    check_outside_runs,
    is_marked,
    replace_marked_dir,
    write_atomic,
)

EXPERIMENT = "riskplan"
EXPORT_VERSION = 2  # part of the fingerprint: a change of what an export writes replaces older exports


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
        "riskplan.config_sha": recorded_sha(run.path, run.config),
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


# ------------------------------------------------------------------------------------------- MLflow
REMOVED = "; what it had begun in the store was removed"  # a file store's, after a failure


class MlflowTarget:
    """An MLflow tracking store: one experiment, one MLflow run per riskplan run."""

    def __init__(self, uri: str, experiment: str = EXPERIMENT) -> None:
        self.uri = uri
        self.by_dir: dict[str, list] = {}
        self.store = file_store(uri)
        self.before = set(os.listdir(self.store)) if self.store is not None else set()  # the store's, not this export's
        self.kept: set[str] = set()  # the experiment folder's runs this export keeps: there before it, or finished
        self.finished = 0  # runs this export wrote whole
        self.left = ""  # what a failure left in the store, for its line
        try:
            self._open(experiment)
            if self.store is not None:
                self.kept = set(os.listdir(self.store / self.experiment_id))
        except Exception as err:
            if self.store is None or isinstance(err, OSError):  # a server's, a disk's: ExportFailed
                self._undo()
                raise
            raise BadInput(  # its files are the user's to mend: MLflow reads them as it goes, any way they break
                "--uri",
                f"{self.store} is a damaged MLflow file store ({_error_text(err)}); repair or move it, or give "
                f"another --uri",
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
        run_id = None
        try:
            start = int(rec.start * 1000)
            run_id = self.client.create_run(self.experiment_id, start, tags=tags, run_name=rec.name).info.run_id
            params = [Param(key, rec.params[k][:MAX_PARAM_VAL_LENGTH]) for k, key in mlflow_keys(rec.params).items()]
            for i in range(0, len(params), MAX_PARAMS_TAGS_PER_BATCH):
                self.client.log_batch(run_id, params=params[i : i + MAX_PARAMS_TAGS_PER_BATCH])
            keys = mlflow_keys(dict.fromkeys(key for key, *_ in rec.points))
            metrics = [Metric(keys[key], value, round(t * 1000), step) for key, step, value, t in rec.points]
            for i in range(0, len(metrics), MAX_METRICS_PER_BATCH):
                self.client.log_batch(run_id, metrics=metrics[i : i + MAX_METRICS_PER_BATCH])
            # the fingerprint last: a run cut short by an error is never taken for a finished export
            self.client.set_tag(run_id, "riskplan.fingerprint", rec.fingerprint)
            self.client.set_terminated(run_id, "FINISHED", end_time=round(rec.end * 1000))
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
        self.by_dir[rec.tags["riskplan.run_dir"]] = []
        self.kept.add(run_id)
        self.finished += 1
        return Exported(rec.path, "replaced" if old else "exported", f"mlflow run {run_id}")

    def _failed(self, run_id: str | None) -> None:
        """A run the store's failure cut short (`run_id`: None where it failed to be made): in a file store, its
        folder, however far it got, is removed with what else this export began there (a meta.yaml left empty by
        a full disk broke the store for every later export); in a server's or database's store, whose client
        removes nothing, it is marked failed, not left running."""
        if self.store is not None:
            folder = self.store / self.experiment_id
            with contextlib.suppress(OSError):
                for name in set(os.listdir(folder)) - self.kept:
                    shutil.rmtree(folder / name, ignore_errors=True)
            self._undo()
            if run_id is None or not (folder / run_id).exists():
                self.left = REMOVED
                return
        if run_id is not None:
            with contextlib.suppress(Exception):
                self.client.set_terminated(run_id, "FAILED")
            self.left = f"; its partial run {run_id} is left marked FAILED, and the next export replaces it"

    def _undo(self) -> None:
        """Remove from a file store what this export made there before the store failed, unless it finished a run:
        the experiment's folder (its meta.yaml left empty by a full disk broke the store for every later export)."""
        if self.store is None or self.finished:
            return
        for name in set(os.listdir(self.store)) - self.before - {lock.LOCK, ".trash"}:  # an empty store stays one
            shutil.rmtree(self.store / name, ignore_errors=True)
        self.left = REMOVED


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
        from tensorboard.summary.writer.record_writer import RecordWriter  # optional: the tensorboard extra

        values = {
            k: (v if isinstance(v, (bool, int, float, str)) else json.dumps(v)) for k, v in flatten(rec.config).items()
        }
        values["riskplan.group"] = rec.group
        by_step: dict[int, list] = {}
        for key, step, value, t in rec.points:
            by_step.setdefault(step, []).append((key, value, t))
        events = [
            Event(wall_time=rec.start, file_version="brain.Event:2"),  # what TensorBoard's writers begin with
            Event(
                wall_time=rec.start,
                step=0,
                summary=hparams.hparams_pb(values, trial_id=name, start_time_secs=int(rec.start)),
            ),
            Event(wall_time=rec.start, step=0, summary=text.text_pb("riskplan/run", _text_table(rec.tags))),
            *(
                Event(
                    wall_time=max(t for _, _, t in items),
                    step=step,
                    summary=Summary(value=[Summary.Value(tag=key, simple_value=value) for key, value, _ in items]),
                )
                for step, items in sorted(by_step.items())
            ),
        ]
        # written in this thread (TensorBoard's EventFileWriter writes in a thread of its own, which printed a full
        # disk's traceback beside the export's one line)
        with open(directory / f"events.out.tfevents.{int(rec.start):010d}.riskplan", "wb") as handle:
            records = RecordWriter(handle)
            for event in events:
                records.write(event.SerializeToString())


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
    written = written_path(target, destination)
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
    writer = None
    try:
        with mlflow_settings(destination), one_writer(target, destination):
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
                    if stops_export(err, target):
                        raise
                    result.skipped.append(Broken(info.path, _failure(err)))
                    continue
                result.done.append(done)
                if echo is not None:
                    echo(done)
    except store_errors(target) as err:  # the store failed (disk full, permissions, a server): one line
        left = getattr(writer, "left", "")  # MLflow's: what became of the run it was writing
        raise ExportFailed(f"{' '.join(filter(None, (target, destination)))}: {_failure(err)}{left}") from None
    return result
