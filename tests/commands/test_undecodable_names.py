"""Names the locale cannot decode: under a locale that is not UTF-8 (LC_ALL=C without Python's UTF-8 mode), a
non-ASCII folder name reaches Python as lone surrogates, which no UTF-8 file (config, log, table) can hold. A run
used to train and then fail writing its tables; such an argument or working directory is now bad input before
anything is written, and a run folder renamed so by hand is skipped by report, not fatal."""

from __future__ import annotations

import os
import re
import shutil

import numpy as np
import pytest
from support import TINY, run_cli
from typer.testing import CliRunner

from riskplan import compose
from riskplan.cli import app
from riskplan.run.columns import read_parquet, write_parquet
from riskplan.run.results import find_runs
from riskplan.run.training import train
from riskplan.util.errors import BadInput
from riskplan.util.paths import shown_bytes, undecoded

NAME = os.fsdecode(b"r\xfcn")  # 'rün' in Latin-1, as a UTF-8 locale hands it to Python: 'r\udcfcn'
SHOWN = r"r\xfcn"
LINE = (
    "holds bytes this system's locale cannot decode, and riskplan writes its paths into UTF-8 files; run under a "
    "UTF-8 locale (LC_ALL=C.UTF-8, or PYTHONUTF8=1) or use an ASCII name"
)
runner = CliRunner()


def test_a_name_with_undecoded_bytes_is_told_and_shown_as_its_bytes():
    assert undecoded(NAME) and not undecoded("rün") and not undecoded("run")
    assert shown_bytes(NAME) == SHOWN and shown_bytes("run/a") == "run/a"


def test_an_argument_with_undecoded_bytes_is_one_line_and_nothing_is_written(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["train", *TINY, f"hydra.run.dir={tmp_path}/{NAME}"])
    assert result.exit_code == 2
    assert result.stderr == f"error: argument hydra.run.dir={tmp_path}/{SHOWN}: {LINE}\n"
    assert list(tmp_path.iterdir()) == []


def test_a_working_directory_with_undecoded_bytes_is_one_line(tmp_path, monkeypatch):
    here = tmp_path / NAME
    here.mkdir()
    monkeypatch.chdir(here)
    result = runner.invoke(app, ["train", *TINY])
    assert result.exit_code == 2
    assert result.stderr == f"error: the working directory {tmp_path}/{SHOWN}: {LINE}\n"
    assert list(here.iterdir()) == []  # no outputs/


def test_the_python_api_refuses_such_an_output_directory_before_training(tmp_path):
    with pytest.raises(BadInput) as refused:
        train(compose(TINY), tmp_path / NAME)
    assert str(refused.value) == f"{tmp_path}/{SHOWN}: {LINE}"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow  # a run, then two reports: about 3 s
def test_report_skips_a_run_folder_renamed_with_undecoded_bytes(tmp_path):
    good = tmp_path / "runs" / "good"
    train(compose(TINY), good)
    shutil.copytree(good, tmp_path / "runs" / NAME)
    with pytest.warns(UserWarning, match=re.escape(f"skipped {tmp_path}/runs/{SHOWN}: its name holds bytes")):
        result = runner.invoke(app, ["report", str(tmp_path / "runs"), "--out", str(tmp_path / "report")])
    assert result.exit_code == 0, result.output
    assert "1 run(s) in 1 group(s)" in result.stdout
    alone = runner.invoke(app, ["report", str(tmp_path / "runs" / NAME), "--out", str(tmp_path / "other")])
    assert alone.exit_code == 2 and alone.stderr == f"error: argument {tmp_path}/runs/{SHOWN}: {LINE}\n"
    with pytest.warns(UserWarning, match="skipped"), pytest.raises(BadInput) as nothing:
        find_runs([tmp_path / "runs" / NAME])  # the Python API takes such a path
    assert str(nothing.value).endswith("holds no run whose folder name this system's locale decodes (see above)")


def test_parquet_files_are_read_and_written_under_any_name_the_system_gave(tmp_path):
    """arrow encodes a path as UTF-8; riskplan hands it an open file instead."""
    path = tmp_path / f"{NAME}.parquet"
    write_parquet({"x": np.arange(3), "y": np.array([0.5, np.nan, 2.0])}, path)
    frame = read_parquet(path, columns=["x"])
    assert frame.x.tolist() == [0, 1, 2] and list(frame.columns) == ["x"]


@pytest.mark.slow  # a process of its own under the C locale: about 3 s
def test_under_an_ascii_locale_a_non_ascii_run_directory_is_refused_before_it_exists(tmp_path):
    """'rün' in UTF-8 (this process's locale), which the C locale cannot decode."""
    result = run_cli(
        ["train", *TINY, f"hydra.run.dir='{tmp_path}/rün'"],
        tmp_path,
        LC_ALL="C",
        LANG="C",
        PYTHONUTF8="0",
        PYTHONCOERCECLOCALE="0",
    )
    assert result.returncode == 2
    assert result.stderr == f"error: argument hydra.run.dir='{tmp_path}/r\\xc3\\xbcn': {LINE}\n"
    assert list(tmp_path.iterdir()) == []
