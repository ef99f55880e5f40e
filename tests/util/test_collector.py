"""riskplan.util.collector: the garbage collector is tuned only in a `riskplan` command-line process, is paused
for a train command's start-up and back for its loop (also when the command fails), and skips its last
collections at exit."""

from __future__ import annotations

import gc
import subprocess
import sys

import pytest
from support import TINY
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.util import collector

LOUD_CYCLE = """
import riskplan.util.collector as collector
if {command_line}:
    collector.command_line_process()
class Loud:
    def __del__(self):
        print("collected", flush=True)
cycle = Loud(); cycle.me = cycle; del cycle  # garbage only the cyclic collector can find
print("end", flush=True)
"""


@pytest.fixture
def command_line(monkeypatch):
    """This test process as if `main` had started it (without its exit hook), the collector restored after."""
    monkeypatch.setattr(collector, "_command_line", True)
    frozen = gc.get_freeze_count()
    yield
    collector.resume_collection()
    gc.enable()
    if gc.get_freeze_count() > frozen:
        gc.unfreeze()  # the test's objects back within the collector's reach


def test_outside_a_command_line_process_nothing_changes():
    frozen = gc.get_freeze_count()
    collector.pause_collection()
    assert gc.isenabled()
    collector.resume_collection()
    assert gc.isenabled() and gc.get_freeze_count() == frozen


def test_pause_then_resume_freezes_the_start_up_and_collects_again(command_line):
    collector.pause_collection()
    assert not gc.isenabled()
    kept = [[] for _ in range(1000)]  # containers: objects the collector tracks
    frozen = gc.get_freeze_count()
    collector.resume_collection()
    assert gc.isenabled() and gc.get_freeze_count() >= frozen + len(kept)
    collector.resume_collection()  # a second resume changes nothing
    assert gc.isenabled()


def test_a_user_who_disabled_the_collector_keeps_it_disabled(command_line):
    gc.disable()
    collector.pause_collection()
    collector.resume_collection()
    assert not gc.isenabled()


@pytest.mark.parametrize("command_line_process", [False, True])
def test_the_exit_of_a_command_line_process_skips_the_last_collections(command_line_process):
    done = subprocess.run(
        [sys.executable, "-c", LOUD_CYCLE.format(command_line=command_line_process)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.split()
    assert lines == (["end"] if command_line_process else ["end", "collected"])


def test_train_resumes_the_collector_it_paused_for_its_start_up(command_line, tmp_path):
    frozen = gc.get_freeze_count()
    result = CliRunner().invoke(app, ["train", *TINY, f"hydra.run.dir={tmp_path / 'run'}"])
    assert result.exit_code == 0, result.output
    assert gc.isenabled() and gc.get_freeze_count() > frozen  # resumed at the loop, the start-up frozen


def test_train_that_fails_on_bad_input_resumes_the_collector(command_line, tmp_path):
    result = CliRunner().invoke(app, ["train", "risk.beta=2", f"hydra.run.dir={tmp_path / 'run'}"])
    assert result.exit_code == 2, result.output
    assert "risk.beta" in result.output
    assert gc.isenabled()
