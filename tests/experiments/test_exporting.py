"""`riskplan export`: runs replayed into MLflow and TensorBoard are read back with the libraries' own readers
(MlflowClient over the file store, TensorBoard's EventAccumulator) and compared with the runs' metrics.parquet
and summary.json; re-exports neither duplicate nor go stale; broken runs are skipped; the Foxglove layout names
only topics the run's log holds."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from support import TINY, held_by_another_process
from typer.testing import CliRunner

from riskplan import compose, train
from riskplan.cli import app
from riskplan.experiments.exporting import (
    export_runs,
    metric_prefix,
    param_value,
    summary_figures,
    tensorboard_name,
)
from riskplan.experiments.reporting.collect import flatten
from riskplan.experiments.sweep_worker import config_sha
from riskplan.run.foxglove_layout import LAYOUT_FILE, layout, panels, topics, write_layout
from riskplan.util.lock import LOCK

runner = CliRunner()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Two seeds of one centralized condition, a team of 3, and a run killed before it finished."""
    root = tmp_path_factory.mktemp("export") / "runs"
    train(compose(TINY + ["seed=0"]), root / "single_0")
    train(compose(TINY + ["seed=1"]), root / "single_1")
    train(compose(TINY + ["experiment=paper_team"]), root / "team")
    killed = root / "killed"
    shutil.copytree(root / "single_0", killed)
    for name in ("metrics.parquet", "eval.parquet", "trajectories.parquet", "summary.json"):
        (killed / name).unlink()
    data = (killed / "run.mcap").read_bytes()
    (killed / "run.mcap").write_bytes(data[: len(data) // 2])
    return root


GOOD = ("single_0", "single_1", "team")


def metrics(run: Path) -> pd.DataFrame:
    return pd.read_parquet(run / "metrics.parquet")


def summary(run: Path) -> dict:
    return json.loads((run / "summary.json").read_text())


def config(run: Path) -> dict:
    import yaml

    return yaml.safe_load((run / ".hydra" / "config.yaml").read_text())


def expected_series(run: Path) -> dict[str, list[tuple[int, float]]]:
    """key -> [(step, value)] as the export should write it, from metrics.parquet and summary.json."""
    m = metrics(run)
    s = summary(run)
    headline = int(s["headline_robot"])
    out: dict[str, list] = {}
    for robot, rows in m.groupby("robot"):
        for c in m.columns:
            if c in ("iteration", "robot") or m[c].dtype == bool:  # flags (healthy) are not metrics
                continue
            points = [(int(i), float(v)) for i, v in zip(rows.iteration, rows[c]) if math.isfinite(v)]
            if points:
                out[f"{metric_prefix(int(robot), headline)}/{c}"] = points
    last = int(m.iteration.max()) + 1
    for k, v in summary_figures(s).items():
        out[f"summary/{k}"] = [(last, v)]
    return out


def invoke(*args: str):
    result = runner.invoke(app, ["export", *args])
    assert "Traceback" not in result.output
    return result


# ------------------------------------------------------------------------------------------- MLflow
def mlflow_runs(store: Path) -> dict[str, object]:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=store.resolve().as_uri())
    experiment = client.get_experiment_by_name("riskplan")
    found = client.search_runs([experiment.experiment_id])
    return client, {Path(r.data.tags["riskplan.run_dir"]).name: r for r in found}


@pytest.fixture
def file_store(monkeypatch):
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")  # MLflow >= 3.7 wants it to open a file store


@pytest.mark.slow  # the `runs` fixture: three runs and a killed one, then an export
def test_mlflow_holds_every_metric_summary_param_and_tag(runs, tmp_path, file_store):
    pytest.importorskip("mlflow")
    store = tmp_path / "mlruns"
    result = invoke(str(runs), "--to", "mlflow", "--uri", str(store))
    assert result.exit_code == 0, result.output
    assert f"skipped {runs / 'killed'}:" in result.stderr
    assert "3 run(s) to mlflow: 3 exported, 0 replaced, 0 unchanged, 1 skipped" in result.stdout

    client, found = mlflow_runs(store)
    assert sorted(found) == sorted(GOOD)
    for name in GOOD:
        run_dir, run = runs / name, found[name]
        assert run.info.status == "FINISHED" and run.info.run_name == name
        # the config as params, flattened with dotted keys
        assert run.data.params == {k: param_value(v) for k, v in flatten(config(run_dir)).items()}
        assert run.data.params["risk.beta"] == "0.1" and run.data.params["seed"] in ("0", "1")
        # every metric history, step = iteration, exactly the parquet / summary.json value
        series = expected_series(run_dir)
        assert set(run.data.metrics) == set(series)
        for key, points in series.items():
            history = sorted((m.step, m.value) for m in client.get_metric_history(run.info.run_id, key))
            assert history == points, key
        s = summary(run_dir)
        assert run.data.metrics["summary/cvar"] == s["cvar"]["value"]
        assert run.data.metrics["summary/cvar_low"] == s["cvar"]["low"]
        assert run.data.metrics["summary/cvar_high"] == s["cvar"]["high"]
        tags = run.data.tags
        assert tags["riskplan.run_dir"] == str(run_dir.resolve())
        assert tags["riskplan.config_sha"] == config_sha(config(run_dir))
        assert tags["riskplan.headline_robot"] == str(s["headline_robot"])
        assert tags["riskplan.provenance.git_sha"] == str(s["provenance"]["git_sha"])
    # robots: per-robot prefixes for the team, the headline (network average) under train/
    assert {"robot_0/cvar", "robot_1/cvar", "robot_2/cvar", "train/cvar"} <= set(found["team"].data.metrics)
    assert not any(k.startswith("robot_") for k in found["single_0"].data.metrics)
    assert "train/consensus_error" not in found["single_0"].data.metrics  # NaN for one robot: not logged
    # seed groups: the two seeds share a group, the team is another
    group = {
        name: (found[name].data.tags["riskplan.group"], found[name].data.tags["riskplan.group_sha"]) for name in GOOD
    }
    assert group["single_0"] == group["single_1"] != group["team"]


@pytest.mark.slow  # the `runs` fixture: three runs and a killed one, then an export
def test_mlflow_reexport_is_idempotent_and_replaces_a_changed_run(runs, tmp_path, file_store):
    pytest.importorskip("mlflow")
    mine = tmp_path / "runs"
    shutil.copytree(runs / "single_0", mine / "single_0")
    store = tmp_path / "mlruns"
    assert invoke(str(mine), "--to", "mlflow", "--uri", f"file:{store}").exit_code == 0
    _, first = mlflow_runs(store)

    again = invoke(str(mine), "--to", "mlflow", "--uri", f"file:{store}")
    assert again.exit_code == 0 and "0 exported, 0 replaced, 1 unchanged" in again.stdout
    _, second = mlflow_runs(store)
    assert [r.info.run_id for r in second.values()] == [r.info.run_id for r in first.values()]

    s = summary(mine / "single_0")  # the run changed (as after --resume train.iterations=N)
    s["cvar"]["value"] += 1.0
    (mine / "single_0" / "summary.json").write_text(json.dumps(s))
    third = invoke(str(mine), "--to", "mlflow", "--uri", f"file:{store}")
    assert third.exit_code == 0 and "0 exported, 1 replaced, 0 unchanged" in third.stdout
    _, after = mlflow_runs(store)  # active runs only: the old one is deleted, not duplicated
    assert len(after) == 1 and after["single_0"].info.run_id != first["single_0"].info.run_id
    assert after["single_0"].data.metrics["summary/cvar"] == s["cvar"]["value"]

    metrics = pd.read_parquet(mine / "single_0" / "metrics.parquet")  # a value changed, rows and columns alike
    metrics.loc[0, "mean"] *= 2.0  # was "unchanged": the fingerprint held the row count and last iteration only
    metrics.to_parquet(mine / "single_0" / "metrics.parquet")
    fourth = invoke(str(mine), "--to", "mlflow", "--uri", f"file:{store}")
    assert fourth.exit_code == 0 and "0 exported, 1 replaced, 0 unchanged" in fourth.stdout


@pytest.mark.slow  # a run, then an export
def test_a_source_name_mlflow_refuses_is_exported_under_a_safe_key(tmp_path, file_store):
    """A source called 'sáfe src/😀' (the CLI takes it) names summary figures MLflow refuses: its key keeps ASCII
    letters, digits, _-./ and spaces, the rest '_'; the run is exported whole and finished, never left RUNNING."""
    pytest.importorskip("mlflow")
    run = tmp_path / "runs" / "named"
    train(compose([*TINY, "world.sources.0.name='sáfe src/😀'"]), run)
    store = tmp_path / "mlruns"
    done = invoke(str(run), "--to", "mlflow", "--uri", f"file:{store}")
    assert done.exit_code == 0 and "1 exported" in done.stdout, done.output
    client, found = mlflow_runs(store)
    exported = found["named"]
    assert exported.info.status == "FINISHED" and exported.data.tags["riskplan.fingerprint"]
    named = [key for key in exported.data.metrics if "src" in key]
    assert named and all(re.fullmatch(r"[A-Za-z0-9_\-./ ]+", key) for key in named), named
    assert any("s_fe src/_" in key for key in named), named
    assert len(client.search_runs([exported.info.experiment_id], run_view_type=3)) == 1  # none left RUNNING


@pytest.mark.slow  # two runs, then exports
def test_names_mlflow_would_merge_stay_apart_and_a_run_it_refuses_is_skipped_alone(tmp_path, file_store, monkeypatch):
    """Sources 'x?' and 'x!' both become 'x_' in MLflow's characters: each keeps its own metric, with its own
    value. A run whose values MLflow refuses (a metric name past its 250 characters) is skipped with the reason and
    leaves no run in the store; the other run is exported."""
    pytest.importorskip("mlflow")
    from riskplan.experiments import exporting

    runs = tmp_path / "runs"
    train(compose([*TINY, "world.sources.0.name='x?'", "world.sources.1.name='x!'"]), runs / "a_named")
    train(compose([*TINY, "seed=1"]), runs / "b_refused")
    record = exporting.run_record

    def refused(info):  # what MLflow refuses, in one run only
        rec = record(info)
        if rec.name == "b_refused":
            rec.points.append(("x" * 300, 0, 1.0, rec.start))
        return rec

    monkeypatch.setattr(exporting, "run_record", refused)
    store = tmp_path / "mlruns"
    done = invoke(str(runs), "--to", "mlflow", "--uri", f"file:{store}")
    assert done.exit_code == 0 and "1 exported" in done.stdout, done.output
    assert "b_refused: MLflow refused its values: " in done.output
    _, found = mlflow_runs(store)
    assert set(found) == {"a_named"}  # the refused run was deleted, not left FAILED beside it
    reached = json.loads((runs / "a_named" / "summary.json").read_text())["source_reached"]
    metrics = found["a_named"].data.metrics
    assert metrics["summary/source_reached.x_"] == reached["x?"]
    assert metrics["summary/source_reached.x__1"] == reached["x!"]
    assert reached["x?"] != reached["x!"]  # two counts, which one key had merged


@pytest.mark.slow  # imports MLflow's name rules (near a second)
def test_an_mlflow_experiment_name_it_would_refuse_is_bad_input_before_the_store(tmp_path):
    pytest.importorskip("mlflow")
    store = tmp_path / "mlruns"
    for name, words in (("x" * 501, "is 501 characters long; MLflow takes a name of at most 500"), ("a\nb", "got 'a")):
        result = invoke(str(tmp_path), "--to", "mlflow", "--uri", str(store), "--experiment", name)
        assert result.exit_code == 2 and result.stderr.startswith(f"error: --experiment: {words}"), result.output
    assert not store.exists()


# ------------------------------------------------------------------------------------------- TensorBoard
def exported(logdir: Path) -> list[Path]:
    """The log directory's entries but its writers' lock."""
    return [p for p in logdir.iterdir() if p.name != LOCK]


def accumulator(directory: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(directory), size_guidance={"scalars": 0, "tensors": 0})
    acc.Reload()
    return acc


@pytest.mark.slow  # the `runs` fixture: three runs and a killed one, then an export
def test_tensorboard_scalars_per_step_equal_the_run_within_float32(runs, tmp_path):
    pytest.importorskip("tensorboard")
    logdir = tmp_path / "tb"
    result = invoke(str(runs), "--to", "tensorboard", "--uri", str(logdir))
    assert result.exit_code == 0, result.output
    assert "3 exported, 0 replaced, 0 unchanged, 1 skipped" in result.stdout
    assert sorted(p.name for p in exported(logdir)) == sorted(tensorboard_name((runs / n).resolve()) for n in GOOD)
    for name in GOOD:
        acc = accumulator(logdir / tensorboard_name((runs / name).resolve()))
        series = expected_series(runs / name)
        assert set(acc.Tags()["scalars"]) == set(series)
        for key, points in series.items():
            got = [(e.step, e.value) for e in acc.Scalars(key)]
            assert got == [(step, float(np.float32(v))) for step, v in points], key
        assert {"_hparams_/session_start_info", "riskplan/run"} <= set(acc.Tags()["tensors"])
        text = acc.Tensors("riskplan/run")[0].tensor_proto.string_val[0].decode()
        assert str((runs / name).resolve()) in text and config_sha(config(runs / name)) in text


@pytest.mark.slow  # the `runs` fixture: three runs and a killed one, then an export
def test_a_run_repeating_another_config_and_seed_is_exported_once(runs, tmp_path):
    pytest.importorskip("tensorboard")
    copies = tmp_path / "copies"
    for name in ("a", "b"):  # one run in two directories: the same config and seed, one sample
        shutil.copytree(runs / "single_0", copies / name)
    shutil.copytree(runs / "single_1", copies / "c")  # another seed: a sample of its own
    logdir = tmp_path / "tb"
    result = invoke(str(copies), "--to", "tensorboard", "--uri", str(logdir))
    assert result.exit_code == 0, result.output
    assert "2 run(s) to tensorboard: 2 exported, 0 replaced, 0 unchanged, 0 skipped, 1 duplicate" in result.stdout
    assert result.stderr.splitlines() == [
        f"duplicate {copies / 'b'}: the same config and seed as {copies / 'a'}; not exported (one sample)"
    ]
    assert sorted(p.name for p in exported(logdir)) == sorted(
        tensorboard_name((copies / n).resolve()) for n in ("a", "c")
    )


@pytest.mark.slow  # the `runs` fixture: three runs and a killed one, then an export
def test_tensorboard_reexport_replaces_one_subdirectory_per_run(runs, tmp_path):
    pytest.importorskip("tensorboard")
    mine = tmp_path / "runs"
    shutil.copytree(runs / "team", mine / "team")
    logdir = tmp_path / "tb"
    assert invoke(str(mine), "--to", "tensorboard", "--uri", str(logdir)).exit_code == 0
    again = invoke(str(mine), "--to", "tensorboard", "--uri", str(logdir))
    assert "0 exported, 0 replaced, 1 unchanged" in again.stdout
    s = summary(mine / "team")
    s["mean"]["value"] = 1234.5
    (mine / "team" / "summary.json").write_text(json.dumps(s))
    third = invoke(str(mine), "--to", "tensorboard", "--uri", str(logdir))
    assert "0 exported, 1 replaced, 0 unchanged" in third.stdout
    (only,) = exported(logdir)  # no duplicate, no temp directory left
    assert len(list(only.glob("events.out.tfevents.*"))) == 1
    assert [e.value for e in accumulator(only).Scalars("summary/mean")] == [1234.5]


@pytest.mark.slow  # the `runs` fixture: three runs and a killed one, then an export
def test_a_write_failure_is_one_line_exit_1_and_keeps_the_previous_export(runs, tmp_path, monkeypatch):
    pytest.importorskip("tensorboard")
    from riskplan.experiments.exporting import TensorboardTarget

    mine = tmp_path / "runs"
    shutil.copytree(runs / "single_0", mine / "single_0")
    logdir = tmp_path / "tb"
    assert invoke(str(mine), "--to", "tensorboard", "--uri", str(logdir)).exit_code == 0
    before = {p.name: p.read_bytes() for p in logdir.rglob("*") if p.is_file()}
    (mine / "single_0" / "summary.json").write_text(json.dumps({**summary(mine / "single_0"), "wall_time": 9.0}))

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(TensorboardTarget, "_events", staticmethod(full))
    result = invoke(str(mine), "--to", "tensorboard", "--uri", str(logdir))
    assert result.exit_code == 1
    assert result.stderr.splitlines() == [
        f"error: tensorboard {logdir}: could not be written (OSError: [Errno 28] No space left on device)"
    ]
    assert {p.name: p.read_bytes() for p in logdir.rglob("*") if p.is_file()} == before
    assert not [p for p in logdir.iterdir() if p.name.startswith(".") and p.name != LOCK]  # its writers' lock stays


@pytest.mark.slow  # the `runs` fixture: three runs and a killed one, then an export
def test_a_missing_optional_package_is_bad_input_and_writes_nothing(runs, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "mlflow", None)  # as if it were not installed
    monkeypatch.chdir(tmp_path)
    result = invoke(str(runs), "--to", "mlflow")
    assert result.exit_code == 2
    assert result.stderr.splitlines() == [
        "error: --to mlflow: needs the mlflow-skinny package, which is not installed; pip install 'riskplan[mlflow]'"
    ]
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------- Foxglove
def mcap_topics(run: Path) -> set[str]:
    from mcap.reader import make_reader

    with open(run / "run.mcap", "rb") as f:
        return {channel.topic for channel in make_reader(f).get_summary().channels.values()}


@pytest.mark.slow  # the `runs` fixture
def test_export_tells_the_runs_loaded_before_it_exports(runs, tmp_path):
    shutil.copytree(runs, tmp_path / "runs")  # the Foxglove layout goes into each run directory
    heard = []
    result = export_runs([tmp_path / "runs"], "foxglove", progress=lambda *told: heard.append(told))
    done = [d for d, _ in heard]
    assert heard[-1] == (4, 4) and done == sorted(done)  # the killed run is loaded too, then skipped
    assert sorted(Path(e.path).name for e in result.done) == list(GOOD)


@pytest.mark.slow  # the `runs` fixture: three runs and a killed one, then an export
@pytest.mark.parametrize("name, robots", [("single_0", 1), ("team", 3)])
def test_foxglove_layout_references_only_topics_of_the_run(runs, tmp_path, name, robots):
    run = tmp_path / name
    shutil.copytree(runs / name, run)
    written = (run / LAYOUT_FILE).read_text()  # every training run ships its layout
    (run / LAYOUT_FILE).unlink()  # an older run without one gets it from riskplan export --to foxglove
    result = invoke(str(run), "--to", "foxglove")
    assert result.exit_code == 0 and "1 exported" in result.stdout
    assert (run / LAYOUT_FILE).read_text() == written
    data = json.loads((run / LAYOUT_FILE).read_text())
    assert set(panels(data["layout"])) == set(data["configById"])  # every panel placed, none dangling
    assert {p.split("!")[0] for p in data["configById"]} >= {"3D", "Plot", "RawMessages"}
    used = topics(data)
    assert used <= mcap_topics(run)
    assert {"/world/map", "/world/markers", "/paths", "/team/graph", "/metrics", "/summary"} <= used
    plotted = [p["value"] for panel in data["configById"].values() for p in panel.get("paths", [])]
    wanted = (
        ["/metrics{robot==0}.cvar"]
        if robots == 1
        else [
            "/metrics{robot==-1}.cvar",
            "/metrics{robot==0}.cvar",
            "/metrics{robot==1}.cvar",
            "/metrics{robot==2}.cvar",
        ]
    )
    assert [p for p in plotted if p.endswith(".cvar")] == wanted
    assert [p.replace(".mean", ".cvar") for p in plotted if p.endswith(".mean")] == wanted
    grid = next(c for c in data["configById"].values() if c.get("followTf") == "grid")
    assert set(grid["topics"]) == {"/world/map", "/world/markers", "/paths"}
    assert invoke(str(run), "--to", "foxglove").stdout.endswith(
        "0 exported, 0 replaced, 1 unchanged, 0 skipped -> each run directory\n"
    )


@pytest.mark.slow  # the `runs` fixture: three runs and a killed one, then an export
def test_write_layout_is_what_export_writes(runs, tmp_path):
    path = write_layout(tmp_path, robots=3, size=(12, 12))
    assert json.loads(path.read_text()) == layout(3, (12, 12))
    assert json.loads(path.read_text()) == json.loads(json.dumps(layout(3)))  # plain JSON, no NaN


# ------------------------------------------------------------------------------------------- what a run becomes
def test_params_figures_prefixes_and_names_known_answers():
    """The pure parts of an export: config values as text, summary.json's finite numbers by dotted key (an interval
    as key, key_low, key_high), the metric prefix of each robot, and TensorBoard's file-name-safe subdirectory."""
    assert [param_value(v) for v in ("cvar", 0.1, 3, True, None, [1, 2])] == [
        "cvar",
        "0.1",
        "3",
        "true",
        "null",
        "[1, 2]",
    ]
    summary = {
        "schema_version": 1,
        "provenance": {"git_sha": "abc", "numpy": 2},
        "cvar": {"value": -2.5, "low": -3.0, "high": float("nan")},
        "theta_final": [46.5, -0.75],
        "beta": 0.1,
        "headline_robot": -1,
        "complete": True,
        "experiment": "paper_single",
        "wall_time": float("inf"),
    }
    assert summary_figures(summary) == {
        "cvar": -2.5,
        "cvar_low": -3.0,
        "theta_final.0": 46.5,
        "theta_final.1": -0.75,
        "beta": 0.1,
        "headline_robot": -1.0,
    }
    assert summary_figures(None) == {}
    assert [metric_prefix(r, 0) for r in (0, 1, -1)] == ["train", "robot_1", "team"]
    assert [metric_prefix(r, -1) for r in (-1, 0, 2)] == ["train", "robot_0", "robot_2"]
    name = tensorboard_name(Path("/data/runs/a b:c"))
    assert re.fullmatch(r"a_b_c-[0-9a-f]{8}", name)
    assert tensorboard_name(Path("/elsewhere/a b:c")) != name  # the same name in another place: another directory
    assert tensorboard_name(Path("/data/..")).startswith("run-")


def test_every_targets_default_destination_is_under_outputs_or_in_each_run(tmp_path, monkeypatch):
    """Without --uri or --out an export writes under outputs/, which .gitignore leaves out (the trackers' stores),
    or into each run directory (the Foxglove layout, the ROS 2 bags): from a repository's root it adds nothing
    that git would list."""
    from riskplan.experiments.export_destinations import TARGETS, check_uri

    monkeypatch.chdir(tmp_path)
    stores = {
        "mlflow": (tmp_path / "outputs" / "mlruns").as_uri(),
        "tensorboard": str(tmp_path / "outputs/tensorboard"),
    }
    assert {to: check_uri(to, None) for to in TARGETS} == {**stores, "foxglove": "", "ros2": ""}
    ignored = (Path(__file__).resolve().parents[2] / ".gitignore").read_text().splitlines()
    assert "/outputs/*" in ignored


@pytest.mark.slow  # a run, then an export
def test_an_export_into_a_directory_another_export_writes_is_refused_naming_it(tmp_path):
    """Two exports into one TensorBoard log directory failed on each other's temp folders, and into one MLflow file
    store made two experiments of one name: the destination has one writer at a time."""
    run, logdir = tmp_path / "run", tmp_path / "tb"
    train(compose(TINY), run)
    logdir.mkdir()
    with held_by_another_process(logdir) as pid:
        result = invoke(str(run), "--to", "tensorboard", "--uri", str(logdir))
        assert result.exit_code == 2 and result.stderr.strip() == (
            f"error: {logdir}: is in use by another riskplan process (pid {pid}); one process writes a "
            f"tensorboard export destination at a time: wait for it to end or stop it"
        )
        assert exported(logdir) == []
