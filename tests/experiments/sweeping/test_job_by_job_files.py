"""Job by job, Hydra's run_job writes no .hydra/ (sweep_worker.OWN_FILES): each job writes it under its folder's
lock, once the folder is its own. The files are byte for byte those Hydra's run_job writes, which resuming,
reporting, exporting and sweeping again read. A finished job whose .hydra/ a power cut left empty (the files are
renamed into place unsynced) gets them back from the sweep's re-run, batched or job by job, its run untouched."""

from __future__ import annotations

from pathlib import Path

import pytest
from support import TINY, files, held_by_another_process

from riskplan.experiments.sweep_worker import OWN_FILES
from riskplan.experiments.sweeping import execute
from riskplan.experiments.sweeping.execute import run_sweep


def hydra_folders(root: Path) -> dict[str, str]:
    """Every job's .hydra/ file below root, its text with root's path as SWEEP."""
    return {name: text.decode().replace(str(root), "SWEEP") for name, text in files(root).items() if "/.hydra/" in name}


@pytest.mark.slow  # two small sweeps
@pytest.mark.parametrize(
    "args, jobs",
    [
        (["seed=0,1"], 1),  # joblib's worker
        (["risk.beta=0.1,0.2", "hydra/launcher=basic", "hydra.output_subdir=.hydra"], None),  # in this process
    ],
    ids=["joblib", "basic, output_subdir given"],
)
def test_a_job_by_job_sweep_s_files_are_those_hydra_s_run_job_writes(tmp_path, monkeypatch, args, jobs):
    mine = tmp_path / "mine"
    run_sweep([*args, *TINY], jobs, sweep_dir=mine, out=lambda text: None)
    launch = execute.launch
    monkeypatch.setattr(execute, "launch", lambda argv, log, waiting, each: launch(argv, log, waiting))  # Hydra's
    hydra = tmp_path / "hydra"
    run_sweep([*args, *TINY], jobs, sweep_dir=hydra, out=lambda text: None)
    written = hydra_folders(mine)
    assert len(written) == 6 and written == hydra_folders(hydra)
    assert OWN_FILES not in "".join(written.values())
    launched = [(root / "multirun.yaml").read_text().replace(str(root), "SWEEP") for root in (mine, hydra)]
    assert launched[0] == launched[1]  # the key is each job's, not the launch's


@pytest.mark.slow  # a small sweep
def test_a_job_whose_folder_another_process_holds_leaves_its_files(tmp_path):
    """A task of an earlier launch holds seed=0's folder: the job gives up at once, and Hydra wrote nothing there."""
    run_sweep(["seed=1", *TINY], 1, sweep_dir=tmp_path / "s", out=lambda text: None)
    out = tmp_path / "s" / "seed=0"
    out.mkdir()
    (out / "job.log").write_text("=== riskplan sweep job started\n")
    with held_by_another_process(out):
        before = files(out)
        run_sweep(["seed=0,1", *TINY], 1, sweep_dir=tmp_path / "s", out=lambda text: None)
        assert files(out) == before  # no .hydra/ (Hydra wrote one there before riskplan's job ran)


@pytest.mark.slow  # two small sweeps
@pytest.mark.parametrize("jobs", [None, 1], ids=["batched", "job by job"])
def test_a_re_run_writes_again_the_hydra_files_a_finished_job_lost(tmp_path, jobs):
    sweep = tmp_path / "s"
    run_sweep(["seed=0,1", *TINY], jobs, sweep_dir=sweep, out=lambda text: None)
    before = files(sweep / "seed=0")
    (sweep / "seed=0" / ".hydra" / "config.yaml").write_text("")  # as a power cut can leave it
    (sweep / "seed=0" / ".hydra" / "overrides.yaml").write_text("- seed=0\n- 'train.it")  # cut short
    lines = []
    outcome = run_sweep(["seed=0,1", *TINY], jobs, sweep_dir=sweep, out=lines.append)
    assert any("2 jobs: 1 to run, 1 already finished" in line for line in lines) and outcome.failed == []
    assert files(sweep / "seed=0") == before  # written again as they were; the run's own files untouched
