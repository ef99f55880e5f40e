"""Shared fixtures and the quick tier.

The tests mirror the package (tests/engine, tests/engine/team, tests/config, tests/run, tests/util, tests/experiments,
tests/commands); end-to-end runs are in tests/e2e. `pytest -m "not slow"` is the quick tier (on every core through
pytest-xdist, see pytest_cmdline_main): everything under tests/e2e and tests/clusters is marked slow here, and the
other slow tests carry the mark themselves. Shared helpers and the run configs (TINY, FAST) are in tests/support.py.
"""

from __future__ import annotations

import atexit
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path

import pytest
import support
from support import FAST, TINY, team_conf  # noqa: F401  (`from conftest import FAST, team_conf` keeps working)

try:
    from hypothesis import settings
except ImportError:  # tests/ray_check.sh's environment has no hypothesis (nor a property test)
    pass
else:  # the property tests: reproducible examples, no deadline on a loaded machine
    settings.register_profile("riskplan", max_examples=100, deadline=None, derandomize=True)
    settings.load_profile("riskplan")

TESTS = Path(__file__).resolve().parent
# pytest caches each test module as it rewrote its asserts, unless Python may not write bytecode: where the
# environment says so (PYTHONDONTWRITEBYTECODE), every run parsed and rewrote all of them again, 4-5 s of each
# worker's start. Collection caches them (in the gitignored __pycache__ folders), and the tests then run as the
# environment asked.
DONT_WRITE_BYTECODE = sys.dont_write_bytecode
sys.dont_write_bytecode = False
# Runs record their cost for the time estimates (riskplan.run.cost): the tests' runs go to a folder of their own,
# not into the user's cache, and a test that checks the calibration sets its own. The process that made the folder
# (the xdist workers inherit its variable) removes it as it exits.
if "RISKPLAN_CACHE_DIR" not in os.environ:
    os.environ["RISKPLAN_CACHE_DIR"] = tempfile.mkdtemp(prefix="riskplan-tests-cache-")
    atexit.register(shutil.rmtree, os.environ["RISKPLAN_CACHE_DIR"], ignore_errors=True)
# The local Ray instances of the team.backend=ray tests keep their session folders (logs, sockets) in Ray's temp
# dir, /tmp/ray unless RAY_TMPDIR (or, on Linux, TMPDIR) says otherwise: 50 of them were left there by every run of
# the suite. They go to a folder of the tests' own, removed the same way (its name short: Ray's socket paths must
# stay under 107 bytes). A TMPDIR given is left to Ray (tests/ray_check.sh gives one and removes it).
if "RAY_TMPDIR" not in os.environ and "TMPDIR" not in os.environ:
    os.environ["RAY_TMPDIR"] = tempfile.mkdtemp(prefix="rp-ray-")
    atexit.register(shutil.rmtree, os.environ["RAY_TMPDIR"], ignore_errors=True)
SLOW_FOLDERS = ("e2e", "clusters")  # whole runs through the CLI, and real clusters


# Tests that must share one xdist worker: a real cluster is started once per package (two workers would both start
# one), and a module's session fixtures of its own (real runs and a report) are built once, not once per worker.
SHARED_WORKER = {"clusters": "clusters", "test_report_contents.py": "report_contents"}


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    """Both tiers run on every core (pytest-xdist, in the test extra). The full suite keeps the tests of
    SHARED_WORKER's groups each on one worker (--dist loadgroup); the quick tier holds none of them and lets an idle
    worker take tests queued for the other (--dist worksteal): 54 s instead of 58-59 s on 2 cores, for 1,927 small
    tests whose durations vary. An explicit -n or --dist (or -p no:xdist) wins."""
    if (
        config.pluginmanager.hasplugin("xdist")
        and getattr(config.option, "numprocesses", None) is None
        and "PYTEST_XDIST_WORKER" not in os.environ
        and (os.cpu_count() or 1) > 1
    ):
        config.option.numprocesses = os.cpu_count()
        if config.option.dist == "no":
            quick = (config.option.markexpr or "").replace(" ", "") == "notslow"
            config.option.dist = "worksteal" if quick else "loadgroup"


def pytest_collection_finish(session):
    sys.dont_write_bytecode = DONT_WRITE_BYTECODE


def pytest_collection_modifyitems(config, items):
    """Mark every test under tests/e2e and tests/clusters slow; keep each SHARED_WORKER group on one worker."""
    for item in items:
        try:
            parts = item.path.resolve().relative_to(TESTS).parts
        except ValueError:  # a test outside tests/
            continue
        if parts[0] in SLOW_FOLDERS:
            item.add_marker(pytest.mark.slow)
        group = SHARED_WORKER.get(parts[0]) or SHARED_WORKER.get(parts[-1])
        if group and config.pluginmanager.hasplugin("xdist"):  # tests/ray_check.sh's environment has no xdist
            item.add_marker(pytest.mark.xdist_group(group))


def _handlers_kept():
    """Put SIGTERM's and SIGINT's handlers back afterwards: a `ray.init` in this process (a fixture, a cluster
    driver) makes SIGTERM call sys.exit and leaves it so after shutdown."""
    saved = {number: signal.getsignal(number) for number in (signal.SIGTERM, signal.SIGINT)}
    yield
    for number, handler in saved.items():
        signal.signal(number, handler)


# Both scopes: a module's fixtures (set up before any test's) may call ray.init too. Autouse fixtures come first
# within their scope, so these save the handlers before the fixtures of their scope run.
signal_handlers_kept_per_module = pytest.fixture(scope="module", autouse=True)(_handlers_kept)
signal_handlers_kept_per_test = pytest.fixture(autouse=True)(_handlers_kept)


@pytest.fixture
def in_tmp(tmp_path, monkeypatch) -> Path:
    """A fresh working directory (a command's default outputs/ goes there)."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def tiny_overrides() -> list[str]:
    """The fastest overrides that still make a meaningful run (support.TINY)."""
    return list(TINY)


@pytest.fixture
def fast_overrides() -> list[str]:
    """Overrides that make a run take well under a second (support.FAST)."""
    return list(FAST)


@pytest.fixture(scope="session")
def uninterrupted(tmp_path_factory):
    """uninterrupted(seed): the directory of `riskplan train` of support.CHECKPOINTED with that seed, run once a
    session (read only): the run that killed, interrupted and resumed runs and sweep jobs must equal. In one thread:
    tests/e2e/test_determinism.py compares the other thread counts and launchers with it."""
    runs: dict[int, Path] = {}

    def run(seed: int = 0) -> Path:
        if seed not in runs:
            out = tmp_path_factory.mktemp(f"uninterrupted_seed{seed}") / "run"
            result = support.train_cli(
                [*support.CHECKPOINTED, f"seed={seed}"], out, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1"
            )
            assert result.returncode == 0, result.stderr
            runs[seed] = out
        return runs[seed]

    return run
