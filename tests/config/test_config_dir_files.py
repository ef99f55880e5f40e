"""Which files of a `-cd DIR` are read before Hydra composes: those Hydra could load from DIR as a search-path entry
(any group folder, at any depth, and DIR's own top-level files), not every *.yaml below it. A run's .hydra records,
outputs/, .git and Python environments are never config groups; a folder of thousands is no config folder."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

import riskplan.config.user_files as user_files
from riskplan.cli import app
from riskplan.config.user_files import check_config_files, config_files
from riskplan.util.errors import BadInput

runner = CliRunner()
MINE = "# @package _global_\nexperiment: mine\ntrain:\n  iterations: 3\n"
NOT_CONFIG = "- a list\n- at its top level\n"  # a run's .hydra/overrides.yaml: valid YAML, no config


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_only_files_hydra_could_load_are_read(tmp_path):
    """DIR/<group>/<option>.yaml at any depth and DIR's own files; not a run's records, outputs/, .git, a virtualenv
    or a conda environment, each of which held a file that refused the folder."""
    loaded = [
        write(tmp_path / "top.yaml", "seed: 1\n"),
        write(tmp_path / "experiment" / "mine.yaml", MINE),
        write(tmp_path / "experiment" / "sub" / "deep.yaml", MINE),
        write(tmp_path / "mygroup" / "x.yaml", "seed: 2\n"),
    ]
    write(tmp_path / "outputs" / "runs" / "2025_mine" / ".hydra" / "overrides.yaml", NOT_CONFIG)
    write(tmp_path / "outputs" / "runs" / "2025_mine" / "notes.yaml", NOT_CONFIG)
    write(tmp_path / "elsewhere" / "run" / ".hydra" / "overrides.yaml", NOT_CONFIG)
    write(tmp_path / ".git" / "x.yaml", NOT_CONFIG)
    write(tmp_path / "venv" / "pyvenv.cfg", "home = /usr/bin\n")
    write(tmp_path / "venv" / "lib" / "site-packages" / "pkg" / "x.yaml", NOT_CONFIG)
    write(tmp_path / "env" / "conda-meta" / "history", "")
    write(tmp_path / "env" / "lib" / "x.yaml", NOT_CONFIG)
    assert config_files(tmp_path) == loaded  # DIR's own files, then each folder's, in order
    check_config_files(tmp_path)


def test_a_linked_group_folder_is_read_and_a_link_loop_once(tmp_path):
    """Hydra follows a linked group folder, so its files are checked; a link back up the tree is walked once."""
    shared = write(tmp_path / "shared" / "bad.yaml", NOT_CONFIG)
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "experiment").symlink_to(shared.parent, target_is_directory=True)
    (tmp_path / "configs" / "loop").symlink_to(tmp_path / "configs", target_is_directory=True)
    assert config_files(tmp_path / "configs") == [tmp_path / "configs" / "experiment" / "bad.yaml"]
    with pytest.raises(BadInput, match="holds a list at its top level"):
        check_config_files(tmp_path / "configs")


def test_a_folder_of_more_folders_than_any_config_folder_is_one_line(tmp_path, monkeypatch):
    """`-cd /` walked the whole filesystem (and read every *.yaml on it)."""
    monkeypatch.setattr(user_files, "MAX_FOLDERS", 3)
    for name in ("a", "b", "c"):
        (tmp_path / name).mkdir()
    with pytest.raises(BadInput) as refused:
        check_config_files(tmp_path)
    assert refused.value.where == str(tmp_path)
    assert refused.value.problem.startswith("holds more than 3 folders (besides hidden ones, outputs/ and Python")
    (tmp_path / "c").rename(tmp_path / ".c")  # hidden: not counted
    check_config_files(tmp_path)


def test_the_root_folder_is_refused_in_one_line():
    result = runner.invoke(app, ["check", "-cd", "/"])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: /: holds more than 2,000 folders") and result.stderr.count("\n") == 1


def test_a_project_folder_with_its_runs_and_virtualenv_is_a_config_dir(tmp_path, monkeypatch):
    """`riskplan train -cd . experiment=mine` worked once: the second time its first run's .hydra/overrides.yaml
    (a list) refused the folder; so did a file inside .venv for -cd of a project."""
    write(tmp_path / "experiment" / "mine.yaml", MINE)
    write(tmp_path / "outputs" / "runs" / "2025-01-01_00-00-00_mine" / ".hydra" / "overrides.yaml", NOT_CONFIG)
    write(tmp_path / ".venv" / "lib" / "python3.11" / "site-packages" / "x" / "broken.yaml", "a: [\n")
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["check", "-cd", ".", "experiment=mine"])
    assert result.exit_code == 0, result.output
    assert "experiment: mine" in result.stdout


def test_a_bad_file_in_a_nested_group_is_still_named(tmp_path):
    """experiment=sub/deep loads DIR/experiment/sub/deep.yaml: a file there is checked as before."""
    bad = write(tmp_path / "experiment" / "sub" / "deep.yaml", MINE + "seed: 1\nseed: 2\n")
    result = runner.invoke(app, ["check", "-cd", str(tmp_path), "experiment=sub/deep"])
    assert result.exit_code == 2
    assert result.stderr == f"error: {bad}: line 6: the key 'seed' is given twice (first on line 5); give it once\n"
