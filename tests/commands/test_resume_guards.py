"""`riskplan train --resume` (and `hydra.run.dir=`) on what is not a run of its own to go on with: a landscape's or a
report's output, a sweep's job folder, a config whose key follows train.iterations; the overrides it reads as a fresh
train does (040 is 40; ++, +, ~ and Hydra's flags said plainly); what an extension and a restart leave behind
(.hydra/overrides.yaml, what a killed write left, the logged iterations a restart trains again); a run directory
name too long for the filesystem. Each run here is TINY, in this process (typer's CliRunner)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from support import TINY, files
from typer.testing import CliRunner

from riskplan import compose, load_run
from riskplan.cli import app
from riskplan.experiments.landscape import compute_landscape
from riskplan.util.errors import BadInput

pytestmark = pytest.mark.slow  # each trains or resumes runs: seconds in all

runner = CliRunner()


def train(out: Path, *overrides: str) -> Path:
    result = runner.invoke(app, ["train", *TINY, *overrides, f"hydra.run.dir={out}"])
    assert result.exit_code == 0, result.output
    return out


def resume(out: Path, *overrides: str):
    return runner.invoke(app, ["train", "--resume", str(out), *overrides])


def refused(result) -> str:
    """The one line a bad input gets, after `error: `, checked to be the only one, with exit code 2."""
    assert result.exit_code == 2, result.output
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("error: ")
    return line.removeprefix("error: ")


def summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


# ------------------------------------------------------------------------------ not a run of riskplan train
@pytest.fixture
def landscape(tmp_path) -> Path:
    out = tmp_path / "land"
    compute_landscape(compose(TINY), out, points=3, episodes=20)
    assert (out / ".hydra" / "config.yaml").is_file()  # what alone would pass for a run's
    return out


def test_a_landscape_is_not_resumed_nor_trained_into_nor_loaded(landscape):
    before = files(landscape)
    assert refused(resume(landscape)) == (
        f"{landscape}: holds the output of riskplan landscape, not a run; give the directory of a riskplan train "
        f"run to --resume"
    )
    line = refused(runner.invoke(app, ["train", *TINY, f"hydra.run.dir={landscape}"]))
    assert line == (
        f"hydra.run.dir: {landscape} holds the output of riskplan landscape, not a run; give a new or empty directory"
    )
    with pytest.raises(BadInput, match="holds the output of riskplan landscape, not a run"):
        load_run(landscape)
    assert files(landscape) == before


def test_a_report_is_not_resumed_nor_trained_into(tmp_path):
    report = tmp_path / "report"  # what riskplan report leaves: its manifest and its files
    report.mkdir()
    (report / "report.html").write_text("<html></html>")
    manifest = {"kind": "report", "written_by": "riskplan report", "files": ["report.html"]}
    (report / ".riskplan-manifest.json").write_text(json.dumps(manifest))
    before = files(report)
    assert "holds the output of riskplan report, not a run" in refused(resume(report))
    assert "holds the output of riskplan report, not a run" in refused(
        runner.invoke(app, ["train", *TINY, f"hydra.run.dir={report}"])
    )
    assert files(report) == before


def test_a_sweep_job_is_left_to_its_sweep(tmp_path):
    job = train(tmp_path / "sweep" / "seed_0")
    status = {"status": "done", "error": None, "config_sha": "f4799add8cfecfca", "cvar": 1.0}
    (job / "status.json").write_text(json.dumps(status))  # as a sweep's job writes it
    before = files(job)
    assert refused(resume(job, "train.iterations=5")) == (
        f"{job}: is a job of the sweep in {job.parent}, which resumes its own jobs: run riskplan sweep again with "
        f"that sweep's overrides and hydra.sweep.dir={job.parent} (it skips the finished jobs and resumes the others)"
    )
    assert files(job) == before


def test_a_run_whose_config_is_empty_never_started_and_says_so(tmp_path):
    """What Hydra leaves when the disk is full as a run begins (it writes .hydra/ in place): an empty config, which
    read as {} gave `world.sources: no sources; ...`."""
    out = tmp_path / "never"
    (out / ".hydra").mkdir(parents=True)
    (out / ".hydra" / "config.yaml").write_text("")
    (out / "app.log").write_text("")
    before = files(out)
    assert refused(resume(out)) == (
        f"{out / '.hydra' / 'config.yaml'}: is empty: the run never started; remove the directory and train again"
    )
    assert files(out) == before


# ------------------------------------------------------------------------------ the overrides of a resume
def test_iterations_are_read_as_a_fresh_train_reads_them(tmp_path):
    """010 is 10, as Hydra reads it for `riskplan train train.iterations=010`, not YAML 1.1's octal 8."""
    out = train(tmp_path / "run")
    assert resume(out, "train.iterations=010").exit_code == 0
    assert summary(out)["iterations"] == 10
    fresh = train(tmp_path / "fresh", "train.iterations=010")
    assert summary(fresh)["iterations"] == 10


