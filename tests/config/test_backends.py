"""Every backend and device of the registry (riskplan.config.backends), with no test code of its own: a record for
each choice of the schema, the modules it names, the extra it needs, and the network it simulates or not."""

from __future__ import annotations

import dataclasses
import inspect

import pytest
from support import bad_input, setup_of

from riskplan.config import validate
from riskplan.config.backends import BACKENDS, DEVICES, load
from riskplan.config.schema import Backend, Device
from riskplan.engine.rollout import simulate
from riskplan.util.checks import installed
from riskplan.util.errors import MissingExtra

RECORDS = [("team.backend", spec) for spec in BACKENDS.values()] + [
    ("engine.device", spec) for spec in DEVICES.values()
]
IDS = [f"{key}={spec.name.value}" for key, spec in RECORDS]


def test_each_choice_of_the_schema_has_its_record():
    assert list(BACKENDS) == list(Backend) and all(name == spec.name for name, spec in BACKENDS.items())
    assert list(DEVICES) == list(Device) and all(name == spec.name for name, spec in DEVICES.items())


def available(spec) -> bool:
    return spec.needs is None or installed(spec.needs.module)


@pytest.mark.parametrize("key, spec", RECORDS, ids=IDS)
def test_a_missing_extra_is_one_line_naming_the_choice(key, spec, monkeypatch):
    if spec.needs is None:
        validate.check_extra(key, spec.name.value)  # needs nothing
        return
    monkeypatch.setitem(
        validate.EXTRAS,
        (key, spec.name.value),
        ("riskplan_absent_module", *validate.EXTRAS[(key, spec.name.value)][1:]),
    )
    with pytest.raises(
        MissingExtra,
        match=rf"^{key}={spec.name.value}: needs {spec.needs.what}, which is not installed; pip install 'riskplan\[{spec.needs.extra}\]'",
    ):
        validate.check_extra(key, spec.name.value)


@pytest.mark.parametrize("spec", list(BACKENDS.values()), ids=[s.name.value for s in BACKENDS.values()])
def test_the_backend_names_a_driver_with_the_drivers_arguments(spec):
    if spec.driver is None:
        return  # the engine's loop, as run.training drives it
    if not available(spec):
        pytest.skip(f"{spec.needs.module} is not installed")
    assert list(inspect.signature(load(spec.driver)).parameters)[:4] == ["setup", "out", "resume", "progress"]


@pytest.mark.parametrize("spec", list(BACKENDS.values()), ids=[s.name.value for s in BACKENDS.values()])
def test_a_simulated_network_takes_delays_and_drops_and_a_real_one_refuses_them(spec):
    overrides = ["experiment=paper_team", f"team.backend={spec.name.value}", "team.drop=0.2"]
    if not available(spec):
        pytest.skip(f"{spec.needs.module} is not installed")
    if spec.simulated_network:
        assert setup_of(*overrides).params.team.drop == 0.2
    else:
        assert bad_input(*overrides).where == "team.drop"


@pytest.mark.parametrize("spec", list(DEVICES.values()), ids=[s.name.value for s in DEVICES.values()])
def test_the_device_names_a_kernel_with_the_arguments_of_simulate(spec):
    if not available(spec):
        pytest.skip(f"{spec.needs.module} is not installed")
    try:
        kernel = load(spec.kernel)
    except ImportError as err:  # numba-cuda installed with a numpy it does not support: the build says so
        pytest.skip(f"{spec.kernel} does not import here: {err}")
    assert inspect.signature(kernel).parameters.keys() == inspect.signature(simulate).parameters.keys()
    assert spec.check is None or callable(load(spec.check))


def test_the_records_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        BACKENDS[Backend.ray].deterministic = True
