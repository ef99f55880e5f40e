"""A user's config folder (-cd DIR) read before Hydra composes it: each file Hydra would fail on with a traceback, or
expand for minutes, is one line naming the file and its line."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

import riskplan.config.user_files as user_files
from riskplan.cli import app
from riskplan.config.typed import check_file_value
from riskplan.config.user_files import check_config_files
from riskplan.util.errors import BadInput

HEAD = "# @package _global_\nexperiment: mine\n"
BOMB = (
    HEAD
    + "a0: &a0 [x, x, x, x, x, x, x, x, x]\n"
    + "".join(f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]\n" for i in range(1, 10))
)  # 459 bytes holding 9^9 values: 120 s and 1.4 GB, unfinished, before


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        (
            HEAD + "train:\n\titerations: 3\n",
            "is not valid YAML at line 4, column 1: found character '\\t' that cannot",
        ),
        (HEAD + "seed: 1\nseed: 2\n", "line 4: the key 'seed' is given twice (first on line 3); give it once"),
        (
            HEAD + "seed: !!python/object/apply:os.system [echo]\n",
            "line 3: the tag !!python/object/apply:os.system makes",
        ),
        (BOMB, "line 9: expands to more than 1,000,000 values through its aliases (*name); write the values out"),
        pytest.param(
            HEAD + "junk: " + "[" * 2000 + "]" * 2000 + "\n",
            "is nested too deeply to read (thousands of levels)",
            marks=pytest.mark.slow,  # a second: PyYAML recurses until Python stops it
        ),
        ("- seed\n- 3\n", "holds a list at its top level; a config file is a mapping of keys, e.g. seed: 3"),
        (b"# @package _global_\nexperiment: m\xe9\n", "is not UTF-8 text (byte 0xe9 on line 2); save it as UTF-8"),
        # Hydra took these for a package: "Key '' not in 'RiskplanConf'", or its own ValueError
        ("# @package ../../etc\nseed: 3\n", "has the header '# @package ../../etc'; a package is _global_, _group_"),
        ("\n# @package\nseed: 3\n", "has the header '# @package'; a package is"),
        ("# @package _global_ world\nseed: 3\n", "has the header '# @package _global_ world'; a package is"),
    ],
)
def test_a_file_hydra_would_fail_on_is_one_line_naming_it(tmp_path, text, problem):
    path = tmp_path / "experiment" / "mine.yaml"
    path.parent.mkdir()
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(BadInput) as refused:
        check_config_files(tmp_path)
    assert refused.value.where == str(path) and refused.value.problem.startswith(problem)


@pytest.mark.parametrize("header", ["# @package _global_", "#@package world.sources", "# @package _group_", "# plain"])
def test_a_package_hydra_knows_passes_and_the_header_ends_at_the_first_other_line(tmp_path, header):
    (tmp_path / "mine.yaml").write_text(f"{header}\nseed: 3\n# @package ../not/a/header/any/more\n")
    check_config_files(tmp_path)


def test_files_of_plain_values_and_a_few_aliases_pass(tmp_path):
    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "mine.yaml").write_text(
        HEAD + "cov: &c [[4.0, 0.0], [0.0, 4.0]]\nworld:\n  sources:\n    - {position: [1, 1], covariance: *c}\n"
        "    - {position: [5, 5], covariance: *c}\n"
    )
    (tmp_path / "notes.yaml").write_text("")  # an empty file is an empty mapping
    check_config_files(tmp_path)


def test_a_file_beyond_the_size_limit_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(user_files, "MAX_BYTES", 100)
    (tmp_path / "big.yaml").write_text("seed: 1\n" * 20)
    with pytest.raises(BadInput, match="is 0 MB; a config file holds at most 0 MB"):
        check_config_files(tmp_path)


def test_the_command_line_names_the_file_and_composition_errors_name_the_file_too(tmp_path):
    folder = tmp_path / "mine"
    (folder / "experiment").mkdir(parents=True)
    (folder / "experiment" / "odd.yaml").write_text(HEAD + "seed: 1\nseed: 2\n")
    result = CliRunner().invoke(app, ["check", "-cd", str(folder), "experiment=odd"])
    assert result.exit_code == 2 and result.stderr == (
        f"error: {folder}/experiment/odd.yaml: line 4: the key 'seed' is given twice (first on line 3); give it once\n"
    )
    (folder / "experiment" / "odd.yaml").write_text(HEAD + "train:\n  lr: 3\n")  # valid YAML, a key the schema lacks
    result = CliRunner().invoke(app, ["check", "-cd", str(folder), "experiment=odd"])
    assert result.exit_code == 2 and result.stderr.startswith("error: key 'train.lr': unknown key 'lr'; valid keys ")
    assert result.stderr.endswith(" (in the config file experiment/odd.yaml)\n")


@pytest.mark.parametrize(
    ("file", "text", "problem"),
    [
        ("world/mine.yaml", "stop_at_source: 2\n", "line 1: key 'world.stop_at_source': got 2; expected true or false"),
        ("experiment/mine.yaml", HEAD + "train:\n  baseline: -1\n", "line 3: key 'train.baseline': got -1;"),
        ("mine.yaml", "defaults:\n  - _self_\ntrain: {baseline: '7'}\n", "line 3: key 'train.baseline': got '7';"),
        (
            "places/mine.yaml",
            "# @package world\nregions:\n  - {rect: [0, 0, 1, 1], risky: 2}\n",
            "line 2: key 'world.regions.0.risky': got 2;",
        ),
    ],
)
def test_a_boolean_given_another_integer_in_a_file_is_refused_as_on_the_command_line(tmp_path, file, text, problem):
    # Hydra's merge onto the schema turns any integer into true, so the file is the last place the slip shows
    path = tmp_path / file
    path.parent.mkdir(exist_ok=True)
    path.write_text(text)
    with pytest.raises(BadInput) as refused:
        check_config_files(tmp_path, check_file_value)
    assert refused.value.where == str(path) and refused.value.problem.startswith(problem)


@pytest.mark.parametrize(
    ("file", "text"),
    [
        ("world/mine.yaml", "stop_at_source: 0\nsize: [5, 5]\n"),
        ("experiment/mine.yaml", HEAD + "train: {baseline: 1}\n"),
        ("experiment/other.yaml", "train: {baseline: 5}\n"),  # lands under experiment, a string key: not a flag
        ("risk/mine.yaml", "# @package _global_\nworld: {stop_at_source: false}\n"),
    ],
)
def test_booleans_written_as_hydra_reads_them_pass(tmp_path, file, text):
    path = tmp_path / file
    path.parent.mkdir(exist_ok=True)
    path.write_text(text)
    check_config_files(tmp_path, check_file_value)
