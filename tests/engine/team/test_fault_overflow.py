"""A byzantine robot (team.faults) whose messages would overflow the team's numbers: refused by the config when the
value or scale alone says so (exit 2, one line naming the key, nothing written), and, whatever the cause, a team whose
healthy thetas drift too far apart for a float stops at run time with NumericalTrouble (exit 1, one line, the last
good checkpoint kept), never recording a consensus error or theta of inf. Huge but finite consensus errors are measured
without overflowing (tests/engine/team/test_convergence.py checks the rest bit for bit)."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
from support import CHECKPOINTED_TEAM, TINY, setup_of
from typer.testing import CliRunner

import riskplan.engine.step as engine_step
from riskplan import load_run
from riskplan.cli import app
from riskplan.config.typed import typed
from riskplan.config.validate import BYZANTINE_LIMIT, check_team
from riskplan.engine.step import Estimates, NumericalTrouble, TrainState, advance, check_agreement
from riskplan.engine.team.convergence import consensus_error
from riskplan.run.checkpoint import CHECKPOINT
from riskplan.run.ray_team import _Team
from riskplan.util.errors import BadInput

runner = CliRunner()
TEAM = [*TINY, "experiment=paper_team", "team.robots=3"]


def byzantine(payload: str) -> str:
    return f"team.faults=[{{robot:0,kind:byzantine,from:0,{payload}}}]"


# ---------------------------------------------------------------------------------------------- the config


@pytest.mark.parametrize(
    "payload, key, shown",
    [
        ("value:1e308", "team.faults.0.value", "1e+308"),
        ("value:-1e200", "team.faults.0.value", "-1e+200"),
        ("value:[1,-1e101]", "team.faults.0.value", "-1e+101"),
        ("scale:1e308", "team.faults.0.scale", "1e+308"),
        ("scale:1e200", "team.faults.0.scale", "1e+200"),
    ],
)
@pytest.mark.parametrize("command", ["train", "check"])
@pytest.mark.slow  # 10 commands through the CLI
def test_a_byzantine_value_or_scale_that_overflows_is_refused_in_one_line(
    tmp_path, monkeypatch, payload, key, shown, command
):
    monkeypatch.chdir(tmp_path)
    run_dir = ["hydra.run.dir=run"] if command == "train" else []
    result = runner.invoke(app, [command, *TEAM, byzantine(payload), *run_dir])
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert lines[0].startswith(f"error: {key}: got {shown}; expected ") and "1e100]" in lines[0]
    assert "overflow" in lines[0] and "Traceback" not in result.output
    assert list(tmp_path.iterdir()) == []  # no run directory, no outputs/


@pytest.mark.parametrize("payload", [{"value": 1e100}, {"value": [-1e100, 3.0]}, {"scale": 1e100}, {"value": 1e9}])
def test_byzantine_values_and_scales_up_to_the_limit_are_valid(payload):
    fault = {"robot": 1, "kind": "byzantine", "from": 0, **payload}
    check_team(typed({"team": {"robots": 3, "faults": [fault]}}).team)
    assert BYZANTINE_LIMIT == 1e100


def test_just_beyond_the_limit_names_the_entry():
    faults = [{"robot": 2, "kind": "crash", "from": 1}, {"robot": 1, "kind": "byzantine", "scale": 1.01e100}]
    with pytest.raises(
        BadInput, match=r"^team\.faults\.1\.scale: got 1\.01e\+100; expected a noise scale in \(0, 1e100\]"
    ):
        check_team(typed({"team": {"robots": 3, "faults": faults}}).team)


# ---------------------------------------------------------------------------------------------- at run time


def estimates(robots: int, params: int = 2) -> Estimates:
    """Estimates of zero gradients: advance then steps theta by the consensus rounds alone."""
    stats = {name: np.zeros(robots) for name in ("mean", "cvar", "value_at_risk", "std", "objective")}
    return Estimates(4, np.zeros((robots, 4)), stats, np.zeros((robots, params)), np.full(robots, 0.1))


@pytest.mark.parametrize(
    "thetas, message",
    [
        ([[1e308, 0.0], [-1e308, 0.0], [0.0, 0.0]], "consensus error max ||theta^i - theta^j|| is not finite"),
        ([[1e308, 0.0]] * 3, "mean theta is not finite"),  # each theta's logits are finite, their sum is not
    ],
)
def test_a_team_whose_thetas_overflow_its_agreement_stops_with_numerical_trouble(thetas, message):
    """Every theta finite, with finite logits (check_step passes), yet the healthy robots' consensus error or mean
    theta (the network average's row) is not: NumericalTrouble in one line, no Statistics."""
    setup = setup_of("experiment=paper_team")
    state = TrainState(0, np.array(thetas), setup.mixer.fresh())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warning on the way
        with pytest.raises(NumericalTrouble) as caught:
            advance(setup, state, estimates(3))
    text = str(caught.value)
    assert text.startswith("iteration 0: the healthy robots' ") and message in text and "\n" not in text
    assert "lower train.step_size.initial" in text


def test_a_huge_but_finite_consensus_error_is_measured_without_overflow():
    setup = setup_of("experiment=paper_team")
    state = TrainState(0, np.array([[1e200, 0.0], [0.0, 0.0], [0.0, -1e200]]), setup.mixer.fresh())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # squaring the gaps would overflow: they are scaled first
        _, statistics = advance(setup, state, estimates(3))
    assert statistics.consensus_error == pytest.approx(math.hypot(1e200, 1e200), rel=1e-15)


def test_consensus_error_beyond_the_largest_float_is_inf_and_warns_nothing():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert consensus_error(np.array([[1.7e308, 0.0], [-1.7e308, 0.0]])) == math.inf
        assert consensus_error(np.array([[1.7e308, 1e-300], [0.0, 0.0]] * 20)) == 1.7e308  # the pruned path too
        assert consensus_error(np.array([[1e300], [-1e300]])) == 2e300
        with pytest.raises(NumericalTrouble, match=r"^iteration 4: .*consensus error"):
            check_agreement(4, np.array([[1.7e308, 0.0], [-1.7e308, 0.0]]), math.inf)
    check_agreement(4, np.array([[1.0, 2.0], [3.0, 4.0]]), math.sqrt(8.0))  # finite: nothing to say


def test_the_ray_driver_checks_each_completed_iteration_alike(tmp_path):
    """team.backend=ray computes the consensus error of the robots' reports itself (riskplan.run.ray_team): the same
    check, before its network-average row is logged."""

    class Log:
        def __init__(self):
            self.logged = []

        def rows(self, rows, *extra):
            self.logged.append((rows, extra))

    setup = setup_of("experiment=paper_team")
    log = Log()
    states = [{"iteration": np.int64(0)} for _ in range(3)]
    team = _Team(None, setup, tmp_path, log, states, [], [])
    far = [[1e308, 0.0], [-1e308, 0.0], [0.0, 0.0]]
    team.partial[0] = {i: {"row": {"theta_0": far[i][0], "theta_1": far[i][1]}} for i in range(3)}
    with pytest.raises(NumericalTrouble, match=r"^iteration 0: .*consensus error"):
        team.complete(0)
    assert log.logged == [] and team.rows == []


def test_a_run_whose_team_drifts_apart_stops_and_keeps_its_last_good_checkpoint(tmp_path, monkeypatch):
    """From iteration 7 the consensus step hands back thetas each finite with finite logits but too far apart: the
    next step stops the run (exit 1, one line), the checkpoint of iteration 5 is kept, no row holds inf."""
    original = engine_step.consensus_step

    def drifting(setup, mixer, thetas, grads, eps, l):
        mixed = original(setup, mixer, thetas, grads, eps, l)
        return np.array([[1e308, 0.0], [-1e308, 0.0], [0.0, 0.0]]) if l == 7 else mixed

    monkeypatch.setattr(engine_step, "consensus_step", drifting)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "run"
    result = runner.invoke(app, ["train", *CHECKPOINTED_TEAM, f"hydra.run.dir={out}"])
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1, result.output
    assert [line for line in lines if line.startswith("error:")] == [lines[-1]]
    assert "iteration 8: the healthy robots' consensus error" in lines[-1] and "Traceback" not in result.output
    assert "overflow encountered" not in result.output
    assert json.loads((out / CHECKPOINT).read_text())["iteration"] == 5
    run = load_run(out)
    assert not run.complete and list(run.metrics.iteration.unique()) == list(range(8))
    assert np.isfinite(run.metrics.drop(columns="healthy").to_numpy(dtype=float)).all()
