"""`riskplan export` refuses a bad destination at once, in one line, and writes nothing: a URI MLflow would retry
for minutes or take for a folder, a file URI naming another host, a folder that is not an export of the target's, a
damaged MLflow store, a destination inside a run folder. One run that cannot be exported (a damaged table, a folder
in its way) is skipped with one line and the others are exported; TensorBoard is never given a value it shows as
inf."""

from __future__ import annotations

import json
import os
import shutil
import socket
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from support import TINY
from typer.testing import CliRunner

from riskplan import compose, train
from riskplan.cli import app
from riskplan.experiments.export_destinations import check_tracking_uri, check_uri, mlflow_settings
from riskplan.experiments.exporting import tensorboard_name
from riskplan.run.foxglove_layout import LAYOUT_FILE
from riskplan.util.lock import LOCK

runner = CliRunner()


def invoke(*args: str):
    result = runner.invoke(app, ["export", *args])
    assert "Traceback" not in result.output
    return result


def refused(result, start: str) -> None:
    """Bad input: exit code 2 and one line on stderr, starting `start`."""
    assert result.exit_code == 2, result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(start), result.stderr


def closed_port() -> int:
    """A local port nothing listens on (it was free a moment ago)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------------- destinations
@pytest.mark.parametrize(
    "to, uri, words",
    [
        ("mlflow", "http://127.0.0.1:{port}", "no server answers at 127.0.0.1:{port} (Connection refused)"),
        ("mlflow", "http://", "names no server"),
        ("mlflow", "http://localhost:99999", "is not a valid URI (Port out of range"),
        ("mlflow", "http://[::1", "is not a valid URI (Invalid IPv6 URL)"),
        ("mlflow", "file://[::1", "is not a valid URI (Invalid IPv6 URL)"),
        ("mlflow", "htp:/x", "MLflow knows no scheme 'htp'; give a folder, http://host:5000 or sqlite:///mlflow.db"),
        ("mlflow", "mlflow+foo://bar", "MLflow knows no scheme 'mlflow+foo'"),
        ("mlflow", "sqlite://", "is a database in memory"),
        ("mlflow", "sqlite:////proc/x.db", "/proc/x.db is under /proc, a kernel filesystem"),
        ("mlflow", "file://somehost/tb", "names the host somehost; give a local path"),
        ("tensorboard", "file://somehost/tb", "names the host somehost"),
        ("tensorboard", "http://x/tb", "http://x/tb: TensorBoard writes a local folder, not a URI"),
    ],
)
def test_a_bad_uri_is_one_line_at_once_and_writes_nothing(tmp_path, monkeypatch, to, uri, words):
    """Each of these took minutes of MLflow's retries, a traceback, or wrote somewhere else (/tb, ./http:/x/tb)."""
    monkeypatch.chdir(tmp_path)
    port = closed_port()
    uri = uri.format(port=port)
    result = invoke(str(tmp_path), "--to", to, "--uri", uri)
    refused(result, "error: --uri: ")
    assert words.format(port=port) in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_server_that_accepts_a_connection_and_a_local_file_uri_are_taken(tmp_path):
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        uri = f"http://127.0.0.1:{server.getsockname()[1]}"
        assert check_tracking_uri(uri) == uri
    assert check_uri("tensorboard", f"file://localhost{tmp_path}/tb") == str(tmp_path / "tb")
    assert check_uri("mlflow", f"file://{tmp_path}/mlruns") == (tmp_path / "mlruns").as_uri()


def test_mlflow_gives_up_on_a_silent_server_in_seconds_unless_told_otherwise(monkeypatch):
    """MLflow retries a server 7 times over minutes by default: an export sets fewer, and a shorter timeout, where
    the user set none, and leaves the environment as it was afterwards."""
    monkeypatch.delenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", raising=False)
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "77")
    with mlflow_settings("http://host:5000"):
        assert os.environ["MLFLOW_HTTP_REQUEST_MAX_RETRIES"] == "1"
        assert os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] == "77"  # the user's
    assert "MLFLOW_HTTP_REQUEST_MAX_RETRIES" not in os.environ and os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] == "77"


