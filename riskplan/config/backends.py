"""Where a run computes: the backends (team.backend) and the devices (engine.device), one place that names each
choice and what it needs. Validation, the build, the sweeps and the run's summary read these records instead of
testing for a value; `tests/config/test_backends.py` tests every record.

A new backend or device is its module (a driver of the algorithm, or an episode kernel with the arguments and
numbers of `riskplan.engine.rollout.simulate`), its value in `schema.Backend` or `schema.Device`, and its line here
(docs/extending.md). The modules are named, not imported: the config sits below them, and an optional package is
imported only by the runs that choose it.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from riskplan.config.schema import Backend, Device


@dataclass(frozen=True)
class Extra:
    """An optional package a choice needs: the module it provides, what it is, and the riskplan extra that installs
    it (`pip install 'riskplan[<extra>]'`)."""

    module: str
    what: str
    extra: str
    note: str = ""


@dataclass(frozen=True)
class BackendSpec:
    """team.backend=<name>: where the robots run."""

    name: Backend
    driver: str | None  # module:function(setup, out, resume, progress) that trains a run on it (None: the engine's
    # loop, as run.training drives it)
    needs: Extra | None = None
    deterministic: bool = True  # the same numbers every time (False: the wall clock orders its messages)
    simulated_network: bool = True  # team.delay, team.drop and team.switching apply (a real network refuses them)
    batched: bool = True  # sweep --batch may train it with other runs (False: each run alone)
    resume_check: str | None = None  # module:function(setup, out) -> finished, for a driver's own checkpoints


@dataclass(frozen=True)
class DeviceSpec:
    """engine.device=<name>: where a run's episodes run, always to the same numbers."""

    name: Device
    kernel: str  # module:function that runs a batch of episodes, as engine.rollout.simulate
    needs: Extra | None = None
    check: str | None = None  # module:function that refuses a machine without it (BadInput), when the run is built


BACKENDS = {
    Backend.simulated: BackendSpec(Backend.simulated, None),
    Backend.ray: BackendSpec(
        Backend.ray,
        "riskplan.run.ray_team:train_ray",
        Extra("ray", "Ray", "distributed"),
        resume_check="riskplan.run.ray_team:prepare_ray_resume",
        deterministic=False,
        simulated_network=False,
        batched=False,
    ),
}

DEVICES = {
    Device.cpu: DeviceSpec(Device.cpu, "riskplan.engine.rollout:simulate"),
    Device.cuda: DeviceSpec(
        Device.cuda,
        "riskplan.engine.cuda_rollout:simulate",
        Extra("numba_cuda", "numba-cuda", "cuda"),
        check="riskplan.engine.cuda_rollout:check_gpu",
    ),
}


def load(target: str):
    """The function a record names (`module:function`), its module imported now."""
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)
