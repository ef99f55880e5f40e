"""riskplan landscape's guards: a failed rewrite keeps the previous landscape whole, and the report skips one that
did not finish; a second landscape into one --out is refused when it starts; only a features policy's weights are
varied, any two of them, labelled by what they weigh; Hydra's directories, unknown options and bad ranges are one
line that echoes what was typed; huge thetas are written as floats."""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from support import FAST, TINY, child_env, riskplan_command
from typer.testing import CliRunner

import riskplan
from riskplan.cli import app
from riskplan.experiments import landscape as L
from riskplan.experiments.output_manifest import WriteFailed
from riskplan.experiments.reporting import write_report
from riskplan.experiments.reporting.collect import collect
from riskplan.experiments.reporting.figures.beyond import fig_landscape
from riskplan.experiments.reporting.study_tables import landscape_for
from riskplan.experiments.reporting.tables import pair_text, runs_on
from riskplan.util.lock import LOCK, holder

pytestmark = pytest.mark.slow  # many configs composed and checked: seconds in all (the quick tier stays under a minute)

runner = CliRunner()
GRID = ["--points", "2", "--episodes", "5"]


def files(root: Path) -> dict[str, bytes]:
    """Every file below root but the writers' lock, by relative path."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file() and p.name != LOCK}


def refused(*args: str) -> str:
    """`riskplan landscape ARGS`: exit code 2 and one line on stderr, returned."""
    result = runner.invoke(app, ["landscape", *args])
    assert result.exit_code == 2, result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in result.output, result.output
    return lines[0]


# ------------------------------------------------------------------------------------------------ finding 1
@pytest.mark.parametrize(
    "fails",
    [
        lambda src, dst: "summary.json" in (Path(src).name, Path(dst).name),  # as if immutable (chattr +i)
        lambda src, dst: Path(dst).name == "status.json" and Path(src).name.endswith(".tmp"),  # the last file placed
    ],
    ids=["summary_immutable", "status_placed"],
)
def test_a_failed_rewrite_keeps_the_previous_landscape_whole(tmp_path, monkeypatch, fails):
    out = tmp_path / "scan"
    cfg = riskplan.compose(TINY)
    L.compute_landscape(cfg, out, points=3, episodes=10)
    before = files(out)
    real, failed = os.replace, []

    def replace(src, dst):
        if not failed and fails(src, dst):
            failed.append(src)
            raise PermissionError(1, "Operation not permitted")
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(WriteFailed) as err:
        L.compute_landscape(cfg, out, points=4, episodes=3)
    assert files(out) == before, "the previous landscape was changed"
    assert failed and "could not be written (Operation not permitted)" in str(err.value)
    assert "the files there before stay as they were" in str(err.value)
    (scan,) = collect([out]).landscapes
    assert scan.summary["points"] == 3 and len(scan.table) == 9


@pytest.mark.slow  # three landscapes and a report through the CLI
def test_an_immutable_file_leaves_the_previous_landscape_whole_and_reported(tmp_path):
    """The tester's reproduction: a rewrite that cannot replace summary.json (chattr +i) used to leave the new
    landscape.parquet beside the old summary.json, which the report then mixed."""
    out = tmp_path / "scan"
    invoke = runner.invoke(app, ["landscape", *TINY, "--points", "3", "--episodes", "10", "--out", str(out)])
    assert invoke.exit_code == 0, invoke.output
    before = files(out)
    if subprocess.run(["chattr", "+i", str(out / "summary.json")], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not possible here (not root, or the filesystem does not support it)")
    try:
        result = runner.invoke(app, ["landscape", *TINY, "--points", "4", "--episodes", "3", "--out", str(out)])
    finally:
        subprocess.run(["chattr", "-i", str(out / "summary.json")], check=True)
    assert result.exit_code == 1 and result.stderr.startswith(f"error: {out}/summary.json: could not be written (")
    assert files(out) == before
    report = runner.invoke(app, ["report", str(out), "--out", str(tmp_path / "report"), "--format", "png"])
    assert report.exit_code == 0, report.output
    assert (tmp_path / "report" / "landscape.csv").read_text().splitlines()[1].split(",")[1:4] == ["0.1", "10", "3"]


@pytest.mark.slow  # a run and two reports
def test_a_failed_report_rewrite_keeps_the_previous_report_whole(tmp_path, monkeypatch):
    """The report writes its set the same way: an SVG per figure staged, then report.html that cannot be placed,
    leaves the PNG report as it was, without SVGs beside it."""
    run, out = tmp_path / "run", tmp_path / "report"
    riskplan.train(riskplan.compose(TINY), run)
    write_report([run], out, ["png"])
    before = files(out)
    real, failed = os.replace, []

    def replace(src, dst):
        if not failed and Path(dst).name == "report.html" and Path(src).name.endswith(".tmp"):
            failed.append(src)
            raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(WriteFailed):
        write_report([run], out, ["png", "svg"])
    assert files(out) == before


@pytest.mark.parametrize(
    ("status", "reason"),
    [
        (None, "landscape: status.json: not found, so the landscape did not finish writing"),
        ('{"status": "running"}', "landscape: status.json: says 'running', not 'done'"),
    ],
)
def test_the_report_skips_a_landscape_that_is_not_done(tmp_path, status, reason):
    out = tmp_path / "scan"
    L.compute_landscape(riskplan.compose(TINY), out, points=2, episodes=5)
    if status is None:
        (out / "status.json").unlink()
    else:
        (out / "status.json").write_text(status)
    collected = collect([out])
    assert not collected.landscapes and [(b.path, b.reason) for b in collected.broken] == [(out, reason)]
    result = runner.invoke(app, ["report", str(out), "--out", str(tmp_path / "report")])
    assert result.exit_code == 2 and result.stderr == (
        f"error: {out}: holds no run that can be reported: {out} {reason}; compute it again (riskplan landscape "
        f"--out DIR), then report it\n"
    )
    assert not (tmp_path / "report").exists()


# ------------------------------------------------------------------------------------------------ finding 5: the lock
def test_a_second_landscape_into_one_out_is_refused_while_the_first_computes(tmp_path, monkeypatch):
    """The first holds --out's lock from its start: the second is refused at once, naming it, and the first ends
    whole (it used to be the first that stopped, after all its work)."""
    out = tmp_path / "scan"
    evaluate, second = L.evaluate_grid, []

    def meanwhile(*args, **kwargs):
        second.append(runner.invoke(app, ["landscape", *TINY, *GRID, "--out", str(out)]))
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(L, "evaluate_grid", meanwhile)
    L.compute_landscape(riskplan.compose(TINY), out, points=3, episodes=5)
    assert second[0].exit_code == 2 and second[0].stderr == (
        f"error: {out}: is in use by another riskplan process (pid {os.getpid()}); one process writes a landscape "
        f"directory at a time: wait for it to end or stop it\n"
    )
    assert json.loads((out / "summary.json").read_text())["points"] == 3
    assert json.loads((out / "status.json").read_text())["status"] == "done"


@pytest.mark.slow  # a long landscape in a process of its own
def test_a_second_landscape_process_is_refused_at_once(tmp_path):
    out = tmp_path / "scan"
    first = subprocess.Popen(
        [*riskplan_command(), "landscape", "--points", "60", "--episodes", "20000", "--out", str(out)],
        cwd=tmp_path,
        env=child_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.time() + 120
        while holder(out) != first.pid and first.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        assert holder(out) == first.pid, "the first landscape did not take --out's lock"
        started = time.time()
        line = refused(*GRID, "--out", str(out))
        assert time.time() - started < 10 and first.poll() is None
        assert line == (
            f"error: {out}: is in use by another riskplan process (pid {first.pid}); one process writes a landscape "
            f"directory at a time: wait for it to end or stop it"
        )
    finally:
        first.kill()
        first.wait(timeout=60)


# ------------------------------------------------------------------------------------------------ findings 2 and 4
def test_a_tabular_policy_is_refused(tmp_path):
    out = tmp_path / "scan"
    assert refused(*FAST, *GRID, "policy.kind=tabular", "--out", str(out)) == (
        "error: policy.kind: got 'tabular'; the landscape varies two weights of a features policy (eq. 3), not two "
        "of a table's 720 logits: give policy.kind=features (policy.features chooses the weights)"
    )
    assert not out.exists()


def test_any_two_theta_components_are_varied_and_labelled(tmp_path):
    out = tmp_path / "scan"
    features = "policy.features=[signals,risky]"
    result = runner.invoke(app, ["landscape", *FAST, *GRID, features, "--axes", "0,2", "--out", str(out)])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["axes"] == [0, 2] and summary["theta_names"] == ["safe", "risky", "risky_region"]
    assert summary["axis_labels"] == ["weight of source safe", "weight of feature risky_region"]
    collected = collect([out])
    (scan,) = collected.landscapes
    assert set(scan.table.theta_1) == {summary["theta_fixed"][1]} and scan.table.theta_2.nunique() == 2
    spec = fig_landscape(collected, scan, 0)
    assert {ax.get_xlabel() for ax in spec.figure.axes} >= {r"$\theta_{0}$ (weight of source safe)"}
    assert {ax.get_ylabel() for ax in spec.figure.axes} >= {r"$\theta_{2}$ (weight of feature risky_region)"}
    assert refused(*FAST, *GRID, features, "--axes", "0,3", "--out", str(tmp_path / "other")) == (
        "error: --axes: got 0,3; expected two different theta components of 0 safe, 1 risky, 2 risky_region"
    )


def test_runs_of_another_policy_are_not_drawn_on_a_landscape():
    """Same world and theta length, other features: [signals, stay] is not the [signals, risky] landscape's theta,
    nor is a features landscape the paper's 2-parameter policy's for policies.csv."""
    world = {"world": {"size": [20, 20]}}
    scan = SimpleNamespace(
        config={**world, "policy": {"kind": "features", "features": ["signals", "risky"]}},
        beta=0.1,
        summary={"theta_names": ["safe", "risky", "risky_region"], "theta_fixed": [20.0, 20.0, 0.0]},
    )

    def run(names):
        return SimpleNamespace(
            config={**world, "risk": {"measure": "cvar", "beta": 0.1}},
            run=SimpleNamespace(summary={"theta_names": names}),
            final_theta=lambda: [0.0, 0.0, 0.0],
        )

    same, other = run(["safe", "risky", "risky_region"]), run(["safe", "risky", "stay"])
    assert runs_on(scan, SimpleNamespace(runs=[same, other])) == [same]
    group = SimpleNamespace(config=world, beta=0.1)
    assert landscape_for(SimpleNamespace(landscapes=[scan]), group) is None


# ------------------------------------------------------------------------------------------------ findings 3 and 5
@pytest.mark.parametrize("key", ["hydra.run.dir", "hydra.sweep.dir"])
def test_hydra_directories_are_refused_pointing_to_out(tmp_path, monkeypatch, key):
    monkeypatch.chdir(tmp_path)
    assert refused(*FAST, *GRID, f"{key}=X") == (
        f"error: {key}: riskplan landscape writes where --out says (default "
        f"outputs/landscapes/<timestamp>_<experiment>/), not into Hydra's directories; give --out DIR"
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["--range=-inf,5"], "error: --range: got '-inf,5'; expected finite numbers, e.g. --range=-20,60"),
        (["--range=inf,5"], "error: --range: got 'inf,5'; expected finite numbers, e.g. --range=-20,60"),
        (
            ["--range=0,1e308"],
            "error: --range: got '0,1e308'; a theta that far overflows the softmax (theta . features is not finite), "
            "as riskplan train refuses it: give a narrower range, e.g. -20,20",
        ),
        (["--axes", "inf,1"], "error: --axes: got 'inf,1'; expected two whole theta indices, e.g. 0,1"),
        (
            ["policy.features=[stay]", "train.theta0=[0]"],
            "error: policy.features: gives theta one weight on this world (stay); the landscape varies two: add a "
            "source, or a feature (e.g. policy.features=[signals,risky])",
        ),
        (
            ["--resume", "x"],
            "error: option '--resume': is not known to riskplan landscape; give Hydra overrides (key=value) and "
            "--out, --points, --episodes, --range, --axes, -cd",
        ),
    ],
)
def test_bad_options_are_one_line_saying_what_was_typed(tmp_path, args, line):
    out = tmp_path / "scan"
    assert refused(*FAST, *GRID, *args, "--out", str(out)) == line
    assert not out.exists()


def test_huge_thetas_are_written_as_floats():
    assert pair_text((0.0, 1e200)) == "(0.0, 1e+200)"
    assert pair_text((46.54, -0.66)) == "(46.5, -0.7)"
