"""The outputs of `riskplan report` and `riskplan landscape` are safe: runs with broken configs are skipped with
their reason; --out is refused when it holds files riskplan did not write (a manifest marks what the command
wrote, so re-running into its own output works); every file is written atomically, so a full disk (a real tmpfs)
leaves the previous files whole and no temp or empty file; a read-only target (a real read-only bind mount) is one
line; the landscape is bounded in memory and time before it runs; summary.json is strict JSON; missing values in
the report's outputs are empty cells or n/a, never nan or inf."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from support import TINY, held_by_another_process
from typer.testing import CliRunner

import riskplan
from riskplan.cli import app
from riskplan.experiments.landscape import compute_landscape
from riskplan.run.results import load_run
from riskplan.util.errors import BadInput
from riskplan.util.lock import LOCK

LAND = ["--points", "3", "--episodes", "20"]
MANIFEST = ".riskplan-manifest.json"  # riskplan.experiments.output_manifest.MANIFEST
runner = CliRunner()


@pytest.fixture(scope="module")
def done(tmp_path_factory) -> Path:
    """One tiny finished run (copied by the tests that change it)."""
    out = tmp_path_factory.mktemp("hardening") / "done"
    riskplan.train(riskplan.compose(TINY), out)
    return out


def invoke(*args: str, code: int):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == code, f"exit {result.exit_code}: {result.output}{result.exception!r}"
    assert "Traceback" not in result.output
    return result


def one_error_line(result) -> str:
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    return lines[0]


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Every entry below root: file contents (None for a directory)."""
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None) for p in sorted(root.rglob("*"))}


def bad_files(root: Path) -> list[str]:
    """Temp files and empty files below root (an interrupted or failed write would leave them); a writers' lock
    is empty where its pid could not be written, which is no half-written output."""
    return [
        str(p)
        for p in root.rglob("*")
        if p.is_file() and p.name != LOCK and (p.name.endswith(".tmp") or p.stat().st_size == 0)
    ]


# ------------------------------------------------------------------------------------------------ broken configs
BROKEN = {  # run name -> (config text or a function of the good text, what the reason says)
    "invalid_yaml": ("seed: [0\n", "is not valid YAML"),
    "a_list": ("- seed\n- 0\n", "holds a list, not a mapping of config keys"),
    "a_string": ("just words\n", "holds a string, not a mapping"),
    "unknown_key": (
        lambda t: t.replace("  measure: cvar", "  measur: cvar"),
        "config fails the schema: key 'risk.measur': unknown key",
    ),
    "wrong_type": (
        lambda t: t.replace("  beta: 0.1", "  beta: abc"),
        "config fails the schema: key 'risk.beta': got 'abc'; expected a number",
    ),
    "out_of_range": (lambda t: t.replace("  beta: 0.1", "  beta: 7"), "config fails the schema: risk.beta: got 7"),
    "env_unset": (
        lambda t: t.replace("  beta: 0.1", "  beta: ${oc.env:RISKPLAN_TEST_SURELY_UNSET}"),
        "cannot be resolved at risk.beta (the environment variable RISKPLAN_TEST_SURELY_UNSET is not set)",
    ),
    "missing_key": (
        lambda t: t.replace("  beta: 0.1", "  beta: ${risk.nowhere}"),
        "cannot be resolved at risk.beta (Interpolation key 'risk.nowhere' not found)",
    ),
    "self_reference": (
        lambda t: t.replace("seed: 0", "seed: ${seed}", 1),
        "cannot be resolved at seed (Recursive interpolation detected)",
    ),
}


