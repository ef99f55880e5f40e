"""Values of the wrong shape are one line naming the key, what it got and what it takes (exit code 2, nothing
written), never a traceback: a nested list or a mapping in a flat list of scalars (OmegaConf's typed lists take one
as an item), a list where the schema has a mapping and the reverse, null for a key that takes none, an integer other
than 0 or 1 for a boolean, a fractional rect corner, a fault's start beyond any iteration, a signal too faint to
sense."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from riskplan.cli import app
from riskplan.config.typed import check_flags
from riskplan.run.compose import parse_overrides
from riskplan.util.errors import BadInput

runner = CliRunner()
TEAM = "experiment=paper_team"


def refused(args: list[str], line: str, where: Path) -> None:
    """The command exits with code 2, prints exactly `line` on stderr and writes nothing."""
    result = runner.invoke(app, args)
    assert (result.exit_code, result.stderr) == (2, f"error: {line}\n"), result.output
    assert list(where.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["check", "train.theta0=[[1],[2]]"], "train.theta0: got [[1], [2]]; expected a list of numbers"),
        (["train", "train.theta0=[[1,2]]"], "train.theta0: got [[1, 2]]; expected a list of numbers"),
        (["check", "train.theta0=[{a:1}]"], "train.theta0: got [{a: 1}]; expected a list of numbers"),
        (["check", "world.size=[[12],[12]]"], "world.size: got [[12], [12]]; expected a list of whole numbers"),
        (
            ["check", "world.regions.0.halfplane=[[1],0,0]"],
            "world.regions.0.halfplane: got [[1], 0.0, 0.0]; expected a list of numbers",
        ),
        (
            [
                "check",
                TEAM,
                "team.speeds=[[1],[1],[1]]",
            ],
            "team.speeds: got [[1], [1], [1]]; expected a list of numbers",
        ),
        (
            ["check", "policy.features=[[signals]]"],
            "policy.features: got [[signals]]; expected a list of names from signals, risky, stay",
        ),
        (  # every job of a sweep: refused before anything runs
            ["sweep", "train.theta0=[[1]]", "seed=0,1"],
            "train.theta0: got [[1]]; expected a list of numbers (in every one of the 2 combinations; nothing was run)",
        ),
    ],
)
@pytest.mark.slow  # 8 commands through the CLI
def test_a_nested_list_or_a_mapping_in_a_flat_list_is_one_line(in_tmp, args, line):
    refused(args, line, in_tmp)


def test_a_nested_list_in_an_experiment_file_is_one_line(in_tmp):
    folder = in_tmp / "configs"
    (folder / "experiment").mkdir(parents=True)
    (folder / "experiment" / "mine.yaml").write_text(
        "# @package _global_\nexperiment: mine\ntrain:\n  theta0: [[1], [2]]\n"
    )
    result = runner.invoke(app, ["check", "-cd", str(folder), "experiment=mine"])
    assert (result.exit_code, result.stderr) == (2, "error: train.theta0: got [[1], [2]]; expected a list of numbers\n")
    assert [p.name for p in in_tmp.iterdir()] == ["configs"]


@pytest.mark.parametrize(
    ("args", "line"),
    [  # lists of lists: OmegaConf checks their items, and the line says what an item takes
        (
            [TEAM, "team.graph=edges", "team.edges=[[0.5,1],[1,2]]"],
            "key 'team.edges.0': got [0.5, 1]; expected a list of whole numbers",
        ),
        (["world.obstacles=[[[1],2]]"], "key 'world.obstacles.0': got [[1], 2]; expected a list of whole numbers"),
        (  # a list over a mapping, a mapping over a list
            ["risk.schedule=[linear]"],
            "key 'risk.schedule': got a list; expected a mapping with keys kind, start, iterations",
        ),
        (["world.size={a:1}"], "key 'world.size': got a mapping; expected a list of whole numbers"),
        (
            ["risk.measure=null"],
            "key 'risk.measure': got null; expected a measure's name: cvar, neutral, wang, mean_cvar, entropic or one "
            "from a package",
        ),
        (
            ["experiment=${oc.env:HOME}"],
            f"key 'experiment': got '{Path.home()}', a path out of its folder (an interpolation gives one); give one of "
            "its options by name: floor_plan, paper_single, paper_team, or your own with -cd DIR",
        ),
        (  # positions keep their own lines
            ["experiment=floor_plan", "world.start={metres:[0.9,0.9]}"],
            "key 'world.start': a mapping cannot replace the list an earlier config gives it; a position in metres "
            "over an [x, y] is written ${metres:X,Y}, which stands for {metres: [X, Y]}",
        ),
        ([TEAM, "team.starts=[[[0],0],[1,1],[2,2]]"], "team.starts.0: got [[0], 0]; expected [x, y] of whole numbers"),
        (
            ["world.sources.0.covariance=[[[1],0],[0,1]]"],
            "world.sources.0.covariance: got [[[1], 0], [0, 1]]; expected [[a, b], [b, c]]",
        ),
    ],
)
def test_a_value_of_the_wrong_shape_says_what_the_key_takes(in_tmp, args, line):
    refused(["check", *args], line, in_tmp)


@pytest.mark.parametrize(
    ("rect", "shown"),
    [
        ("abc", "'abc'"),
        ("[0.5,0,3,3]", "[0.5, 0, 3, 3]"),
        ("[0,0,3]", "[0, 0, 3]"),
        ("[0,0,3,true]", "[0, 0, 3, True]"),
    ],
)
def test_a_rect_takes_four_whole_corners_as_a_cell_takes_two(in_tmp, rect, shown):
    """A fractional corner was taken as the next whole cell (0.5 as x >= 1), where any cell refuses a fraction."""
    line = f"world.regions.1.rect: got {shown}; expected [x0, y0, x1, y1] of whole numbers"
    refused(["check", f"world.regions.1.rect={rect}"], line, in_tmp)


@pytest.mark.parametrize(("start", "shown"), [("1e308", "1e+308"), ("2.5", "2.5"), (str(2**63), str(2**63))])
def test_a_fault_starts_at_a_whole_iteration_below_2_63(in_tmp, start, shown):
    """1e308 is >= 0, but no iteration; 2^63 overflowed the engine's int64 iterations once the run had started."""
    line = f"team.faults.0.from: got {shown}; expected the iteration it starts at, a whole number 0 <= from < 2^63, e.g. 50"
    refused(["check", TEAM, f"team.faults=[{{robot:0,kind:crash,from:{start}}}]"], line, in_tmp)


