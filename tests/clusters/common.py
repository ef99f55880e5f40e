"""What the tests of riskplan on real clusters share: waiting, the `riskplan` command, a sweep's files, and the
shell blocks of docs/clusters.md that the tests run as written.

A block of the docs is tested when the line right before its ```bash fence is `<!-- tested: KIND -->`:

    slurm         run in order, in one temporary working directory, with the SLURM test cluster's environment
                  (tests/clusters/test_slurm_sweeps.py)
    ray-local     run with a plain environment: a local Ray instance (tests/clusters/test_ray_sweeps.py)
    ray-cluster   run with the two-node Ray cluster's driver environment: RAY_ADDRESS and its token, what a user
                  on a node of the cluster has (tests/clusters/test_ray_sweeps.py)
    ray-team      team.backend=ray on a local Ray instance (tests/clusters/test_ray_team_docs.py)
    ray-team-cluster  team.backend=ray on the two-node Ray cluster, with its driver environment (the same file)

Each block runs with `bash -euo pipefail`, so every command in it must succeed. Every `riskplan sweep` prints
`sweep directory: DIR`; the tests check every such directory (all jobs done, each with its summary.json).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from support import alive  # noqa: F401  (re-exported: the cluster tests import it from here)

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs" / "clusters.md"
MARKER = re.compile(r"^<!-- tested: ([a-z-]+) -->\s*$")
KINDS = ("slurm", "ray-local", "ray-cluster", "ray-team", "ray-team-cluster")
SWEEP_DIR = re.compile(r"^sweep directory: (.+)$", re.MULTILINE)
# summary.json's numbers that a resumed job must reproduce exactly
NUMBERS = ("mean", "cvar", "value_at_risk", "cvar_0.05", "cvar_0.1", "cvar_0.2", "risky_fraction", "theta_final")


def cluster_pids(conf: Path) -> list[int]:
    """Every live process whose environment holds SLURM_CONF=conf (a SLURM test cluster's slurmstepd, jobs)."""
    marker = f"SLURM_CONF={conf}".encode()
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and int(proc.name) != os.getpid():
            try:
                if marker in (proc / "environ").read_bytes().split(b"\0"):
                    pids.append(int(proc.name))
            except OSError:
                continue
    return pids


def wait_until(condition, timeout: float, what: str, every: float = 0.2) -> None:
    """Poll `condition` until it is true; fail naming `what` after `timeout` seconds (a safety net, not a
    measurement)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(every)


def riskplan_exe() -> str:
    """The `riskplan` command of this Python's environment (else the one on PATH)."""
    found = Path(sys.executable).with_name("riskplan")
    if found.is_file():
        return str(found)
    found = shutil.which("riskplan")
    if found is None:
        pytest.skip("the riskplan command is not installed next to this Python nor on PATH")
    return found


def with_venv_on_path(env: dict[str, str]) -> dict[str, str]:
    """`env` with this Python's bin directory first on PATH, as for a user whose virtualenv is active (jobs on the
    cluster inherit it)."""
    return {**env, "PATH": os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])}


def status(job_dir: Path) -> dict:
    """The job's status.json, {} while it is missing or half written."""
    try:
        return json.loads((job_dir / "status.json").read_text())
    except (OSError, ValueError):
        return {}


def numbers(job_dir: Path) -> dict:
    """The summary.json numbers a re-run or resumed job must reproduce exactly."""
    summary = json.loads((job_dir / "summary.json").read_text())
    return {key: summary[key] for key in NUMBERS}


def sweep_dirs(output: str, cwd: Path) -> list[Path]:
    """The sweep directories that `riskplan sweep` printed, in order."""
    return [(cwd / line.strip()).resolve() for line in SWEEP_DIR.findall(output)]


def finished_jobs(sweep_dir: Path) -> dict[str, Path]:
    """{job folder name: path} of a sweep whose every job is done (summary.parquet says so and each folder holds
    its summary.json); fails otherwise."""
    import pandas as pd

    summary = pd.read_parquet(sweep_dir / "summary.parquet")
    assert len(summary) and (summary["status"] == "done").all(), summary[["job", "status", "error"]].to_string()
    jobs = {row.job: Path(row.path) for row in summary.itertuples()}
    jobs = {name: path if path.is_absolute() else sweep_dir / path.name for name, path in jobs.items()}
    for name, path in jobs.items():
        assert (path / "summary.json").is_file(), f"{name}: no summary.json in {path}"
        assert status(path).get("status") == "done", (name, status(path))
    return jobs


@dataclass
class Block:
    kind: str
    line: int  # of the ```bash fence in docs/clusters.md
    text: str

    def __str__(self) -> str:
        return f"docs/clusters.md:{self.line} ({self.kind})"


def bash_blocks(path: Path = DOCS) -> list[tuple[int, str | None, str]]:
    """Every ```bash block of the page: (line of its fence, its `tested:` kind or None, its text)."""
    lines = path.read_text().splitlines()
    blocks, index = [], 0
    while index < len(lines):
        if lines[index].strip() == "```bash":
            before = next((lines[j] for j in range(index - 1, -1, -1) if lines[j].strip()), "")
            match = MARKER.match(before.strip())
            end = next(j for j in range(index + 1, len(lines)) if lines[j].strip() == "```")
            blocks.append((index + 1, match.group(1) if match else None, "\n".join(lines[index + 1 : end]) + "\n"))
            index = end
        index += 1
    return blocks


def marked_blocks(kind: str, path: Path = DOCS) -> list[Block]:
    """The blocks marked `<!-- tested: kind -->`, in page order."""
    assert kind in KINDS, kind
    found = [Block(k, line, text) for line, k, text in bash_blocks(path) if k == kind]
    assert found, f"no block of docs/clusters.md is marked <!-- tested: {kind} -->"
    return found


def run_block(block: Block, cwd: Path, env: dict[str, str], timeout: float = 600) -> subprocess.CompletedProcess:
    """Run a block of the docs as written, with bash, in `cwd`; fail with its output unless it exits 0."""
    result = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", block.text],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert result.returncode == 0, (
        f"{block} exited {result.returncode}\n--- block\n{block.text}--- stdout\n{result.stdout[-4000:]}"
        f"\n--- stderr\n{result.stderr[-4000:]}"
    )
    return result