def test_plus_plus_sets_the_iterations_and_the_other_prefixes_are_said_plainly(tmp_path):
    out = train(tmp_path / "run")
    before = files(out)
    assert refused(resume(out, "+train.iterations=5")) == (
        "override '+train.iterations=5': + adds a key, and train.iterations is in every run's config: give "
        "train.iterations=N"
    )
    assert refused(resume(out, "~train.iterations")) == (
        "override '~train.iterations': cannot delete a key of a resumed run; only train.iterations=N may be given"
    )
    assert refused(resume(out, "--cfg", "job")) == (
        f"option '--cfg': riskplan train --resume passes no Hydra flag through; the run's config is "
        f"{out / '.hydra/config.yaml'}"
    )
    assert files(out) == before
    assert resume(out, "++train.iterations=5").exit_code == 0
    assert summary(out)["iterations"] == 5


def test_an_extended_run_records_its_iterations_in_its_overrides(tmp_path):
    out = train(tmp_path / "run", "train.iterations=4")  # TINY's 3, then 4: both in overrides.yaml
    hydra_before = yaml.safe_load((out / ".hydra" / "hydra.yaml").read_text())
    assert resume(out, "train.iterations=6").exit_code == 0
    overrides = yaml.safe_load((out / ".hydra" / "overrides.yaml").read_text())
    assert [o for o in overrides if "train.iterations" in o] == ["train.iterations=6"]
    assert overrides[: len(TINY) - 1] == [o for o in TINY if not o.startswith("train.iterations")]
    hydra_after = yaml.safe_load((out / ".hydra" / "hydra.yaml").read_text())
    assert hydra_after["hydra"]["overrides"]["task"] == overrides  # Hydra's own copy of the list says the same
    hydra_after["hydra"]["overrides"]["task"] = hydra_before["hydra"]["overrides"]["task"]
    assert hydra_after == hydra_before  # and nothing else of it changed


def test_a_key_that_follows_the_iterations_keeps_the_run_from_being_extended(tmp_path):
    """Extended, the schedule would stretch over the iterations trained already: a run of neither config."""
    out = train(tmp_path / "run", "risk.schedule=linear", "risk.schedule.iterations=${train.iterations}")
    before = files(out)
    assert refused(resume(out, "train.iterations=5")) == (
        f"risk.schedule.iterations: follows train.iterations in {out / '.hydra/config.yaml'}, so extending the run "
        f"would change it for the iterations trained already; this run cannot be extended: train a new run with "
        f"train.iterations=5"
    )
    assert files(out) == before
    assert resume(out).stdout.startswith(f"already finished: {out}")  # as it is, it resumes


# ------------------------------------------------------------------------------ what a resume leaves
def test_a_restart_says_what_becomes_of_the_logged_iterations_and_clears_a_killed_write(tmp_path):
    out = train(tmp_path / "run")
    reference = summary(out)
    (out / "checkpoint").unlink()  # removed by hand: nothing to go on from
    (out / ".eval.parquet.4242.tmp").write_bytes(b"half a table")  # what a SIGKILL mid-write leaves
    result = resume(out)
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith(
        f"restarting (no checkpoint yet): {out}; the 3 iterations its run.mcap holds are trained again from the "
        f"start, to the same numbers\n"
    )
    assert not list(out.glob(".*.tmp"))
    assert summary(out)["cvar"] == reference["cvar"]


def test_a_resume_clears_what_a_killed_write_left(tmp_path):
    out = train(tmp_path / "run")
    (out / "summary.json").unlink()  # killed as it wrote its tables: checkpointed at its end, not finished
    (out / ".eval.parquet.4242.tmp").write_bytes(b"half a table")
    result = resume(out)
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith(f"resuming: {out}")
    assert not list(out.glob(".*.tmp")) and (out / "summary.json").is_file()


@pytest.mark.parametrize("where", ["{long}", "x/{long}/y"])
def test_a_run_directory_name_too_long_is_bad_input_and_nothing_is_made(in_tmp, where):
    out = where.format(long="a" * 300)
    line = refused(runner.invoke(app, ["train", *TINY, f"hydra.run.dir={out}"]))
    assert line == (
        f"hydra.run.dir: names a folder of 300 bytes ({'a' * 24}...); this filesystem takes names of at most 255 "
        f"bytes: give a shorter one"
    )
    assert list(in_tmp.iterdir()) == []