@pytest.mark.parametrize(("scale", "shown", "peak"), [("0", "0", "0"), ("1e-320", "9.99989e-321", "9.88e-323")])
def test_a_signal_too_faint_to_sense_is_refused(in_tmp, scale, shown, peak):
    """w = 0 (or a denormal) makes the source's signal vanish: theta's weight for it could never learn."""
    line = (
        f"world.sources.0.scale: got {shown}; the signal would peak at about {peak}, below 1e-100, where the policy "
        "cannot sense the source; give a larger |scale|, or null for a peak of 1"
    )
    refused(["check", f"world.sources.0.scale={scale}"], line, in_tmp)


def test_a_negative_scale_is_a_signal_read_with_its_sign(in_tmp):
    with pytest.warns(UserWarning, match="source 0 'safe' is reached by 0.0% of the initial policy's episodes"):
        result = runner.invoke(app, ["check", "world.sources.0.scale=-50"])  # theta0 weighs a repelling signal
    assert result.exit_code == 0 and result.stdout.endswith("config OK\n"), result.output


@pytest.mark.parametrize(
    ("override", "line"),
    [
        ("world.stop_at_source=2", "key 'world.stop_at_source': got 2; expected true or false (or 1 or 0)"),
        ("train.baseline=5", "key 'train.baseline': got 5; expected true or false (or 1 or 0)"),
        ("team.directed=-1", "key 'team.directed': got -1; expected true or false (or 1 or 0)"),
        ("train.baseline='2'", "key 'train.baseline': got '2'; expected true or false (or 1 or 0)"),
        ("train.baseline=true,2", "key 'train.baseline': got 2; expected true or false (or 1 or 0)"),  # a sweep's
        (
            "world.regions=[{name:a,rect:[0,0,1,1],risky:2}]",  # inside a list the override sets
            "key 'world.regions.0.risky': got 2; expected true or false (or 1 or 0)",
        ),
    ],
)
def test_a_boolean_takes_no_integer_but_0_or_1(override, line):
    """OmegaConf turns any integer into a bool (5 is true, -1 is true): the override is checked before it can."""
    with pytest.raises(BadInput) as err:
        check_flags(parse_overrides([override]))
    assert str(err.value) == line


@pytest.mark.parametrize("value", ["true", "false", "0", "1", "yes", "off", "maybe"])
def test_booleans_as_omegaconf_spells_them_pass_the_check(value):
    check_flags(parse_overrides([f"train.baseline={value}"]))  # `maybe` is OmegaConf's to refuse, in its own line


def test_a_boolean_given_an_integer_is_refused_by_the_cli(in_tmp):
    """check_override_values checks the parsed overrides of check, train, sweep and reproduce alike."""
    refused(["check", "train.baseline=5"], "key 'train.baseline': got 5; expected true or false (or 1 or 0)", in_tmp)
