"""engine.device changes how a run computes, never its numbers: it enters neither a run's identity (run_identity,
a sweep job's config_sha), nor a sweep's folder names, nor the report's groups."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf
from support import TINY

from riskplan.experiments.reporting.collect import as_compared
from riskplan.experiments.sweep_worker import run_identity
from riskplan.experiments.sweeping.grid import constant_keys
from riskplan.experiments.sweeping.plan import plan_sweep
from riskplan.run.compose import compose


def test_the_identity_leaves_the_engine_out_and_keeps_what_ran():
    cpu, cuda = (OmegaConf.to_container(compose([f"engine.device={d}"], validate=False)) for d in ("cpu", "cuda"))
    assert cpu["engine"] != cuda["engine"] and run_identity(cpu) == run_identity(cuda)
    older = {k: v for k, v in cpu.items() if k != "engine"}  # a run written before the engine node existed
    assert run_identity(older) == run_identity(cpu)
    assert run_identity({**cpu, "seed": 1}) != run_identity(cpu)
    assert as_compared(cuda) == as_compared(cpu) == as_compared(older)


def test_the_engine_never_names_a_folder():
    varying = [["seed=0", "engine.device=cuda"], ["seed=1", "engine.device=cuda"]]
    assert constant_keys(varying) == ["engine.device"]
    assert constant_keys([["engine.device=cpu", "seed=0"]]) == ["engine.device"]  # seed is all that is left
    assert constant_keys([["seed=0", "risk.beta=0.1"], ["seed=1", "risk.beta=0.1"]]) == ["risk.beta"]


@pytest.fixture
def gpu_here(monkeypatch):
    """As if this machine had a GPU (the plan builds every job; none runs)."""
    monkeypatch.setattr("riskplan.run.build.check_device", lambda params: None)


@pytest.mark.slow  # about a second
def test_a_sweep_on_the_gpu_has_the_folders_and_job_identities_of_the_sweep_on_the_cpu(in_tmp, gpu_here):
    plans = {
        device: plan_sweep(["seed=0,1", *([f"engine.device={device}"] if device else []), *TINY])
        for device in ("cuda", "cpu", None)
    }
    for plan in plans.values():
        assert [job.folder for job in plan.jobs] == ["seed=0", "seed=1"]
        assert [job.label for job in plan.jobs] == ["seed=0", "seed=1"]
        assert all(job.invalid is None for job in plan.jobs)
    assert len({tuple(job.sha for job in plan.jobs) for plan in plans.values()}) == 1
    alone = plan_sweep(["engine.device=cuda"])  # the one override names nothing: the folder of a job without any
    assert "hydra.sweep.subdir=defaults" in alone.argv
