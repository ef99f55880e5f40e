"""`riskplan export` onto a disk that fills up part-way (a real tmpfs): one line and exit code 1, whichever run it
fills on. TensorBoard's event files are written in the export's own thread (TensorBoard's writer thread printed
`Exception in thread ...` and a traceback beside the line); an MLflow file store keeps no part of a run the disk cut
short (it was left marked FAILED, or with an empty meta.yaml that broke the store for every later export), and after
space is freed the same export finishes. The mounts need root; without it the tests are skipped, saying why."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest
from support import TINY, mounted, run_cli
from typer.testing import CliRunner

from riskplan import compose, train
from riskplan.cli import app
from riskplan.util.paths import MARKER

pytestmark = pytest.mark.slow  # three runs, then exports on a mounted tmpfs

runner = CliRunner()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("export_full") / "runs"
    for seed in range(3):
        train(compose([*TINY, f"seed={seed}"]), root / f"seed={seed}", progress=False)
    return root


def tmpfs(target: Path, size: str):
    return mounted(target, "-t", "tmpfs", "-o", f"size={size}", "tmpfs")


def free(disk: Path) -> int:
    stats = os.statvfs(disk)
    return stats.f_bavail * stats.f_frsize


def leave_free(disk: Path, left: int) -> Path:
    """A file `fill` that leaves `left` bytes of the disk free (to its pages)."""
    (disk / "fill").write_bytes(b"\0" * max(0, free(disk) - left))
    return disk / "fill"


def export(runs: Path, *args: str):
    result = runner.invoke(app, ["export", str(runs), *args])
    assert "Traceback" not in result.output and "Exception in thread" not in result.output, result.output
    return result


@pytest.mark.parametrize("pages", range(1, 8))  # each run takes 3 pages: the disk fills in each of its writes
def test_tensorboard_on_a_disk_that_fills_is_one_line_and_leaves_whole_runs(runs, tmp_path, pages):
    with tmpfs(tmp_path / "disk", "300k") as disk:
        leave_free(disk, pages * 4096)
        logdir = disk / "tb"
        # in a process of its own: pytest would catch what a thread of TensorBoard's printed
        result = run_cli(["export", str(runs), "--to", "tensorboard", "--uri", str(logdir)], tmp_path)
        assert result.returncode == 1, result.stdout + result.stderr
        assert result.stderr.splitlines() == [
            f"error: tensorboard {logdir}: could not be written (OSError: [Errno 28] No space left on device)"
        ]
        left = [p for p in logdir.iterdir() if p.name != ".riskplan.lock"]
        assert all((p / MARKER).is_file() for p in left), left  # whole runs only: no temp folder


def test_mlflow_on_a_disk_that_fills_keeps_no_part_of_a_run_and_finishes_once_freed(runs, tmp_path, monkeypatch):
    pytest.importorskip("mlflow")
    from mlflow.tracking import MlflowClient

    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    with tmpfs(tmp_path / "disk", "4m") as disk:
        store, measured = disk / "mlruns", disk / "measured"
        before = free(disk)
        assert export(runs / "seed=0", "--to", "mlflow", "--uri", str(measured)).exit_code == 0
        one_run = before - free(disk)
        subprocess.run(["rm", "-rf", str(measured)], check=True)
        fill = leave_free(disk, one_run * 3 // 2)  # room for the first run, not the second
        result = export(runs, "--to", "mlflow", "--uri", str(store))
        assert result.exit_code == 1, result.output
        (line,) = result.stderr.splitlines()
        assert re.fullmatch(
            rf"error: mlflow file://{store}: could not be written \((OSError|MlflowException): \[Errno 28\] No space "
            r"left on device\); what it had begun in the store was removed",
            line,
        ), line
        client = MlflowClient(tracking_uri=f"file://{store}")
        (experiment,) = client.search_experiments()
        kept = client.search_runs([experiment.experiment_id])
        assert len(kept) == result.stdout.count("\nexported ") + result.stdout.startswith("exported ") == 1
        assert {run.info.status for run in kept} == {"FINISHED"}
        assert sorted(p.name for p in (store / experiment.experiment_id).iterdir()) == sorted(
            ["meta.yaml", *(run.info.run_id for run in kept)]
        )

        fill.unlink()
        again = export(runs, "--to", "mlflow", "--uri", str(store))
        assert again.exit_code == 0, again.output
        assert "2 exported, 0 replaced, 1 unchanged, 0 skipped" in again.stdout
        assert {run.info.status for run in client.search_runs([experiment.experiment_id])} == {"FINISHED"}
