"""The engine node (engine.device): typed by the schema, cpu by default, and a bad value is one line."""

from __future__ import annotations

import pytest

from riskplan.config.schema import Device, EngineConf, RiskplanConf
from riskplan.config.typed import as_dict, typed
from riskplan.run.compose import compose
from riskplan.util.errors import BadInput


def test_the_device_is_cpu_by_default_and_cuda_by_choice():
    assert RiskplanConf().engine == EngineConf() and EngineConf().device == Device.cpu
    assert Device.names() == ["cpu", "cuda"]
    params = typed(compose(["engine.device=cuda"], validate=False))
    assert params.engine.device == Device.cuda and as_dict(params)["engine"] == {"device": "cuda"}
    assert typed(compose([], validate=False)).engine.device == Device.cpu


@pytest.mark.parametrize("value", ["gpu", "CUDA", "1"])
def test_a_device_outside_the_choices_is_bad_input_naming_them(value):
    with pytest.raises(BadInput, match=r"^engine\.device: got '.*'; expected one of cpu, cuda$"):
        compose([f"engine.device={value}"], validate=False)