def test_a_tensorboard_uri_holding_other_files_is_refused(tmp_path):
    """A folder of runs (or anything else) would get TensorBoard's folders mixed in, as MLflow's --uri refuses."""
    logdir = tmp_path / "mine"
    logdir.mkdir()
    (logdir / "notes.txt").write_text("mine")
    refused(
        invoke(str(tmp_path), "--to", "tensorboard", "--uri", str(logdir)),
        f"error: --uri: {logdir} holds files that are not a TensorBoard export",
    )
    assert [p.name for p in logdir.iterdir()] == ["notes.txt"]


@pytest.mark.parametrize(
    "args, line",
    [
        (["--to", "mlflow", "--experiment", "   "], "error: --experiment: got '   '; give an MLflow experiment name"),
        (["--to", "foxglove", "--out", "x"], "error: --out: only --to ros2 writes into --out; --to foxglove writes"),
        (["--to", "foxglove", "--uri", "x"], "error: --uri: --to foxglove writes foxglove_layout.json into each run"),
    ],
)
def test_option_lines_show_the_value_as_typed_and_name_the_right_option(tmp_path, args, line):
    refused(invoke(str(tmp_path), *args), line)


# ------------------------------------------------------------------------------------------- runs
@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Two seeds of one condition."""
    root = tmp_path_factory.mktemp("safety") / "runs"
    for seed in (0, 1):
        train(compose([*TINY, f"seed={seed}"]), root / f"run_{seed}")
    return root


@pytest.fixture
def mine(runs, tmp_path) -> Path:
    """A copy of the runs, for a test to damage."""
    shutil.copytree(runs, tmp_path / "runs")
    return tmp_path / "runs"


@pytest.mark.slow  # two runs, then exports
def test_a_destination_inside_a_run_folder_is_refused(mine, monkeypatch):
    pytest.importorskip("mlflow")
    pytest.importorskip("tensorboard")
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    run = (mine / "run_1").resolve()
    before = sorted(p.name for p in run.iterdir())
    for args in (
        ["--to", "ros2", "--out", str(run / "rosbag2")],
        ["--to", "ros2", "--out", str(run)],
        ["--to", "tensorboard", "--uri", str(run / "tb")],
        ["--to", "mlflow", "--uri", str(run / "mlruns_inside")],
        ["--to", "mlflow", "--uri", f"sqlite:///{run}/mlflow.db"],
    ):
        key = "--out" if "--out" in args else "--uri"
        result = invoke(str(mine), *args)
        refused(result, f"error: {key}: ")
        assert f"is inside the run folder {run}; give a folder outside the runs" in result.stderr
    assert sorted(p.name for p in run.iterdir()) == before


@pytest.mark.slow  # two runs, then exports
def test_a_damaged_mlflow_store_is_one_line_naming_it(mine, tmp_path, monkeypatch):
    pytest.importorskip("mlflow")
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    store = tmp_path / "mlruns"
    assert invoke(str(mine), "--to", "mlflow", "--uri", str(store)).exit_code == 0
    meta = next(store.glob("*/*/meta.yaml"))
    meta.write_bytes(meta.read_bytes()[:10])  # a run's record cut short
    refused(invoke(str(mine), "--to", "mlflow", "--uri", str(store)), f"error: --uri: {store} is a damaged MLflow")
    (experiment,) = [p for p in store.glob("*/meta.yaml") if p.parent.name != "0"]
    experiment.write_text("garbage: [\n")
    result = invoke(str(mine), "--to", "mlflow", "--uri", str(store))
    refused(result, f"error: --uri: {store} is a damaged MLflow file store (ParserError: ")
    assert result.stderr.rstrip().endswith("repair or move it, or give another --uri")


@pytest.mark.slow  # two runs, then exports
def test_ros2_reads_a_damaged_table_as_loaded_and_skips_a_foreign_one_alone(mine, tmp_path):
    """A cut trajectories.parquet is rebuilt from run.mcap, as the report and TensorBoard read it (the bag once
    read the file itself: a traceback that stopped the export); one with another table's columns is skipped with
    one line, and the other run is exported."""
    pytest.importorskip("mcap_ros2")
    good = mine / "run_0" / "trajectories.parquet"
    expected = pd.read_parquet(good)
    os.truncate(good, 3000)
    shutil.copy(mine / "run_1" / "metrics.parquet", mine / "run_1" / "trajectories.parquet")
    out = tmp_path / "bags"
    result = invoke(str(mine), "--to", "ros2", "--out", str(out))
    assert result.exit_code == 0, result.output
    assert "1 exported, 0 replaced, 0 unchanged, 1 skipped" in result.stdout
    assert result.stderr.splitlines() == [
        f"skipped {mine / 'run_1'}: trajectories table: lacks the column(s) policy, episode, step, x, y: it was "
        f"not written by riskplan; remove trajectories.parquet and the run's tables are rebuilt from run.mcap"
    ]
    from rosbags.rosbag2 import Reader

    (bag,) = [p for p in out.iterdir() if p.name != LOCK]
    with Reader(bag) as reader:
        paths = sum(c.msgcount for c in reader.connections if c.topic == "/robot_0/path")
    final = expected.loc[(expected.policy == "final") & (expected.robot == 0)]
    assert paths == final.episode.nunique() > 0  # every sampled episode, from the table rebuilt from run.mcap


@pytest.mark.slow  # two runs, then exports
def test_a_run_whose_file_cannot_be_written_is_skipped_and_the_others_exported(mine):
    """A folder where run_0's layout goes stopped the export of every run (`error: foxglove : ...`)."""
    layout = mine / "run_0" / LAYOUT_FILE
    layout.unlink()
    (layout / "inside").mkdir(parents=True)
    (mine / "run_1" / LAYOUT_FILE).unlink()
    result = invoke(str(mine), "--to", "foxglove")
    assert result.exit_code == 0, result.output
    assert "1 exported, 0 replaced, 0 unchanged, 1 skipped" in result.stdout
    (line,) = result.stderr.splitlines()
    assert line.startswith(f"skipped {mine / 'run_0'}: could not be written (IsADirectoryError: ")
    assert json.loads((mine / "run_1" / LAYOUT_FILE).read_text())["layout"]
    assert [p.name for p in layout.iterdir()] == ["inside"]


