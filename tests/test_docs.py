"""The documentation: a README that fits, a docs site that builds strictly, tables generated from measured data,
and a wheel that ships the configs and its type marker."""

from __future__ import annotations

import itertools
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_the_readme_fits_and_gives_the_two_commands():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    assert "riskplan reproduce" in text
    ci = (ROOT / ".ci" / "run").read_text()
    install = re.search(r"pip install [^\n]*-e '\.\[test\]'", ci)
    assert install and "pip install -e '.[test]'" in text  # CI installs as the README says
    assert "pytest" in text and re.search(r"^pytest\b", ci, re.M)  # and runs the README's test command


# What a clone of the repository does not have: the sibling folder the project was written beside, and the
# contract file that lived there (its content is docs/contract.md now). Written as patterns, so that this file
# does not name them itself.
OUTSIDE = re.compile(r"(?:\.\.|/work)/shared\b|\bdesign\.md\b")


def tracked_text_files() -> list[Path]:
    """The repository's tracked files that are text (no NUL byte in their first 8 KiB), symlinks left out."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout (an sdist): the tracked files are unknown")
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    files = []
    for name in listed.decode().split("\0"):
        path = ROOT / name
        if name and path.is_file() and not path.is_symlink() and b"\0" not in path.read_bytes()[:8192]:
            files.append(path)
    return files


def test_no_tracked_file_points_outside_the_repository():
    """The repository stands alone: no file refers to the folder beside it or to a contract file kept there (the
    public contract is docs/contract.md, and the paper is cited by its reference in CITATION.cff)."""
    files = tracked_text_files()
    assert any(f.name == "contract.md" for f in files)  # the scan sees the docs
    found = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in files
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert not found, "lines that point outside the repository:\n" + "\n".join(found)


@pytest.mark.slow  # docs/generate.py --check in an interpreter of its own (near a second)
def test_the_generated_tables_match_their_data():
    done = subprocess.run(
        [sys.executable, str(ROOT / "docs" / "generate.py"), "--check"], cwd=ROOT, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stdout + done.stderr


def load_generate(data: Path):
    """docs/generate.py as a module that reads its data from `data`."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("docs_generate", ROOT / "docs" / "generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.DATA = data
    return module


GENERATE = load_generate(ROOT / "docs" / "data")
QUICK = [name for name, spec in GENERATE.TRANSCRIPTS.items() if not spec.slow]


@pytest.mark.parametrize("name", QUICK)
def test_the_bad_input_lines_a_page_shows_are_what_the_commands_print(name):
    """The page's transcript (docs/data/outputs/NAME.txt) is what its commands print now: a message that changes
    changes the page, through python docs/generate.py --collect-outputs NAME."""
    shown = (GENERATE.OUTPUTS / f"{name}.txt").read_text(encoding="utf-8")
    assert shown.startswith("$ riskplan ") and "\nerror: " in shown
    assert GENERATE.comparable(GENERATE.transcript(name)) == GENERATE.comparable(shown)


@pytest.mark.slow  # a run of the paper's world with the example measure, a batched sweep of 16: 10-20 s each
@pytest.mark.parametrize("name", [name for name in GENERATE.TRANSCRIPTS if name not in QUICK])
def test_the_runs_a_page_shows_print_what_it_shows(name):
    shown = (GENERATE.OUTPUTS / f"{name}.txt").read_text(encoding="utf-8")
    if name == "extending_train":
        assert "power 1910.6 [1896.2, 1927.8]" in shown  # the figures docs/extending.md once had wrong
    assert GENERATE.comparable(GENERATE.transcript(name)) == GENERATE.comparable(shown)


def test_every_transcript_is_shown_by_a_page_and_pages_show_no_other_riskplan_output():
    """Each docs/data/outputs/NAME.txt is included by a page, no page types a command's output by hand (`$ riskplan
    ...` followed by what it printed) where it could include one, and the README quotes transcripts verbatim."""
    pages = {page.name: page.read_text(encoding="utf-8") for page in (ROOT / "docs").glob("*.md")}
    for name in GENERATE.TRANSCRIPTS:
        assert any(f'--8<-- "docs/data/outputs/{name}.txt"' in text for text in pages.values()), name
    typed = [
        f"{page}: {line}"
        for page, text in pages.items()
        for line, after in itertools.pairwise(text.splitlines())
        if line.startswith("$ riskplan ") and after.startswith("error: ")
    ]
    assert typed == []
    # GitHub shows the README as it is, with no includes: what it shows must be a transcript's lines as they are
    readme = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    collected = "".join(path.read_text(encoding="utf-8") for path in GENERATE.OUTPUTS.glob("*.txt"))
    quoted = [(line, after) for line, after in itertools.pairwise(readme) if line.startswith("$ riskplan ")]
    assert quoted and all(f"{line}\n{after}\n" in collected for line, after in quoted), quoted


