"""The manifest of a run's files (riskplan.run.run_files): what a run leaves on disk is exactly its outputs, and a
sweep job's fresh start removes every file a run writes, temp files included, but those meant to survive."""

from __future__ import annotations

import fnmatch
import os
from pathlib import Path

import pytest
from support import TINY, stand_in_job

from riskplan.experiments.sweep_worker import is_finished
from riskplan.run import run_files
from riskplan.run.compose import compose
from riskplan.run.training import train_summary
from riskplan.util.lock import LOCK
from riskplan.util.paths import temp_name


def on_disk(out: Path) -> set[str]:
    """Every file below `out`, as its path there."""
    return {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()}


@pytest.mark.parametrize("overrides", [[], ["experiment=paper_team", "team.delay.max=1"]], ids=["single", "team"])
def test_a_runs_files_on_disk_are_the_manifests_outputs(tmp_path, overrides):
    out = tmp_path / "run"
    train_summary(compose([*TINY, *overrides]), out)
    assert on_disk(out) == set(run_files.OUTPUTS)
    assert run_files.has_finished(out) and run_files.is_run_dir(out)
    assert set(run_files.FINISHED) <= set(run_files.OUTPUTS)
    assert {run_files.table_file(t) for t in run_files.TABLES} <= set(run_files.FINISHED)


def test_the_stale_files_are_every_file_a_run_writes_but_those_meant_to_survive(tmp_path, monkeypatch):
    """Every file a run writes, with its temp files (seen as they are renamed over it), is in the manifest; those a
    fresh start does not remove are only the config, the lock and the job's own status.json and job.log."""
    out = tmp_path / "run"
    written: set[str] = set()
    replace = os.replace

    def recording(src, dst, *args, **kwargs):
        for path in (Path(src), Path(dst)):
            if path.resolve().is_relative_to(out.resolve()):
                written.add(str(path.resolve().relative_to(out.resolve())))
        return replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", recording)
    train_summary(compose([*TINY, "train.checkpoint_every=1"]), out)
    train_summary(compose([*TINY, "train.checkpoint_every=1", "train.iterations=4"]), out, resume=True)  # run.mcap cut
    written |= on_disk(out)
    names = {f.name for f in run_files.FILES}
    survivors = {f.name for f in run_files.FILES if not f.stale}
    assert survivors == {run_files.CONFIG, LOCK, run_files.STATUS, run_files.JOB_LOG}

    def of(name: str) -> str:
        """The manifest's file a written file is (itself, or the temp file an atomic write goes through)."""
        for listed in names:
            folder, base = os.path.split(listed)
            if name == listed or fnmatch.fnmatchcase(name, os.path.join(folder, temp_name(base, "*"))):
                return listed
        raise AssertionError(f"{name}: a run writes it, and the manifest does not list it")

    assert {of(name) for name in written} - survivors <= set(run_files.STALE)
    assert run_files.CHECKPOINT_TMP in written and run_files.RUN_LOG + run_files.RESUMING in written

    left = out / temp_name(run_files.SUMMARY, 12345)  # what a killed atomic write leaves
    left.write_text("{}")
    (out / run_files.STATUS).write_text("{}")
    run_files.remove_stale(out)
    assert on_disk(out) == survivors - {run_files.JOB_LOG}


def test_a_sweep_skips_a_job_only_with_every_finished_file(tmp_path):
    out = tmp_path / "job"
    stand_in_job(out, {"status": "done", "config_sha": "abc", "error": None})
    assert is_finished(out, "abc") and not is_finished(out, "abd")
    for name in [*run_files.FINISHED, ".hydra/config.yaml", ".hydra/hydra.yaml", ".hydra/overrides.yaml"]:
        (out / name).rename(out / "aside")
        assert not is_finished(out, "abc"), name
        (out / "aside").rename(out / name)


@pytest.mark.parametrize(
    ("name", "text"),
    [
        (".hydra/config.yaml", ""),  # a power cut: renamed into place, its data never written
        (".hydra/config.yaml", "seed: 0\ntrain: {iterations: 3"),  # cut short
        (".hydra/config.yaml", "- seed=0\n"),  # not a mapping
        (".hydra/overrides.yaml", "seed: 0\n"),  # not a list
        (".hydra/overrides.yaml", "- 'seed=0"),
        (".hydra/hydra.yaml", ""),
    ],
)
def test_a_job_whose_hydra_files_do_not_read_as_hydra_writes_them_is_not_finished(tmp_path, name, text):
    """The sweep's next run then writes them again (test_job_by_job_files). A verdict given before the damage (the
    plan's, kept for the job's and the summary's questions) does not outlive it."""
    stand_in_job(tmp_path, {"status": "done", "config_sha": "abc", "error": None})
    assert is_finished(tmp_path, "abc")
    whole = (tmp_path / name).read_bytes()
    (tmp_path / name).write_text(text)
    assert not is_finished(tmp_path, "abc")
    (tmp_path / name).write_bytes(whole)  # written again, as the re-run does
    assert is_finished(tmp_path, "abc")


def test_a_jobs_unchanged_hydra_files_are_parsed_once(tmp_path, monkeypatch):
    stand_in_job(tmp_path, {"status": "done", "config_sha": "abc", "error": None})
    parsed = []
    monkeypatch.setattr(run_files, "_read_intact", lambda *files: parsed.append(files) or True)
    assert is_finished(tmp_path, "abc") and is_finished(tmp_path, "abc") and is_finished(tmp_path, "abc")
    assert len(parsed) == 1
