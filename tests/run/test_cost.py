"""The run-cost model calibrated on this machine (riskplan.run.cost): fitted to known records, robust to a cache
that is missing, corrupt or read-only, and recorded by every finished run."""

from __future__ import annotations

import json
import os

import pytest
from support import TINY

from riskplan.run import cost
from riskplan.run.compose import compose
from riskplan.run.training import train_summary


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv(cost.CACHE_ENV, str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_without_records_the_model_assumes_the_default_speed_and_says_so(cache):
    model = cost.model()
    assert (model.rate, model.overhead, model.runs) == (cost.DEFAULT_RATE, cost.DEFAULT_OVERHEAD, 0)
    assert "not yet calibrated on this machine: 80M steps/s and 0.5 s per run assumed" in model.describe()


def test_the_model_recovers_overhead_and_rate_from_runs_of_different_sizes(cache):
    for steps in (1e7, 3e7, 6e7, 1e8):
        cost.record(steps, 2.0 + steps / 4e7)  # 2 s of overhead, 40M steps/s
    model = cost.model()
    assert model.runs == 4 and "calibrated on 4 runs" in model.describe()
    assert model.overhead == pytest.approx(2.0) and model.rate == pytest.approx(4e7)
    assert model.run_seconds(8e7) == pytest.approx(4.0)
    # a sweep: its steps share the machine, each worker pays its jobs' set-up and overheads, plus the launch
    assert model.sweep_seconds([8e7] * 4, workers=2) == pytest.approx(cost.LAUNCH + 8.0 + 4 * (cost.SWEEP_JOB + 2) / 2)
    assert model.sweep_seconds([], workers=2) == 0.0


def test_runs_slowed_by_a_busy_minute_do_not_move_the_fitted_line(cache):
    sizes = [1e7 * (k + 1) for k in range(10)]
    for steps in sizes:
        cost.record(steps, 0.5 + steps / 5e7)  # 0.5 s of overhead, 50M steps/s
    for steps in sizes[-3:]:  # three runs ten times slower: a least-squares line says 6M steps/s, overhead < 0
        cost.record(steps, 10 * (0.5 + steps / 5e7))
    model = cost.model()  # most slopes between records, and most overheads, are the line's: their medians are exact
    assert model.runs == 13
    assert model.rate == pytest.approx(5e7) and model.overhead == pytest.approx(0.5)


def test_a_line_that_would_give_small_runs_no_time_goes_through_the_origin(cache):
    runs = [(1e7, 0.1), (2e7, 0.3), (4e7, 0.7), (8e7, 1.5)]  # the Theil-Sen line: 20 ns a step, -0.1 s
    for steps, seconds in runs:
        cost.record(steps, seconds)
    model = cost.model()
    assert model.overhead == 0.0 and model.rate == pytest.approx((2e7 / 0.3 + 4e7 / 0.7) / 2)  # median steps/s


def test_runs_of_one_size_give_the_median_rate(cache):
    for seconds in (3.0, 5.0, 100.0):  # one run on a loaded machine does not move the median
        cost.record(1e8, seconds)
    model = cost.model()
    assert model.overhead == cost.DEFAULT_OVERHEAD and model.rate == pytest.approx(1e8 / (5.0 - cost.DEFAULT_OVERHEAD))


def test_runs_too_short_to_tell_the_rate_leave_the_default(cache):
    cost.record(1e4, 0.3)  # a sweep worker's warm-up: its seconds are overhead
    assert cost.model() == cost.Model(cost.DEFAULT_RATE, cost.DEFAULT_OVERHEAD, 0)
    cost.record(1e8, 3.0)
    model = cost.model()
    assert model.runs == 1 and model.rate == pytest.approx(1e8 / (3.0 - cost.DEFAULT_OVERHEAD))


def test_a_run_with_part_of_the_cores_counts_its_share(cache):
    cost.record(1e8, 10.0, share=0.5)  # the whole machine would have done twice the steps in its 10 s
    assert json.loads(next(cache.iterdir()).read_text())["runs"] == [[2e8, 10.0]]
    cost.record(1e8, 10.0, share=0.0)  # no share of the cores says nothing of their speed
    assert len(json.loads(next(cache.iterdir()).read_text())["runs"]) == 1


def test_only_the_latest_records_are_kept(cache):
    for i in range(cost.KEEP + 10):
        cost.record(1e6 * (i + 1), 1.0 + i)
    runs = json.loads(next(cache.iterdir()).read_text())["runs"]
    assert len(runs) == cost.KEEP and runs[-1] == [1e6 * (cost.KEEP + 10), float(cost.KEEP + 10)]


@pytest.mark.parametrize("text", ["{", "[1, 2]", '{"runs": [[1, "x"], [NaN, 1], [-1, 2], [1e7, 1e999]]}'])
def test_a_corrupt_cache_is_no_calibration(cache, text):
    cache.mkdir()
    cost.cache_file().write_text(text)
    assert cost.model().runs == 0
    cost.record(1e7, 1.5)  # and the next run starts it again
    assert cost.model().runs == 1


def test_non_finite_or_empty_records_are_not_kept(cache):
    for steps, seconds in ((float("inf"), 1.0), (1e7, float("nan")), (0.0, 1.0), (1e7, 0.0)):
        cost.record(steps, seconds)
    assert cost.model().runs == 0


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_cache_costs_only_the_calibration(cache):
    cache.mkdir(mode=0o500)
    cost.record(1e7, 1.0)
    assert cost.model().runs == 0


def test_a_cache_path_that_is_a_file_costs_only_the_calibration(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv(cost.CACHE_ENV, str(blocker / "cache"))
    cost.record(1e7, 1.0)
    assert cost.model().runs == 0


@pytest.mark.slow  # a whole run (near a second)
def test_a_finished_run_records_its_estimated_steps(cache, tmp_path):
    config = compose(TINY)
    train_summary(config, tmp_path / "warm")  # numba's kernels compiled or loaded: the next run compiles nothing
    cost.cache_file().unlink(missing_ok=True)
    train_summary(config, tmp_path / "run")
    (record,) = json.loads(cost.cache_file().read_text())["runs"]
    width, height = (int(v) for v in config.world.size)
    assert record[0] == cost.config_steps(config, width, height, len(config.world.sources), 1) and record[1] > 0


def test_compiles_counts_numbas_compilations_not_its_calls():
    from numba import njit

    @njit
    def twice(x):
        return 2 * x

    before = cost.compiles()
    assert twice(3) == 6 and cost.compiles() == before + 1
    assert twice(4) == 8 and cost.compiles() == before + 1  # compiled once for ints
    assert twice(1.5) == 3.0 and cost.compiles() == before + 2  # and once for floats


def test_a_run_during_which_numba_compiled_does_not_calibrate(cache, tmp_path, monkeypatch):
    counts = iter(range(100))
    monkeypatch.setattr(cost, "compiles", lambda: next(counts))  # a compile between the run's start and end
    train_summary(compose(TINY), tmp_path / "run")
    assert not cost.cache_file().exists() and cost.model().runs == 0


def test_say_rounds_as_an_estimate():
    assert cost.say(3.0) == "under 10 s" and cost.say(59.0) == "about 59 s" and cost.say(600.0) == "about 10 min"
    calibrated = cost.Model(4e7, 2.0, 5)
    assert cost.say(59.0, calibrated) == "about 59 s"


def test_an_uncalibrated_estimate_is_said_as_the_range_its_defaults_span():
    default = cost.Model(cost.DEFAULT_RATE, cost.DEFAULT_OVERHEAD, 0)
    assert cost.UNCALIBRATED == (0.7, 2.0)
    assert cost.say(20.0, default) == "roughly 14 s to 40 s"
    assert cost.say(3.0, default) == "roughly 2 s to 6 s"  # not "under 10 s": the range says how unsure it is
    assert cost.say(600.0, default) == "roughly 7 min to 20 min"


def test_a_small_sweeps_estimate_counts_each_jobs_set_up_and_the_workers_start():
    """12 jobs of 11.5M steps on 2 workers (the sweep that took 17 s on a loaded 2-core VM where the estimate said
    under 10 s): the launch, the steps on the whole machine, and per job its Hydra set-up and its run's overhead."""
    default = cost.Model(cost.DEFAULT_RATE, cost.DEFAULT_OVERHEAD, 0)
    parts = {"launch": 5.0, "steps": 12 * 11.5e6 / 80e6, "jobs": 12 * (0.7 + 0.5) / 2}
    assert (cost.LAUNCH, cost.SWEEP_JOB, cost.DEFAULT_OVERHEAD) == (5.0, 0.7, 0.5)
    seconds = default.sweep_seconds([11.5e6] * 12, workers=2)
    assert seconds == pytest.approx(sum(parts.values())) == pytest.approx(13.925)
    assert cost.say(seconds, default) == "roughly 10 s to 28 s"
    # one batch: no workers to start, no Hydra set-up per job, but each job's evaluation and files in turn
    batch = default.batch_seconds([11.5e6] * 12, batches=1)
    assert batch == pytest.approx(cost.BATCH_LAUNCH + parts["steps"] + (1 + 12) * 0.5)
    assert default.batch_seconds([], batches=1) == 0.0
