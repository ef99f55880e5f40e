"""Where `riskplan check --draw PATH` may write: a new path, an empty file or a picture of PATH's format (one it drew
before). A symbolic link was replaced by a file (a dangling one too), and a file that is no picture was overwritten
without a word; both are refused in one line, and left as they were."""

from __future__ import annotations

import os

import pytest
from typer.testing import CliRunner

from riskplan.cli import app

runner = CliRunner()


def draw(path: str):
    return runner.invoke(app, ["check", "train.iterations=1", "--draw", path])


@pytest.mark.parametrize("target", ["nowhere.png", "world.png"])
def test_a_symbolic_link_is_refused_and_kept(in_tmp, target):
    (in_tmp / "world.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    os.symlink(target, in_tmp / "link.png")
    result = draw("link.png")
    assert result.exit_code == 2
    assert result.stderr == (
        f"error: --draw: link.png is a symbolic link (to {target}); the picture would replace the link, not write its "
        f"target: give the target's own path\n"
    )
    assert os.readlink(in_tmp / "link.png") == target and (in_tmp / "world.png").read_bytes() == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("name", "data"),
    [("notes.png", b"my notes\n"), ("world.pdf", b"\x89PNG\r\n\x1a\n..."), ("world.svg", b"<html>a page</html>")],
)
def test_a_file_that_is_no_picture_of_its_format_is_refused_and_kept(in_tmp, name, data):
    (in_tmp / name).write_bytes(data)
    result = draw(name)
    assert result.exit_code == 2
    fmt = name.rsplit(".", 1)[1].upper()
    assert result.stderr == (
        f"error: --draw: {name} exists and is not a {fmt} picture; --draw replaces only a picture (one it drew "
        f"before): give a new path, or move the file\n"
    )
    assert (in_tmp / name).read_bytes() == data


def test_a_fifo_is_refused_without_waiting_for_a_writer(in_tmp):
    os.mkfifo(in_tmp / "pipe.png")
    result = draw("pipe.png")
    assert result.exit_code == 2 and "pipe.png exists and is not a PNG picture" in result.stderr


@pytest.mark.slow  # three drawings of the world
@pytest.mark.parametrize("fmt", ["png", "svg", "pdf"])
def test_a_picture_drawn_before_and_an_empty_file_are_drawn_over(in_tmp, fmt):
    (in_tmp / f"empty.{fmt}").write_bytes(b"")
    for name in (f"world.{fmt}", f"world.{fmt}", f"empty.{fmt}"):  # new, then over the picture, then over nothing
        result = draw(name)
        assert result.exit_code == 0, result.output
        assert f"world drawn: {name}" in result.stdout
    assert (in_tmp / f"empty.{fmt}").read_bytes() == (in_tmp / f"world.{fmt}").read_bytes()