@pytest.mark.slow  # two runs, then exports
def test_tensorboard_leaves_out_a_value_beyond_float32_with_a_warning(mine, tmp_path):
    """A finite float64 past float32's range became inf in the event files: it is left out, the rest written."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    table = mine / "run_0" / "metrics.parquet"
    m = pd.read_parquet(table)
    m.loc[m.iteration == 1, "grad_norm"] = 1e300
    m.to_parquet(table, index=False)
    logdir = tmp_path / "tb"
    with pytest.warns(UserWarning) as told:  # the CLI prints it as one `warning: ...` line
        result = invoke(str(mine), "--to", "tensorboard", "--uri", str(logdir))
    assert result.exit_code == 0 and "2 exported" in result.stdout, result.output
    assert [str(w.message) for w in told] == [
        f"{(mine / 'run_0').resolve()}: train/grad_norm left out of TensorBoard at the steps beyond float32's range "
        f"(±3.4e38), which it would show as inf; the exact values stay in metrics.parquet"
    ]
    acc = EventAccumulator(str(logdir / tensorboard_name((mine / "run_0").resolve())), size_guidance={"scalars": 0})
    acc.Reload()
    steps = [e.step for e in acc.Scalars("train/grad_norm")]
    assert steps == [i for i in sorted(m.iteration.unique()) if i != 1]
    values = [e.value for tag in acc.Tags()["scalars"] for e in acc.Scalars(tag)]
    assert np.isfinite(values).all()
