"""Bad input everywhere: every row of the bad-input table in docs/robustness.md is run through the real CLI (typer's CliRunner)
in a scratch directory. Each must exit with code 2 and print exactly the table's line on stderr (one plain line,
no traceback), and leave the directory exactly as it was: no run directory, no file touched."""

from __future__ import annotations

import json
import re
import shlex
import shutil
from pathlib import Path

import pytest
from support import TINY
from typer.testing import CliRunner

from riskplan import compose
from riskplan.cli import app
from riskplan.run.checkpoint import CHECKPOINT
from riskplan.run.training import train
from riskplan.util.lock import LOCK

README = Path(__file__).resolve().parents[2] / "docs" / "robustness.md"
BEGIN, END = "<!-- bad-input-table: begin -->", "<!-- bad-input-table: end -->"
RUN = [*TINY, "train.iterations=12", "train.checkpoint_every=5"]  # the table's runs are checkpointed at iteration 12

pytestmark = pytest.mark.slow  # a run, a landscape and a report to copy, then a command per row: 30-45 s

runner = CliRunner()


def table_rows() -> list[tuple[str, str, list[str], str]]:
    """(number, input, argv, expected stderr line) for each row of the README table."""
    text = README.read_text()
    body = text[text.index(BEGIN) + len(BEGIN) : text.index(END)]
    rows = []
    for line in body.strip().splitlines()[2:]:  # skip the header and the --- row
        number, what, command, expected = (cell.strip() for cell in line.strip().strip("|").split(" | "))
        argv = shlex.split(command.strip("`"))
        assert argv[0] == "riskplan", line
        rows.append((number, what, argv[1:], expected.strip("`")))
    return rows


ROWS = table_rows()


def test_the_table_has_at_least_25_distinct_inputs_across_every_command():
    assert len(ROWS) >= 25
    assert len({tuple(argv) for _, _, argv, _ in ROWS}) == len(ROWS)
    assert len({number for number, _, _, _ in ROWS}) == len(ROWS)  # a row's number names it in notes and issues
    commands = {argv[0] + (" --resume" if "--resume" in argv else "") for _, _, argv, _ in ROWS}
    assert commands >= {"train", "train --resume", "check", "report", "sweep"}


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    """The scratch directory's contents: the runs, the empty directory and the file the table names."""
    root = tmp_path_factory.mktemp("bad_input")
    runs = root / "outputs" / "runs"
    done = runs / "done"
    train(compose(RUN), done)  # a finished run, checkpointed at iteration 12
    damaged = runs / "damaged"
    shutil.copytree(done, damaged)
    (damaged / CHECKPOINT).write_text('{"iteration": 1')
    no_config = runs / "no_config"
    shutil.copytree(done, no_config)
    shutil.rmtree(no_config / ".hydra")
    not_mcap = runs / "not_mcap"
    shutil.copytree(done, not_mcap)
    (not_mcap / "run.mcap").write_text("these are notes, not a log")
    (root / "empty").mkdir()
    killed = root / "stopped" / "killed"  # a run killed mid-way: half its log, none of its final files
    shutil.copytree(done, killed)
    log = (killed / "run.mcap").read_bytes()
    (killed / "run.mcap").write_bytes(log[: len(log) // 2])
    for name in ("summary.json", "metrics.parquet", "eval.parquet", "trajectories.parquet"):
        (killed / name).unlink(missing_ok=True)
    (root / "notes.txt").write_text("not a run\n")
    never = runs / "never"  # a run whose start a full disk cut short: Hydra had begun its config, in place
    (never / ".hydra").mkdir(parents=True)
    (never / ".hydra" / "config.yaml").write_text("")
    (never / "app.log").write_text("")
    (never / LOCK).write_text("")  # its lock, which it took first
    (runs / "claimed").mkdir()  # a run killed as it claimed its directory: its lock alone
    (runs / "claimed" / LOCK).write_text("")
    (root / "loop").symlink_to("loop")  # a symbolic link to itself
    (root / "slips" / "world").mkdir(parents=True)  # a -cd folder whose world file gives a boolean key 2
    (root / "slips" / "world" / "slip.yaml").write_text("stop_at_source: 2\n")
    # checkpoints and configs that cannot be this run's (resume validates them)
    for name, edit in (
        ("nan_theta", lambda c: {**c, "thetas": [[float("nan"), 1.0]]}),
        ("negative", lambda c: {**c, "iteration": -3}),
    ):
        bad = runs / name
        shutil.copytree(done, bad)
        checkpoint = json.loads((bad / CHECKPOINT).read_text())
        (bad / CHECKPOINT).write_text(json.dumps(edit(checkpoint)))
    for name, text in (("unresolvable", "seed: ${oc.env:RISKPLAN_UNSET_VARIABLE}\n"), ("not_yaml", "seed: [0\n")):
        bad = runs / name
        shutil.copytree(done, bad)
        config = bad / ".hydra" / "config.yaml"
        config.write_text(
            text + "\n".join(line for line in config.read_text().splitlines() if not line.startswith("seed:")) + "\n"
        )
    # rows 160-179 (report and landscape --out): a landscape's directory and a report's directory, each with the
    # manifest its command writes
    from riskplan.experiments.landscape import compute_landscape
    from riskplan.experiments.reporting import build_report

    compute_landscape(compose(RUN), root / "outputs" / "landscapes" / "land", points=3, episodes=20)
    build_report([done], root / "outputs" / "reports" / "old", ["png"])
    return root


def snapshot(root: Path) -> dict[str, tuple[int, int, bytes]]:
    """Every file and directory below root, with size, modification time and (for files) content."""
    return {
        str(p.relative_to(root)): (
            p.stat().st_size if p.is_file() else -1,
            p.lstat().st_mtime_ns,  # a link's own (one is a loop)
            p.read_bytes() if p.is_file() else b"",
        )
        for p in sorted(root.rglob("*"))
    }


def pattern(expected: str) -> re.Pattern:
    """The table's line as a regex: `…` stands for any text."""
    return re.compile(".*".join(re.escape(part) for part in expected.split("…")))


@pytest.mark.parametrize("number, what, argv, expected", ROWS, ids=[f"{r[0]}-{r[1]}" for r in ROWS])
def test_bad_input(template, tmp_path, monkeypatch, number, what, argv, expected):
    scratch = tmp_path / "scratch"
    shutil.copytree(template, scratch, symlinks=True)  # links as links (one is a loop)
    monkeypatch.chdir(scratch)
    before = snapshot(scratch)

    result = runner.invoke(app, argv)

    assert result.exit_code == 2, f"exit {result.exit_code}: {result.output}{result.exception!r}"
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert pattern(expected).fullmatch(lines[0]), f"\n got: {lines[0]}\nwant: {expected}"
    assert "Traceback" not in result.output
    assert snapshot(scratch) == before, "bad input left something behind"