@pytest.mark.slow  # renders reports
def test_runs_with_broken_configs_are_skipped_with_the_reason(done, tmp_path, monkeypatch):
    monkeypatch.delenv("RISKPLAN_TEST_SURELY_UNSET", raising=False)
    mixed = tmp_path / "mixed"
    shutil.copytree(done, mixed / "good")
    good = (done / ".hydra" / "config.yaml").read_text()
    assert "  beta: 0.1" in good and "  measure: cvar" in good and good.startswith("seed: 0")
    for name, (text, _) in BROKEN.items():
        shutil.copytree(done, mixed / name)
        (mixed / name / ".hydra" / "config.yaml").write_text(text(good) if callable(text) else text)
    scan = mixed / "land_broken"  # a landscape whose config is broken: listed, not fatal
    compute_landscape(riskplan.compose(TINY), scan, points=3, episodes=20)
    (scan / ".hydra" / "config.yaml").write_text("risk: ${nope}\n")

    out = tmp_path / "report"
    result = invoke("report", mixed, "--out", out, "--format", "png", code=0)
    skipped = [line for line in result.stderr.splitlines() if line.startswith("skipped ")]
    assert len(skipped) == len(BROKEN) + 1, result.stderr
    for name, (_, reason) in BROKEN.items():
        line = next(line for line in skipped if line.startswith(f"skipped {mixed / name}: "))
        assert reason in line, line
    assert any(line.startswith(f"skipped {scan}: landscape: .hydra/config.yaml: ") for line in skipped)
    runs = pd.read_csv(out / "runs.csv").set_index("path")
    assert runs.loc[str(mixed / "good"), "status"] == "used"
    assert (runs.drop(str(mixed / "good")).status == "skipped").all()
    assert "1 run(s) in 1 group(s)" in result.stdout and (out / "report.html").is_file()
    # the library says the same, naming the file
    with pytest.raises(BadInput, match=r"config\.yaml: has a value that cannot be resolved at seed"):
        load_run(mixed / "self_reference")


