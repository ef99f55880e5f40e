"""Output directories of report and landscape (riskplan.experiments.output_manifest) when two writers race into one
new --out: the one that loses the lock leaves the winner's lock and directory alone. Whole reports are in
tests/experiments/test_output_safety.py."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import pytest
from support import held_by_another_process

from riskplan.experiments.output_manifest import Output, WriteFailed, claim_output
from riskplan.util import lock
from riskplan.util.errors import BadInput


def test_a_writer_that_made_the_directory_but_lost_its_lock_leaves_the_winners_lock(tmp_path, monkeypatch):
    out = tmp_path / "new"
    output = Output(out, "report", claim_output(out, "report", "--out"))
    made = Output._make
    others = contextlib.ExitStack()
    winner = []

    def made_then_taken(self):  # another report takes the lock between this one's mkdir and its lock
        made(self)
        winner.append(others.enter_context(held_by_another_process(out)))

    monkeypatch.setattr(Output, "_make", made_then_taken)
    with others:
        with pytest.raises(BadInput, match="in use by another riskplan process") as refused:
            with output.writing(["report.html"]):
                output.write("report.html", "<html/>")
        assert f"(pid {winner[0]})" in str(refused.value)
        assert (out / lock.LOCK).exists() and lock.holder(out) == winner[0]


def test_a_writer_whose_directory_another_made_meanwhile_takes_the_lock_not_a_write_failure(tmp_path, monkeypatch):
    out = tmp_path / "new"
    output = Output(out, "report", claim_output(out, "report", "--out"))
    mkdir = Path.mkdir

    def made_by_another_first(self, *args, **kwargs):
        if self == out:
            os.mkdir(out)
        return mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", made_by_another_first)
    with output.writing(["report.html"]):
        output.write("report.html", "<html/>")
    assert (out / "report.html").read_text() == "<html/>" and not output.created


@pytest.mark.parametrize("fails", [RuntimeError, KeyboardInterrupt])
def test_a_new_directory_a_failed_writer_made_goes_again_with_its_lock(tmp_path, fails):
    out = tmp_path / "new"
    output = Output(out, "report", claim_output(out, "report", "--out"))
    with pytest.raises(fails):
        with output.writing(["report.html"]):
            output.write("report.html", "<html/>")
            raise fails()
    assert not out.exists()


def test_a_failed_landscape_into_a_new_directory_removes_it_once_its_lock_is_let_go(tmp_path):
    out = tmp_path / "new"
    output = Output(out, "landscape", claim_output(out, "landscape", "--out"))
    with pytest.raises(WriteFailed):
        with output.locked():  # a landscape holds it for its computation, then writes the set inside
            with output.writing(["status.json"]):
                raise OSError(28, "No space left on device")
    assert not out.exists()
