"""Output directories (riskplan.util.paths): directories claimed in the same second never collide; a failed atomic
write names its file. Read-only and full disks are in tests/run/test_run_safety.py and
tests/experiments/test_output_safety.py."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from riskplan.experiments.hydra_app import write_failure
from riskplan.run.run_files import FILES
from riskplan.util.errors import BadInput
from riskplan.util.paths import (
    INSIDE,
    atomic_path,
    check_output_dir,
    claim_dir,
    replace_marked_dir,
    temp_name,
    write_atomic,
)


def test_two_sweeps_in_the_same_second_get_their_own_directories(tmp_path):
    made = {claim_dir(tmp_path) for _ in range(3)}
    assert len(made) == 3 and all(p.is_dir() for p in made)


@pytest.mark.parametrize("below", ["", "/sub"])
def test_a_dangling_link_or_a_loop_on_an_output_path_is_named(tmp_path, below):
    """mkdir through a link to nothing, or a loop, failed with 'File exists' (exit 1); each is bad input naming the
    link."""
    (tmp_path / "gone").symlink_to(tmp_path / "nowhere")
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    with pytest.raises(BadInput) as dangling:
        check_output_dir(f"{tmp_path}/gone{below}", "--out")
    assert str(dangling.value) == (
        f"--out: {tmp_path}/gone{below}: {tmp_path}/gone is a symbolic link to {tmp_path}/nowhere, which does not "
        f"exist; give a directory path, or make the link's target first"
    )
    with pytest.raises(BadInput) as loop:
        check_output_dir(f"{tmp_path}/a{below}", "--out")
    assert (
        str(loop.value)
        == f"--out: {tmp_path}/a{below}: {tmp_path}/a is a symbolic link in a loop; give a directory path"
    )
    (tmp_path / "nowhere").mkdir()  # the link's target made: a directory like any other
    assert check_output_dir(f"{tmp_path}/gone{below}", "--out") == Path(f"{tmp_path}/gone{below}")


@pytest.mark.parametrize("key", ["--out", "hydra.sweep.dir", "hydra.run.dir"])
def test_a_directory_name_too_long_for_the_filesystem_is_one_line_before_anything_is_made(tmp_path, key):
    """Every output directory (report's and landscape's --out, a sweep's): "File name too long" came as exit 1
    after the work, or once the command began writing."""
    with pytest.raises(BadInput) as refused:
        check_output_dir(tmp_path / "x" / ("a" * 300), key)
    assert str(refused.value) == (
        f"{key}: names a folder of 300 bytes ({'a' * 24}...); this filesystem takes names of at most 255 bytes: give "
        f"a shorter one"
    )
    deep = tmp_path / "/".join(["b" * 200] * 21)  # each name allowed, the whole over PATH_MAX (4096) with its files
    with pytest.raises(BadInput, match=r"bytes long as an absolute path; this filesystem takes paths of at most 4096"):
        check_output_dir(deep, key)
    assert list(tmp_path.iterdir()) == []


def test_the_margin_for_files_inside_holds_a_runs_longest_temp_file():
    longest = max(len(temp_name(Path(f.name).name, "1234567")) + len(Path(f.name).parent.as_posix()) for f in FILES)
    assert longest + 1 <= INSIDE  # a killed atomic write's temp file, with a pid of up to 7 digits


def _no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as close() or fsync() raise it: naming no file


@pytest.mark.parametrize("fails", ["close", "fsync"])
def test_a_write_that_fails_at_close_or_fsync_names_the_file(tmp_path, monkeypatch, fails):
    """Its one line names the file, not only the directory (`cannot write into DIR`)."""
    target = tmp_path / "summary.json"
    if fails == "close":
        written = Path.write_text

        def write_then_fail(self, *args, **kwargs):
            written(self, *args, **kwargs)
            _no_space()

        monkeypatch.setattr(Path, "write_text", write_then_fail)
    else:
        monkeypatch.setattr(os, "fsync", _no_space)
    with pytest.raises(OSError) as caught:
        write_atomic(target, "{}")
    assert caught.value.filename == str(target) and caught.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []  # no temp file left
    line = write_failure(caught.value, tmp_path, "run it again")
    assert line.startswith(f"cannot write {target}: No space left on device; free space"), line


def test_an_error_that_names_a_file_keeps_it_and_one_without_an_errno_is_left_alone(tmp_path):
    other = tmp_path / "elsewhere"
    with pytest.raises(OSError) as named:
        with atomic_path(tmp_path / "a.json"):
            raise FileNotFoundError(errno.ENOENT, "No such file or directory", str(other))
    assert named.value.filename == str(other)
    with pytest.raises(OSError) as bare:
        with atomic_path(tmp_path / "a.json"):
            raise OSError("no errno")
    assert bare.value.filename is None and str(bare.value) == "no errno"


def test_a_marked_directory_whose_marker_fails_leaves_the_naming_to_its_caller(tmp_path, monkeypatch):
    """The marker is written in a temp sibling that goes on the failure: the exporter's line names the target."""
    monkeypatch.setattr(os, "fsync", _no_space)
    with pytest.raises(OSError) as caught:
        replace_marked_dir(tmp_path / "tb", {"format": "x"}, lambda tmp: None)
    assert caught.value.filename is None and str(caught.value) == "[Errno 28] No space left on device"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("relative", [True, False])
def test_a_detour_through_a_missing_folder_is_refused_and_one_through_an_existing_folder_passes(
    tmp_path, monkeypatch, relative
):
    monkeypatch.chdir(tmp_path)
    root = "" if relative else f"{tmp_path}/"
    with pytest.raises(BadInput) as refused:
        check_output_dir(f"{root}a/../b", "hydra.run.dir")
    assert str(refused.value) == (
        f"hydra.run.dir: {root}a/../b goes into {root}a and back out with '..', but {root}a does not exist (making "
        f"the path would leave it behind, empty); give {root}b"
    )
    assert list(tmp_path.iterdir()) == []  # nothing made
    (tmp_path / "a").mkdir()
    check_output_dir(f"{root}a/../b", "hydra.run.dir")
    check_output_dir(f"{root}../{tmp_path.name}/c", "hydra.run.dir")  # up from where one stands: it exists
