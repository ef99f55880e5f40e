"""hydra/launcher=ray_cluster where its `address: auto` finds no Ray head to reach is bad input at plan time:
`riskplan sweep` exits 2 with one line naming the key, writes no sweep directory and never imports Ray
(launcher_settings.check_ray). Before, it printed a table of jobs "not run", then ray.init's ConnectionError, exit 1,
with multirun.yaml, summary.parquet and sweep.log written.

Needs Hydra's Ray launcher (the main suite skips this file; bash tests/ray_check.sh runs it, before the tests that
start a Ray cluster). Ray's temp dir (RAY_TMPDIR) is an empty folder of the test's, so no `ray start` recorded
elsewhere is found; a raylet running on the machine (another test's Ray) would be, and skips the first test (the
second holds whatever runs: Ray prefers the recorded address to a raylet it finds)."""

from __future__ import annotations

import os
import socket
import subprocess

import pytest

pytest.importorskip(
    "hydra_plugins.hydra_ray_launcher",
    reason="the Ray launcher is not installed here; bash tests/ray_check.sh runs this test in its own venv",
)

from riskplan.experiments.sweeping.launcher_settings import raylet_addresses

from .common import riskplan_exe, with_venv_on_path

pytestmark = pytest.mark.slow

COMMAND = ["sweep", "seed=0,1", "hydra/launcher=ray_cluster", "train.iterations=2", "hydra.sweep.dir=s"]


def sweep(tmp_path, ray_tmpdir) -> subprocess.CompletedProcess:
    """COMMAND in a user's shell without RAY_ADDRESS, with Ray's temp dir at `ray_tmpdir`."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("RAY_")}
    env.update(RAY_TMPDIR=str(ray_tmpdir), RAY_USAGE_STATS_ENABLED="0")
    return subprocess.run(
        [riskplan_exe(), *COMMAND],
        env=with_venv_on_path(env),
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )


def refused_line(tmp_path, done: subprocess.CompletedProcess) -> str:
    """The sweep's one line on stderr, after checking that it exited 2 and wrote nothing."""
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr, done.stderr
    assert not (tmp_path / "s").exists()
    return done.stderr.strip()


def test_auto_with_no_ray_instance_on_the_machine_is_bad_input(tmp_path):
    empty = tmp_path / "raytmp"
    empty.mkdir()
    if raylet_addresses():
        pytest.skip(f"a Ray instance runs on this machine ({raylet_addresses()}): auto would find it")
    done = sweep(tmp_path, empty)
    if done.returncode != 2 and raylet_addresses():  # another test's Ray started meanwhile (pytest -n)
        pytest.skip(f"a Ray instance started on this machine during the test ({raylet_addresses()})")
    assert refused_line(tmp_path, done) == (
        f"error: hydra.launcher.ray.init.address: auto found no running Ray instance on this machine (no {empty}/ray/"
        f"ray_current_cluster, no raylet process); start one (ray start --head) or give HOST:PORT of a cluster's "
        f"head (or RAY_ADDRESS)"
    )


def test_auto_with_a_stale_ray_start_record_is_bad_input(tmp_path):
    """`ray start`'s record outlived its head (a crash, not `ray stop`): Ray takes it before any raylet running."""
    with socket.socket() as probe:  # a port where nothing listens
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    (tmp_path / "raytmp" / "ray").mkdir(parents=True)
    (tmp_path / "raytmp" / "ray" / "ray_current_cluster").write_text(f"127.0.0.1:{port}\n")
    line = refused_line(tmp_path, sweep(tmp_path, tmp_path / "raytmp"))
    assert line.startswith(
        f"error: hydra.launcher.ray.init.address: no Ray cluster answers at 127.0.0.1:{port} (Connection refused; "
        f"auto read it from {tmp_path}/raytmp/ray/ray_current_cluster); "
    ), line
