"""A resume goes on in the world its run started in, and says what it measured: run.mcap records the map's files
(resolved path and SHA-256 of the YAML, its image and each mask) as a run starts, and a resume whose map differs, a
file edited in place or another file found from another working directory, is bad input before anything is
written; a run recorded before that record existed still resumes. A resumed run's throughput counts the episodes of
the iterations it trained, not the run's."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest
from support import TINY, files
from typer.testing import CliRunner

import riskplan.run.run_directory as run_directory
from riskplan import compose
from riskplan.cli import app
from riskplan.config.schema import CONF_DIR
from riskplan.run import training
from riskplan.run.log_reader import read_log
from riskplan.util.errors import BadInput

pytestmark = pytest.mark.slow  # each trains or resumes runs: seconds in all

runner = CliRunner()
FLOOR_PLAN = ["experiment=floor_plan", *TINY]


@pytest.fixture
def started(tmp_path, monkeypatch) -> Path:
    """A floor-plan run started in tmp_path/a, whose maps/ holds a copy of riskplan's floor plan; the test runs in
    tmp_path/a."""
    here = tmp_path / "a"
    shutil.copytree(CONF_DIR / "maps", here / "maps")
    monkeypatch.chdir(here)
    result = runner.invoke(app, ["train", *FLOOR_PLAN, "hydra.run.dir=run"])
    assert result.exit_code == 0, result.output
    return here / "run"


def refused(result) -> str:
    assert result.exit_code == 2, result.output
    (line,) = result.stderr.strip().splitlines()
    return line.removeprefix("error: ")


def test_a_run_records_its_map_files(started):
    (yaml_file, image, mask) = read_log(started / "run.mcap").metadata["map"]["files"]
    maps = started.parent / "maps"
    assert [f["key"] for f in (yaml_file, image, mask)] == ["world.map", "world.map", "world.regions.0.mask"]
    assert [f["path"] for f in (yaml_file, image, mask)] == [
        str((maps / name).resolve()) for name in ("floor_plan.yaml", "floor_plan.pgm", "floor_plan_watched.pgm")
    ]
    assert all(len(f["sha256"]) == 64 for f in (yaml_file, image, mask))


def test_a_map_edited_in_place_is_not_resumed(started):
    mask = started.parent / "maps" / "floor_plan_watched.pgm"
    mask.write_bytes(mask.read_bytes()[:-1] + b"\x00")  # one pixel of the watched corridor
    before = files(started)
    line = refused(runner.invoke(app, ["train", "--resume", "run", "train.iterations=5"]))
    assert line == (
        f"world.regions.0.mask: {mask.resolve()} has changed since the run started (not the content run.mcap "
        f"recorded); restore it, or train a new run"
    )
    assert files(started) == before
    (started / "checkpoint").unlink()  # nothing to go on from: a restart trains the logged iterations again, on it
    assert "has changed since the run started" in refused(runner.invoke(app, ["train", "--resume", "run"]))


def test_another_map_found_from_another_directory_is_not_resumed(started, monkeypatch):
    """From elsewhere, maps/floor_plan.yaml is riskplan's own: the same file's copy resumes, an edited copy not."""
    ours = started.parent / "maps" / "floor_plan.yaml"
    elsewhere = started.parent.parent / "b"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert runner.invoke(app, ["train", "--resume", str(started)]).stdout.startswith("already finished")
    ours.write_text(ours.read_text() + "# edited after the run\n")
    monkeypatch.chdir(started.parent)
    before = files(started)
    line = refused(runner.invoke(app, ["train", "--resume", "run", "train.iterations=5"]))
    assert line.startswith(f"world.map: {ours.resolve()} has changed since the run started")
    shutil.copy(CONF_DIR / "maps" / "floor_plan.yaml", ours)  # restored: the content is the run's again
    (elsewhere / "maps").mkdir()
    shutil.copy(ours, elsewhere / "maps" / "floor_plan.yaml")
    (elsewhere / "maps" / "floor_plan.yaml").write_text(ours.read_text().replace("negate: 0", "negate: 0\n# mine"))
    for name in ("floor_plan.pgm", "floor_plan_watched.pgm"):
        shutil.copy(ours.parent / name, elsewhere / "maps" / name)
    monkeypatch.chdir(elsewhere)
    line = refused(runner.invoke(app, ["train", "--resume", str(started), "train.iterations=5"]))
    assert line == (
        f"world.map: {(elsewhere / 'maps' / 'floor_plan.yaml').resolve()} is not the file the run started with "
        f"({ours.resolve()}), and its content differs; resume from the directory the run was started in, or train a "
        f"new run"
    )
    assert files(started) == before
    with pytest.raises(BadInput, match="is not the file the run started with"):  # the Python API's resume too
        training.train(compose([*FLOOR_PLAN, "train.iterations=5"]), started, resume=True)
    assert files(started) == before


def test_a_run_recorded_before_maps_were_identified_still_resumes(tmp_path, monkeypatch):
    shutil.copytree(CONF_DIR / "maps", tmp_path / "maps")
    monkeypatch.chdir(tmp_path)
    with monkeypatch.context() as old:
        old.setattr(run_directory, "map_record", lambda world: None)
        training.train(compose(FLOOR_PLAN), tmp_path / "run")
    assert "map" not in read_log(tmp_path / "run" / "run.mcap").metadata
    result = runner.invoke(app, ["train", "--resume", "run", "train.iterations=5"])
    assert result.exit_code == 0, result.output


def test_a_resumed_runs_throughput_counts_the_episodes_it_trained(tmp_path):
    out = tmp_path / "run"
    training.train(compose(TINY), out)
    training.train(compose([*TINY, "train.iterations=5"]), out, resume=True)
    summary = json.loads((out / "summary.json").read_text())
    metrics = pd.read_parquet(out / "metrics.parquet")
    trained = metrics.samples[metrics.iteration >= 3].sum()  # iterations 3 and 4, in this process
    assert summary["resumed_at"] == 3
    assert summary["throughput_episodes_per_s"] == pytest.approx(trained / summary["wall_time"], rel=1e-12)
    (out / "summary.json").unlink()  # checkpointed at its end, its files not written: it trains nothing more
    training.train(compose([*TINY, "train.iterations=5"]), out, resume=True)
    assert json.loads((out / "summary.json").read_text())["throughput_episodes_per_s"] is None
