"""The registry of risk measures: a measure from an installed package's entry point (group riskplan.risk_measures)
is found by its name, by riskplan.risk and by a config; a broken entry point, a name no package provides and bad
parameters are BadInput in one line; and a built-in name never looks at the installed packages."""

from __future__ import annotations

import importlib.metadata
import sys

import numpy as np
import pytest
from measure_cases import install_package
from support import TINY

from riskplan.config.typed import typed
from riskplan.engine.measures import registry
from riskplan.risk import MEASURES, lookup, names, objective, objective_gradient, risk_spec
from riskplan.run.build import build_setup
from riskplan.run.compose import compose
from riskplan.util.errors import BadInput

POWER = {"measure": "power", "params": {"gamma": 0.5}}


@pytest.fixture
def installed(tmp_path, monkeypatch):
    """The power package on sys.path, with no measure of a package loaded before (and none kept after)."""

    def install(**kwargs):
        site = install_package(tmp_path, **kwargs)
        monkeypatch.syspath_prepend(str(site))
        return site

    monkeypatch.setattr(registry, "_FROM_PACKAGES", {})
    yield install
    sys.modules.pop("riskplan_power", None)


def test_a_packages_measure_is_found_by_its_name(installed):
    installed()
    # the built-in names first, then the installed packages' (the user may have others of their own installed)
    assert "power" not in MEASURES and names()[: len(MEASURES)] == list(MEASURES)
    assert "power" in names()[len(MEASURES) :]
    power = lookup("power")
    assert power.name == "power" and lookup("power") is power  # loaded once
    z = np.random.default_rng(1).normal(size=999)
    s = np.random.default_rng(2).normal(size=(999, 2))
    k = np.arange(z.size + 1) / z.size
    assert objective(z, POWER) == pytest.approx(np.sort(z) @ np.diff(k**0.5), rel=1e-12)  # sum z_(i) [G(i/W) - ...]
    np.testing.assert_array_equal(objective_gradient(z, s, POWER), power.gradient(z, s, power.check({"gamma": 0.5})))
    assert risk_spec(POWER).params == {"gamma": 0.5}


@pytest.mark.slow  # over a second
def test_a_config_selects_and_checks_a_packages_measure(installed):
    installed()
    setup = build_setup(compose([*TINY, "risk.measure=power", "risk.params.gamma=0.5"], validate=False))
    assert setup.params.risk.measure == "power" and setup.params.risk.params == {"gamma": 0.5}
    team = "team.risk=[{measure:power,params:{gamma:0.25}},{measure:cvar,beta:0.2}]"
    setup = build_setup(compose([*TINY, "experiment=paper_team", "team.robots=2", team], validate=False))
    assert [r.measure for r in setup.params.team.risk] == ["power", "cvar"]
    for overrides, message in (
        (["risk.measure=power"], r"^risk\.params\.gamma: missing; measure 'power' needs 0 < gamma < 1$"),
        (["risk.measure=power", "risk.params.gamma=1"], r"^risk\.params\.gamma: got 1; expected 0 < gamma < 1$"),
        (
            ["risk.measure=power", "risk.params.gamma=0.5", "risk.params.delta=2"],
            r"^risk\.params\.delta: unknown parameter of measure 'power'; its parameters: gamma$",
        ),
        (["risk.params.gamma=0.5"], r"^risk\.params\.gamma: the built-in measure 'cvar' takes risk\.beta; "),
        (
            ["experiment=paper_team", "team.robots=2", "team.risk=[{measure:cvar},{measure:power,params:{gamma:2}}]"],
            r"^team\.risk\.1\.params\.gamma: got 2; expected 0 < gamma < 1$",
        ),
        (  # power among the installed measures' names, whichever others the user has installed
            ["risk.measure=powr"],
            r"^risk\.measure: got 'powr'; expected a built-in measure .*\(installed: ([\w, ]+, )?power(, [\w, ]+)?\); "
            r"did you mean 'power'\?$",
        ),
    ):
        with pytest.raises(BadInput, match=message):
            build_setup(compose([*TINY, *overrides], validate=False))
    with pytest.raises(BadInput, match=r"^key 'risk\.params\.gamma': got 'abc'; expected a number$"):
        compose([*TINY, "risk.measure=power", "risk.params.gamma=abc"], validate=False)


@pytest.mark.parametrize(
    ("node", "message"),
    [
        (
            {"measure": "wang", "eta": 0.75, "betta": 0.3},
            r"^risk\.betta: not a key of a risk node; .*did you mean 'beta'\?$",
        ),
        ({"measure": "cvar", "gamma": 0.5}, r"^risk\.gamma: not a key .*under params\)$"),
    ],
)
def test_a_mistyped_key_of_a_risk_mapping_is_refused_not_ignored(node, message):
    """The measure ran at its default eta with 'betta' dropped; an unused key of the schema (beta for wang) is fine,
    as in a config."""
    z = np.random.default_rng(0).normal(size=1000)
    with pytest.raises(BadInput, match=message):
        objective(z, node)
    assert objective(z, {"measure": "wang", "eta": 0.75, "beta": 0.3}) == objective(z, {"measure": "wang", "eta": 0.75})


@pytest.mark.parametrize(
    ("module", "points", "message"),
    [
        (
            "raise ImportError('no numpy here')\n",
            None,
            r"entry point riskplan_power:power fails to load: ImportError: no",
        ),
        ("power = 3\n", None, r"entry point riskplan_power:power is a int, not a measure; make it riskplan\.risk\."),
        (
            "import riskplan.risk\npower = riskplan.risk.distortion('pow', lambda u, g: u**g, g=(0, 1))\n",
            None,
            r"entry point riskplan_power:power is the measure 'pow'; name the entry point as the measure",
        ),
        (
            "",
            {"power": "riskplan_power:power", "other": "riskplan_power:other"},
            r"entry point riskplan_power:power fails to load: AttributeError",
        ),
    ],
)
def test_a_broken_entry_point_is_one_line(installed, module, points, message):
    installed(module=module, entry_points=points)
    with pytest.raises(BadInput, match=rf"^risk\.measure: got 'power', whose {message}"):
        lookup("power")


def test_a_built_in_name_never_looks_at_the_installed_packages(monkeypatch):
    def scan(**kwargs):
        raise AssertionError("entry points looked up for a built-in measure")

    monkeypatch.setattr(importlib.metadata, "entry_points", scan)
    params = typed(compose(TINY, validate=False))
    registry.check_risk_nodes(params)
    for name in MEASURES:
        assert lookup(name).name == name
