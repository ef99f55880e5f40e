"""Config keys read from the schema (riskplan.config.keys.KEYS), and the modules that name keys through it."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from riskplan.config.keys import KEYS
from riskplan.config.schema import RiskplanConf, TeamConf

PACKAGE = Path(__file__).resolve().parents[2] / "riskplan"
# modules whose key names come from KEYS: a quoted dotted key there would be a hand-written copy
READ_FROM_SCHEMA = [
    "run/budget.py",
    "experiments/reproduction.py",
    "experiments/reporting/collect.py",
    "experiments/reporting/labels.py",
    "experiments/reporting/tables.py",
    "experiments/reporting/study_tables.py",
    "experiments/reporting/figures/beyond.py",
    "experiments/reporting/figures/naming.py",
]
DOTTED = re.compile(r"""(?<![A-Za-z{])["'](?:risk|team|train|world|policy|engine)\.[a-z_.]+["']""")


def test_a_key_is_its_dotted_path_and_a_plain_string():
    assert KEYS.team.delay.max == "team.delay.max"
    assert KEYS.risk.schedule.kind == "risk.schedule.kind"
    assert KEYS.experiment == "experiment"
    assert {KEYS.train.samples: 1}["train.samples"] == 1
    assert f"{KEYS.risk.beta}=0.1" == "risk.beta=0.1"


def test_every_field_of_a_group_is_a_key():
    assert [getattr(KEYS.team, f.name) for f in dataclasses.fields(TeamConf)] == [
        f"team.{f.name}" for f in dataclasses.fields(TeamConf)
    ]
    assert [getattr(KEYS, f.name) for f in dataclasses.fields(RiskplanConf)] == [
        f.name for f in dataclasses.fields(RiskplanConf)
    ]


def test_a_key_the_schema_does_not_have_fails_where_it_is_named():
    with pytest.raises(AttributeError, match="team has no key 'dely'; its keys: robots, graph"):
        _ = KEYS.team.dely
    with pytest.raises(AttributeError):
        _ = KEYS.team.delay.max.limit  # a leaf has no keys below it


@pytest.mark.parametrize("module", READ_FROM_SCHEMA)
def test_the_module_writes_out_no_config_key(module):
    assert DOTTED.findall((PACKAGE / module).read_text()) == []
