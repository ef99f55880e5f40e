"""A risk measure of a user's own, end to end: a power distortion written as a separate installed package of a few
lines (tests/measure_cases.py) trains with `risk.measure=power risk.params.gamma=0.5`, its first gradient step is
its estimator on the run's own episodes and matches exact enumeration, and the run goes through the summary, a
sweep, the report and export. Bad parameters and a name no package provides are one line, exit 2, nothing
written."""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest
from measure_cases import install_package
from support import WORLD_3X3, exact_distribution, rollouts, run_cli
from typer.testing import CliRunner

from riskplan import load_run
from riskplan.cli import app
from riskplan.engine.measures import registry
from riskplan.risk import risk_spec
from riskplan.run.build import build_setup

POWER = ["risk.measure=power", "risk.params.gamma=0.5"]
SAMPLES = 200_000  # the first step's episodes: 16 batches of 12,500 give its standard error
QUICK = ["train.eval_episodes=1000", "train.bootstrap=40", "train.paths=1"]
runner = CliRunner()


@pytest.fixture
def package(tmp_path, monkeypatch):
    """The installed package (on this process's sys.path, and in the environment of riskplan's subprocesses), and
    a config folder with the 3x3 world whose every path is enumerated, as experiment=tiny."""
    site = install_package(tmp_path)
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setattr(registry, "_FROM_PACKAGES", {})
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])))
    experiment = tmp_path / "conf" / "experiment"
    experiment.mkdir(parents=True)
    tiny = {"experiment": "tiny", **WORLD_3X3}
    (experiment / "tiny.yaml").write_text("# @package _global_\n" + json.dumps(tiny) + "\n")
    yield tmp_path
    sys.modules.pop("riskplan_power", None)


def exact_objective(setup, theta, measure, params) -> float:
    dist = sorted(exact_distribution(setup, theta).items())
    return measure.of_distribution(np.array([z for z, _ in dist]), np.array([p for _, p in dist]), params)


def test_a_power_distortion_from_a_package_trains_and_its_first_step_matches_exact_enumeration(package):
    out = package / "run"
    args = ["-cd", str(package / "conf"), "experiment=tiny", *POWER, "train.iterations=1", f"train.samples={SAMPLES}"]
    done = run_cli(["train", *args, *QUICK, f"hydra.run.dir={out}"], package)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "risk=power robots=1" in done.stdout and "| eval 1000 episodes: power " in done.stdout
    run = load_run(out)
    assert run.summary["risk"] == "power" and run.summary["objective"]["measure"] == "power"
    assert run.metrics.objective.notna().all() and run.metrics.beta_l.isna().all()  # a measure without a CVaR level

    setup = build_setup(run.config)
    measure, params = risk_spec(setup.params.risk)
    theta0 = np.asarray(setup.theta0, dtype=float)
    step = (np.asarray(run.summary["theta_final"]) - theta0) / setup.params.train.step_size.initial
    episodes = rollouts(setup, theta0, SAMPLES, seed=setup.params.seed)  # iteration 0's episodes, from its stream
    np.testing.assert_allclose(step, measure.gradient(episodes.total_reward, episodes.score, params), rtol=1e-9)

    h = 1e-5
    truth = np.array(
        [
            (exact_objective(setup, theta0 + e, measure, params) - exact_objective(setup, theta0 - e, measure, params))
            / (2 * h)
            for e in np.eye(theta0.size) * h
        ]
    )
    z = episodes.total_reward.reshape(16, -1)
    s = episodes.score.reshape(16, z.shape[1], -1)
    se = np.array([measure.gradient(z[b], s[b], params) for b in range(16)]).std(axis=0, ddof=1) / 4.0
    assert np.linalg.norm(truth) > 0.1 and np.all(se < 0.05 * np.linalg.norm(truth))  # not vacuous
    np.testing.assert_array_less(np.abs(step - truth), 4 * se)


def test_a_packages_measure_goes_through_a_sweep_the_report_and_export(package, monkeypatch):
    sweep = package / "sweep"
    overrides = ["risk.measure=power", "risk.params.gamma=0.5,0.8", "train.iterations=2", "train.samples=300", *QUICK]
    done = run_cli(["sweep", *overrides, f"hydra.sweep.dir={sweep}"], package)  # its jobs find the package too
    assert done.returncode == 0, done.stderr[-2000:]
    runs = sorted(p.parent for p in sweep.rglob("summary.json"))
    assert [json.loads((r / "summary.json").read_text())["objective"]["measure"] for r in runs] == ["power"] * 2
    # the report and export in this process, which finds the package as a new one does (the registry emptied)
    monkeypatch.chdir(package)
    done = runner.invoke(app, ["report", str(sweep)])
    assert done.exit_code == 0, done.output[-2000:]
    page = (sweep / "report" / "report.html").read_text()
    assert "power (gamma=0.5)" in page and "power (gamma=0.8)" in page
    done = runner.invoke(app, ["export", str(sweep), "--to", "tensorboard", "--uri", str(package / "tb")])
    assert done.exit_code == 0, done.output[-2000:]
    assert "2 exported" in done.stdout


@pytest.mark.parametrize(
    ("overrides", "line"),
    [
        (["risk.measure=powr"], "error: risk.measure: got 'powr'; expected a built-in measure"),
        (["risk.measure=power"], "error: risk.params.gamma: missing; measure 'power' needs 0 < gamma < 1"),
        ([*POWER[:1], "risk.params.gamma=1.5"], "error: risk.params.gamma: got 1.5; expected 0 < gamma < 1"),
        ([*POWER[:1], "risk.params.gamma=abc"], "error: key 'risk.params.gamma': got 'abc'; expected a number"),
        ([*POWER, "risk.params.delta=1"], "error: risk.params.delta: unknown parameter of measure 'power'"),
    ],
)
def test_bad_input_for_a_packages_measure_is_one_line_and_exit_2_with_nothing_written(
    package, monkeypatch, overrides, line
):
    # in this process (the package on its sys.path): the command's own exit code and stderr, without a start-up each
    monkeypatch.chdir(package)
    out = package / "run"
    done = runner.invoke(app, ["train", *overrides, "train.iterations=1", f"hydra.run.dir={out}"])
    assert done.exit_code == 2, done.output
    assert done.stderr.strip().startswith(line) and len(done.stderr.strip().splitlines()) == 1
    assert not out.exists()
