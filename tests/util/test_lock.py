"""One writer per run directory (riskplan.util.lock): the lock is reentrant within a process and exclusive between
processes. Whole runs and sweeps that meet a held lock are in tests/run/test_run_safety.py and
tests/experiments/sweeping/test_sweep_safety.py."""

from __future__ import annotations

import os
import subprocess

from riskplan.util.lock import hold_lock, holder


def test_the_lock_is_reentrant_within_a_process_and_exclusive_between_processes(tmp_path):
    with hold_lock(tmp_path):
        with hold_lock(tmp_path):  # the CLI holds it while Hydra runs the training loop, which takes it again
            assert holder(tmp_path) == os.getpid()
        probe = subprocess.run(
            [
                "python",
                "-c",
                "import sys; from riskplan.util.lock import hold_lock\n"
                "from riskplan.util.errors import BadInput\n"
                f"try:\n    with hold_lock({str(tmp_path)!r}): sys.exit(0)\n"
                "except BadInput as err:\n    print(err); sys.exit(3)",
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert probe.returncode == 3 and f"(pid {os.getpid()})" in probe.stdout
    assert holder(tmp_path) is None