def test_the_ray_tables_show_bench_ray_backend_json(tmp_path):
    """Known bench/ray_backend.py JSON files give known rows, with the load average as each measurement ended."""
    import json

    ray = tmp_path / "ray"
    ray.mkdir()
    where = {"when": "2026-01-02 03:04 UTC", "host": "2 cores", "load": "9.00 8.00 7.00", "load_at": "ended"}
    names = ("backends", "scaling", "cluster", "target")
    (tmp_path / "meta.json").write_text(json.dumps({"ray": {name: where for name in names}}))
    row = {"seed": 0, "cvar_simulated": 1444.0, "cvar_ray": 1443.0, "cvar_ray_low": 1441.0, "cvar_ray_high": 1445.0}
    row |= {"relative": -0.0005, "train_s_simulated": 2.0, "train_s_ray": 9.0, "elapsed_s_ray": 30.0}
    backends = {"rows": [row | {"max_staleness": 2.0}], "mean_simulated": 1444.0, "mean_ray": 1443.0}
    (ray / "backends.json").write_text(json.dumps(backends))
    scaling = [
        {"robots": n, "cores": 2, "iterations_per_s_per_robot": rate, "compute_only_iterations_per_s": rate}
        | {"waiting_fraction": wait, "episodes_per_s": episodes, "startup_s": 1.0}
        for n, rate, wait, episodes in ((1, 100.0, 0.0, 2e5), (2, 80.0, 0.1, 3.2e5))
    ]
    (ray / "scaling.json").write_text(json.dumps({"rows": scaling}))
    cluster = {"robots": 16, "nodes": 2, "robots_per_node": {"a": 8, "b": 8}, "consensus_error_early_max": 19.7}
    cluster |= {"consensus_error_late_mean": 2.5, "max_staleness_all": 2.0, "max_staleness_slow": 2.0}
    cluster |= {"mean_staleness_fast": 0.8, "mean_staleness_slow": -1.1, "fast_waiting_fraction": 0.7}
    cluster |= {"slow_waiting_fraction": 0.3, "train_s": 1.5, "startup_s": 19.0, "cvar": 1440.7}
    (ray / "cluster.json").write_text(json.dumps(cluster))
    target = [{"robots": 1, "target": 1380.0, "seconds": 0.5, "iteration": 12, "train_s": 0.2, "final_cvar": 1436.4}]
    target += [{"robots": 4, "target": 1380.0, "seconds": None, "iteration": None, "train_s": 1.7, "final_cvar": 0.0}]
    (ray / "target.json").write_text(json.dumps({"rows": target}))
    generate = load_generate(tmp_path)
    measured = "measured 2026-01-02 03:04 UTC; 2 cores; load average 9.00 8.00 7.00 as it ended"

    text = generate.gen_ray_backends()
    assert "| 0 | 1444.0 | 1443.0 [1441.0, 1445.0] | −0.05% | 2.0 / 9.0 | 30.0 | 2 |" in text
    assert f"simulated 1444.0, ray 1443.0 (−0.069%); {measured}." in text
    assert "| ray's CVaR_0.1 within 2% of the simulated backend's on every seed | 0.05% | yes |" in text
    text = generate.gen_ray_scaling()
    assert "| 2,000 | 1 | 0.5 | 100 | 100% | 100 | 0% | 2e+05 | 1.00 | 1.0 |" in text
    assert "| 2,000 | 2 | 1.0 | 80 | 80% | 80 | 10% | 3.2e+05 | 1.60 | 1.0 |" in text
    assert f"- W = 2,000: {measured}." in text and "20,000 |" not in text  # the missing files: no rows
    text = generate.gen_ray_cluster()
    assert "| 16 | 2 (8 + 8) | 19.70 → 2.50 | 2 / 2 | 0.80 / −1.10 | 70% / 30% | 1.5 | 19.0 | 1440.7 |" in text
    text = generate.gen_ray_target()
    assert "| 1 | 12 | 0.5 | 0.2 | 1436.4 |" in text and "| 4 | not reached | not reached | 1.7 | 0.0 |" in text
    assert "training CVaR_0.1 ≥ 1380 |" in text and text.endswith(f"{measured}.\n")


def test_collecting_the_ray_files_notes_their_load_average(tmp_path):
    """--ray DIR copies bench/ray_backend.py's files; the load average is the JSON's (as it ended) or FILE.load's."""
    import json

    source, data = tmp_path / "bench-ray", tmp_path / "data"
    source.mkdir(), data.mkdir()
    (source / "backends.json").write_text(json.dumps({"rows": [], "load": ["8.99", "8.80", "6.16"]}))
    (source / "target.json").write_text(json.dumps({"rows": []}))
    (source / "target.json.load").write_text("unknown (measured under load from parallel test runs)\n")
    generate = load_generate(data)
    meta = {}
    generate.collect_ray(source, meta)
    assert sorted(p.name for p in (data / "ray").iterdir()) == ["backends.json", "target.json"]
    assert json.loads((data / "ray" / "backends.json").read_text())["load"] == ["8.99", "8.80", "6.16"]
    assert meta["ray"]["backends"]["load"] == "8.99 8.80 6.16" and meta["ray"]["backends"]["load_at"] == "ended"
    assert meta["ray"]["target"]["load"].startswith("unknown") and "load_at" not in meta["ray"]["target"]
    with pytest.raises(SystemExit, match="none of"):
        generate.collect_ray(tmp_path / "empty", meta)


@pytest.mark.slow
def test_the_docs_site_builds_strictly(tmp_path):
    mkdocs = Path(sys.executable).with_name("mkdocs")
    if not mkdocs.is_file() and shutil.which("mkdocs") is None:
        pytest.skip("mkdocs is not installed (pip install -e '.[docs]' or '.[test]' installs it)")
    # not -q: quiet mode logs no warnings, so --strict would have none to count
    command = [str(mkdocs) if mkdocs.is_file() else "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    page = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "objective_gradient" in page  # mkdocstrings rendered the Python API


@pytest.mark.slow
def test_the_wheel_ships_the_configs_and_py_typed(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(ROOT)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    if done.returncode != 0 and "No matching distribution" in done.stderr:
        pytest.skip("the build backend (hatchling) cannot be fetched here")
    assert done.returncode == 0, done.stderr
    names = zipfile.ZipFile(next(tmp_path.glob("riskplan-*.whl"))).namelist()
    assert "riskplan/py.typed" in names
    assert {"riskplan/conf/config.yaml", "riskplan/conf/risk/wang.yaml"} <= set(names)