# ------------------------------------------------------------------------------------------------ --out ownership
def test_report_refuses_an_out_directory_holding_other_files(done, tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("months of work")
    (mine / "report.html").write_text("my own page")
    before = snapshot(tmp_path)
    line = one_error_line(invoke("report", done, "--out", mine, code=2))
    assert line.startswith(f"error: --out: {mine} holds files riskplan report did not write (")
    assert "report.html" in line and "thesis.tex" in line
    assert snapshot(tmp_path) == before

    scan = tmp_path / "scan"  # a landscape's directory is not the report's
    invoke("landscape", *TINY, *LAND, "--out", scan, code=0)
    before = snapshot(tmp_path)
    line = one_error_line(invoke("report", done, "--out", scan, code=2))
    assert line == (
        f"error: --out: {scan} holds the output of riskplan landscape; give riskplan report a directory of its own"
    )
    line = one_error_line(invoke("report", done, "--out", done, code=2))  # the run itself
    assert "holds files riskplan report did not write (.hydra/config.yaml, " in line
    assert snapshot(tmp_path) == before


@pytest.mark.slow  # renders reports
def test_report_reruns_into_its_own_output_and_drops_its_stale_files(done, tmp_path):
    out = tmp_path / "report"
    invoke("report", done, "--out", out, "--format", "png,svg", code=0)
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["kind"] == "report" and set(manifest["files"]) == {p.name for p in out.iterdir()} - {MANIFEST, LOCK}
    assert (out / "fig2_cvar.svg").is_file()

    invoke("report", done, "--out", out, "--format", "pdf", code=0)  # its own directory: accepted
    names = {p.name for p in out.iterdir()}
    assert "fig2_cvar.pdf" in names and not any(n.endswith((".png", ".svg")) for n in names)
    assert set(json.loads((out / MANIFEST).read_text())["files"]) == names - {MANIFEST, LOCK}

    (out / "notes.md").write_text("added by hand")  # a foreign file in it: refused, left alone
    before = snapshot(out)
    line = one_error_line(invoke("report", done, "--out", out, code=2))
    assert line == (
        f"error: --out: {out} holds files riskplan report did not write (notes.md); give a new or "
        f"empty directory, or remove them"
    )
    assert snapshot(out) == before
    (out / "notes.md").unlink()

    (out / MANIFEST).write_text("{not json")
    line = one_error_line(invoke("report", done, "--out", out, code=2))
    assert "holds a damaged .riskplan-manifest.json" in line

    (out / MANIFEST).unlink()  # a report written before manifests existed: refused, left as it is
    before = snapshot(out)
    line = one_error_line(invoke("report", done, "--out", out, "--format", "png", code=2))
    assert line.startswith(f"error: --out: {out} holds files riskplan report did not write ("), line
    assert snapshot(out) == before


@pytest.mark.slow  # five landscapes and a report through the CLI
def test_landscape_out_ownership(done, tmp_path):
    scan = tmp_path / "scan"
    invoke("landscape", *TINY, *LAND, "--out", scan, code=0)
    first = pd.read_parquet(scan / "landscape.parquet")
    invoke("landscape", *TINY, *LAND, "seed=3", "--out", scan, code=0)  # its own directory: re-run
    assert json.loads((scan / "summary.json").read_text())["seed"] == 3
    assert not pd.read_parquet(scan / "landscape.parquet").equals(first)

    report = tmp_path / "report"
    invoke("report", done, "--out", report, "--format", "png", code=0)
    before = snapshot(tmp_path)
    for target, expected in (
        (
            report,
            f"error: --out: {report} holds the output of riskplan report; give riskplan "
            f"landscape a directory of its own",
        ),
        (done, f"error: --out: {done} holds files riskplan landscape did not write ("),
    ):
        line = one_error_line(invoke("landscape", *TINY, *LAND, "--out", target, code=2))
        assert line.startswith(expected), line
    assert snapshot(tmp_path) == before

    (scan / "extra.txt").write_text("x")
    line = one_error_line(invoke("landscape", *TINY, *LAND, "--out", scan, code=2))
    assert line.endswith("(extra.txt); give a new or empty directory, or remove them")
    (scan / "extra.txt").unlink()
    (scan / MANIFEST).unlink()  # a landscape written before manifests existed: refused, left as it is
    before = snapshot(scan)
    line = one_error_line(invoke("landscape", *TINY, *LAND, "--out", scan, code=2))
    assert line.startswith(f"error: --out: {scan} holds files riskplan landscape did not write ("), line
    assert snapshot(scan) == before


@pytest.mark.parametrize(
    "where, expected",
    [
        (
            "/proc/riskplan_report",
            "error: --out: /proc/riskplan_report is under /proc, a kernel filesystem; give a directory on a disk",
        ),
        ("/", "error: --out: / is the filesystem root; give a directory of its own, e.g. outputs/runs/mine"),
        ("", "error: --out: got ''; give a directory path"),
        ("FILE", "error: --out: FILE is a file; expected a directory"),
    ],
)
@pytest.mark.parametrize("command", ["report", "landscape"])
def test_out_that_cannot_be_an_output_directory(done, tmp_path, monkeypatch, where, expected, command):
    monkeypatch.chdir(tmp_path)
    Path("FILE").write_text("a file")
    before = snapshot(tmp_path)
    args = ["report", done, "--format", "png"] if command == "report" else ["landscape", *TINY, *LAND]
    assert one_error_line(invoke(*args, "--out", where, code=2)) == expected
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------------ real mounts
def _root_mount(*args: str) -> None:
    if os.geteuid() != 0:
        pytest.skip("needs root to mount (tmpfs, read-only bind mounts); chmod means nothing to root")
    result = subprocess.run(["mount", *args], capture_output=True, text=True)
    if result.returncode != 0:
        pytest.skip(f"mount {' '.join(args)} failed: {result.stderr.strip()}")


@contextlib.contextmanager
def tmpfs(path: Path, size: str):
    path.mkdir(parents=True, exist_ok=True)
    _root_mount("-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path))
    try:
        yield path
    finally:
        subprocess.run(["umount", str(path)], check=False)


@contextlib.contextmanager
def read_only(source: Path, target: Path):
    target.mkdir(parents=True, exist_ok=True)
    _root_mount("--bind", str(source), str(target))
    try:
        result = subprocess.run(["mount", "-o", "remount,bind,ro", str(target)], capture_output=True, text=True)
        if result.returncode != 0:
            pytest.skip(f"remount read-only failed: {result.stderr.strip()}")
        yield target
    finally:
        subprocess.run(["umount", str(target)], check=False)


def fill(disk: Path) -> None:
    """Write a file until the filesystem is full."""
    with open(disk / "filler", "wb") as handle:
        with contextlib.suppress(OSError):
            while True:
                handle.write(b"\0" * 65536)
                handle.flush()


@pytest.mark.slow  # renders reports and landscapes on a full disk
def test_full_disk_leaves_the_previous_report_and_landscape_whole(done, tmp_path):
    with tmpfs(tmp_path / "disk", "2m") as disk:
        report, scan = disk / "report", disk / "scan"
        invoke("report", done, "--out", report, "--format", "png", code=0)
        invoke("landscape", *TINY, *LAND, "--out", scan, code=0)
        before = {report: snapshot(report), scan: snapshot(scan)}
        fill(disk)
        for args, target in ((["report", done, "--format", "png"], report), (["landscape", *TINY, *LAND], scan)):
            line = one_error_line(invoke(*args, "--out", target, code=1))
            assert line.startswith(f"error: {target}/") and "could not be written (No space left on device)" in line
            assert snapshot(target) == before[target], "a previous file was changed"
        for args, target in (
            (["report", done, "--format", "png"], disk / "new_report"),
            (["landscape", *TINY, *LAND], disk / "new_land"),
        ):
            line = one_error_line(invoke(*args, "--out", target, code=1))
            assert "No space left on device" in line
            assert not target.exists() or not any(target.iterdir())
        assert [p for p in bad_files(disk) if Path(p).name != "filler"] == []
        assert json.loads((scan / "status.json").read_text())["status"] == "done"


@pytest.mark.slow  # renders reports
def test_read_only_targets_are_one_line_and_nothing_is_written(done, tmp_path):
    source = tmp_path / "source"
    shutil.copytree(done, source / "run")
    invoke("report", source / "run", "--format", "png", code=0)  # source/run/report, the default
    with read_only(source, tmp_path / "ro") as ro:
        before = snapshot(ro)
        cases = [
            (
                ["report", ro / "run", "--format", "png"],
                f"error: --out: {ro}/run/report is on a read-only filesystem; give a directory you can write",
            ),
            (
                ["report", ro / "run", "--out", ro / "elsewhere"],
                f"error: --out: {ro}/elsewhere is on a read-only filesystem; give a directory you can write",
            ),
            (
                ["landscape", *TINY, *LAND, "--out", ro / "scan"],
                f"error: --out: {ro}/scan is on a read-only filesystem; give a directory you can write",
            ),
        ]
        for args, expected in cases:
            assert one_error_line(invoke(*args, code=2)) == expected
        assert snapshot(ro) == before


# ------------------------------------------------------------------------------------------------ landscape limits
@pytest.mark.slow  # seven landscape commands through the CLI
def test_landscape_grid_is_bounded_by_memory_and_time_before_it_runs(tmp_path, monkeypatch):
    monkeypatch.delenv("RISKPLAN_MEMORY_GB", raising=False)
    monkeypatch.delenv("RISKPLAN_MAX_HOURS", raising=False)
    out = tmp_path / "scan"
    line = one_error_line(invoke("landscape", "--points", "100000", "--out", out, code=2))
    assert line.startswith("error: --points: a 100000x100000 grid x 4000 episodes needs about ")
    assert line.endswith("; lower it, or raise the limit with RISKPLAN_MEMORY_GB=<GB>")
    line = one_error_line(invoke("landscape", "--points", "2", "--episodes", "2000000000", "--out", out, code=2))
    assert line.startswith("error: --episodes: a 2x2 grid x 2000000000 episodes needs about ")
    line = one_error_line(invoke("landscape", "--points", "1000", "--episodes", "100000", "--out", out, code=2))
    assert line.startswith("error: --points/--episodes: a 1000x1000 grid x 100000 episodes would take about ")
    assert line.endswith("more than the 24.0 h allowed; lower it, or raise the limit with RISKPLAN_MAX_HOURS=<hours>")
    monkeypatch.setenv("RISKPLAN_MAX_HOURS", "1e-9")  # the limit is the environment's
    line = one_error_line(invoke("landscape", *TINY, *LAND, "--out", out, code=2))
    assert "RISKPLAN_MAX_HOURS" in line
    monkeypatch.delenv("RISKPLAN_MAX_HOURS")
    monkeypatch.setenv("RISKPLAN_MEMORY_GB", "0.000001")
    line = one_error_line(invoke("landscape", *TINY, *LAND, "--out", out, code=2))
    assert "more than the 1 KB allowed (RISKPLAN_MEMORY_GB)" in line
    for args, expected in (
        (["--points", "1"], "error: --points: got 1; expected at least 2 grid points per axis"),
        (["--episodes", "0"], "error: --episodes: got 0; expected at least 1 episode per grid point"),
    ):
        assert one_error_line(invoke("landscape", *args, "--out", out, code=2)) == expected
    assert not out.exists()


def test_landscape_summary_is_strict_json(tmp_path, monkeypatch):
    from riskplan.experiments import landscape as L

    real = L.evaluate_grid

    def without_cvar(*args, **kwargs):
        table = real(*args, **kwargs)
        table["cvar"] = np.nan  # nothing finite to maximise
        table.loc[0, "value_at_risk"] = np.inf
        return table

    monkeypatch.setattr(L, "evaluate_grid", without_cvar)
    monkeypatch.setattr(L.time, "perf_counter", lambda: 0.0)  # no time passes: episodes/s undefined
    out = tmp_path / "scan"
    result = invoke("landscape", *TINY, *LAND, "--out", out, code=0)
    assert "max CVaR_0.1 n/a (no finite value on the grid)" in result.stdout
    text = (out / "summary.json").read_text()
    summary = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert summary["best"]["cvar"] == {"theta": None, "value": None} and summary["episodes_per_s"] is None
    assert summary["best"]["value_at_risk"]["value"] is not None  # the infinite point is not the maximum
    from riskplan.experiments.landscape import finite_json

    assert finite_json({"a": [float("nan"), float("-inf"), 1.5]}) == json.dumps({"a": [None, None, 1.5]}, indent=2)


# ------------------------------------------------------------------------------------------------ missing values
@pytest.mark.slow  # renders reports
def test_missing_values_are_empty_cells_or_na_never_nan_or_inf(done, tmp_path):
    inputs = tmp_path / "inputs"
    shutil.copytree(done, inputs / "run")
    flat = inputs / "flat"  # a landscape on the run's world whose objective is 0 everywhere: the gap in % is 0/0
    compute_landscape(riskplan.compose(TINY), flat, points=3, episodes=20)
    table = pd.read_parquet(flat / "landscape.parquet")
    table[["mean", "cvar", "value_at_risk"]] = 0.0
    table.to_parquet(flat / "landscape.parquet")
    other = inputs / "other"  # a landscape of another world: no group on it, so its group cells are missing
    compute_landscape(riskplan.compose([*TINY, "world.horizon=30"]), other, points=3, episodes=20)

    out = tmp_path / "report"
    invoke("report", inputs, "--out", out, "--format", "png", code=0)
    for name in ("report.csv", "runs.csv", "landscape.csv"):
        text = (out / name).read_text().lower()
        assert "nan" not in text and "inf" not in text, name
    scan = pd.read_csv(out / "landscape.csv").set_index("landscape")
    assert pd.isna(scan.loc[str(flat), "gap_percent"]) and scan.loc[str(flat), "gap_to_optimum"] == 0
    assert pd.isna(scan.loc[str(other), "group"])
    html = (out / "report.html").read_text()
    cells = [c.lower() for c in pd.Series(html.split("<td")).str.extract(r"^[^>]*>(.*?)</td>")[0].dropna()]
    assert not any(c in ("nan", "inf", "-inf", "none") or "nan" in c.split() for c in cells)
    assert "<td>n/a</td>" in html


# ------------------------------------------------------------------------------------------------ two writers
@pytest.mark.slow  # renders reports
def test_a_report_written_into_its_directory_by_another_meanwhile_is_refused_not_mixed(done, tmp_path):
    """Two reports into one new --out: each had claimed the directory empty, then both wrote, leaving one's PDFs
    beside the other's PNGs under a manifest of one. The second to write now finds the directory changed, under the
    writers' lock, and stops in one line; the first's report stays whole."""
    from riskplan.experiments.reporting import write_report

    out = tmp_path / "report"
    other = {}

    def meanwhile(phase, done_, total):
        if phase == "making figures" and not other:  # after this report's claim, before it writes
            other["page"] = write_report([done], out, ["pdf"]).page

    with pytest.raises(BadInput) as refused:
        write_report([done], out, ["png"], progress=meanwhile)
    assert str(refused.value) == (
        f"{out}: was written by another riskplan report while this one ran; run the command again (it replaces that "
        f"output) or give another directory"
    )
    listed = set(json.loads((out / ".riskplan-manifest.json").read_text())["files"])
    assert listed == {p.name for p in out.iterdir()} - {".riskplan-manifest.json", LOCK}
    assert not any(name.endswith(".png") for name in listed) and "fig2_cvar.pdf" in listed


@pytest.mark.slow  # about a second: a first report is started and held mid-way
def test_a_second_report_into_a_directory_a_report_is_writing_is_refused_at_once(done, tmp_path):
    """Two reports into one --out: each had claimed the directory empty, then both wrote, leaving one's PDFs beside
    the other's PNGs under a manifest of one. A report into a directory that exists holds the writers' lock from its
    start, so the second is refused in one line before it reads a run, and the first's report is whole."""
    from riskplan.experiments.reporting import write_report

    out = tmp_path / "report"
    out.mkdir()
    other = {}

    def meanwhile(phase, done_, total):
        if phase == "loading runs" and not other:  # after this report's claim, before it reads a run
            with pytest.raises(BadInput) as refused:
                write_report([done], out, ["pdf"])
            other["line"] = str(refused.value)

    write_report([done], out, ["png"], progress=meanwhile)
    assert other["line"] == (
        f"{out}: is in use by another riskplan process (pid {os.getpid()}); one process writes a report directory at "
        f"a time: wait for it to end or stop it"
    )
    listed = set(json.loads((out / ".riskplan-manifest.json").read_text())["files"])
    assert listed == {p.name for p in out.iterdir()} - {".riskplan-manifest.json", LOCK}
    assert not any(name.endswith(".pdf") for name in listed) and "fig2_cvar.png" in listed


def test_a_report_into_a_directory_another_process_writes_is_refused_naming_it(done, tmp_path):
    out = tmp_path / "report"
    out.mkdir()
    with held_by_another_process(out) as pid:
        line = one_error_line(invoke("report", done, "--out", out, "--format", "png", code=2))
        assert line == (
            f"error: {out}: is in use by another riskplan process (pid {pid}); one process writes a report "
            f"directory at a time: wait for it to end or stop it"
        )
        assert sorted(p.name for p in out.iterdir()) == [LOCK]


def test_a_run_that_still_trains_is_said_to_be_running_not_truncated(done, tmp_path):
    """Its log is cut short because the run has not finished: the report says so, naming the process."""
    from riskplan.experiments.reporting.collect import collect

    run = tmp_path / "run"
    shutil.copytree(done, run)
    log = (run / "run.mcap").read_bytes()
    (run / "run.mcap").write_bytes(log[: len(log) // 2])
    (run / "summary.json").unlink()
    with held_by_another_process(run) as pid:
        (broken,) = collect([run]).broken
        assert broken.reason.startswith(f"is still running (pid {pid}): truncated after iteration ")
    (broken,) = collect([run]).broken  # the process gone: a log cut short, as a kill leaves it
    assert broken.reason.startswith("truncated after iteration ")
