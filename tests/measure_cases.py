"""The risk measures that the registry-wide tests run over: every registered measure (the built-in ones, and any
that an installed package adds through the entry-point group riskplan.risk_measures) at two values of its
parameters, and two distortions made here with riskplan.risk.distortion. A new measure is tested by them with no
new test code: its objective against its closed form on a normal (`Measure.of_normal`) and its gradient against
that form's derivatives, and its estimator against an exactly enumerated world (`Measure.of_distribution`).

Test files import it as `from measure_cases import ...`, as they import support.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import pytest

from riskplan.risk import Parameter, Spectral, distortion, lookup, names

# concave: risk-averse; power weighs the lowest quantiles without bound (phi(u) = gamma u^(gamma - 1))
POWER = distortion("power", lambda u, gamma: u**gamma, gamma=(0.0, 1.0))
DUAL_POWER = distortion("dual_power", lambda u, k: 1.0 - (1.0 - u) ** k, k=(1.0, 5.0))
# Where in each parameter's range the two cases sit: mid-range, because the plug-in of a spectrum unbounded at 0
# (power's, gamma u^(gamma - 1)) is biased at finite W, as much as its standard error at 125,000 samples for
# gamma 0.45 (its L-statistic's own bias, which falls slowly with W); the exact tests pick their own extremes.
FRACTIONS = (0.5, 0.8)


def example(parameter: Parameter, fraction: float) -> float:
    """A value a fraction of the way through the parameter's range (an unbounded one taken as one unit wide)."""
    low = parameter.low if math.isfinite(parameter.low) else 0.0
    high = parameter.high if math.isfinite(parameter.high) else low + 1.0
    return low + fraction * (high - low)


def node(measure, fraction: float) -> dict:
    """A risk node of the measure with its parameters at `fraction` of their ranges."""
    params = {p.name: example(p, fraction) for p in measure.parameters}
    return {"measure": measure, **params} if measure.built_in else {"measure": measure, "params": params}


def measure_cases(spectral_only: bool = False) -> list:
    """pytest params: one risk node per measure and fraction (one per measure without parameters)."""
    cases = []
    for measure in [*(lookup(name) for name in names()), POWER, DUAL_POWER]:
        if spectral_only and not isinstance(measure, Spectral):
            continue
        for fraction in FRACTIONS if measure.parameters else FRACTIONS[:1]:
            cases.append(pytest.param(node(measure, fraction), id=f"{measure.name}-{fraction}"))
    return cases


# ------------------------------------------------------------------------------------------------ a user's package
ENTRY_POINTS = {"power": "riskplan_power:power"}  # the package's entry points in the group riskplan.risk_measures
PYPROJECT = """\
[build-system]
requires = ["setuptools>=61"]
build-backend = "setuptools.build_meta"

[project]
name = "riskplan-power"
version = "0.1.0"
dependencies = ["riskplan"]

[project.entry-points."riskplan.risk_measures"]
""" + "".join(f'{name} = "{target}"\n' for name, target in ENTRY_POINTS.items())
MODULE = '''\
"""A power distortion for riskplan: G(u) = u^gamma, risk-averse for gamma < 1."""

import riskplan.risk

power = riskplan.risk.distortion("power", lambda u, gamma: u**gamma, gamma=(0, 1))
'''


def install_package(root: Path, module: str = MODULE, entry_points: dict[str, str] | None = None) -> Path:
    """A measure's package written as a user writes it (root/riskplan-power: pyproject.toml and riskplan_power.py)
    and installed as pip installs it, without a build: the module and a dist-info whose entry_points.txt holds the
    pyproject's entry points (or `entry_points`), in root/site. Put that on sys.path or PYTHONPATH."""
    source, site = root / "riskplan-power", root / "site"
    dist = site / "riskplan_power-0.1.0.dist-info"
    source.mkdir(parents=True)
    dist.mkdir(parents=True)
    (source / "pyproject.toml").write_text(PYPROJECT)
    (source / "riskplan_power.py").write_text(module)
    shutil.copy(source / "riskplan_power.py", site)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: riskplan-power\nVersion: 0.1.0\n")
    points = ENTRY_POINTS if entry_points is None else entry_points
    (dist / "entry_points.txt").write_text(
        "[riskplan.risk_measures]\n" + "".join(f"{k} = {v}\n" for k, v in points.items())
    )
    return site
