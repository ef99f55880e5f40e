"""Config keys read from the schema (riskplan.config.keys.KEYS), and the modules that name keys through it."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from riskplan.config.keys import KEYS, Items, Key, _fields
from riskplan.config.schema import MotionConf, RiskplanConf, TeamConf

PACKAGE = Path(__file__).resolve().parents[2] / "riskplan"
# modules whose key names come from KEYS: a quoted dotted key there would be a hand-written copy
READ_FROM_SCHEMA = [
    "config/validate.py",
    "run/budget.py",
    "run/checkpoint.py",
    "run/maps.py",
    "experiments/bench_gpu.py",
    "experiments/bench_scaling.py",
    "experiments/reproduction.py",
    "experiments/reporting/collect.py",
    "experiments/reporting/labels.py",
    "experiments/reporting/tables.py",
    "experiments/reporting/study_tables.py",
    "experiments/reporting/figures/beyond.py",
    "experiments/reporting/figures/naming.py",
]
DOTTED = re.compile(r"""(?<![A-Za-z{])(["'])(?:risk|team|train|world|policy|engine)\.[a-z_.]+\1""")


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


def test_a_list_item_is_at_its_index_with_the_keys_of_its_dataclass():
    assert KEYS.world.sources.at(3).motion.prob == "world.sources.3.motion.prob"
    assert KEYS.team.risk.at(1).schedule.start == "team.risk.1.schedule.start"  # an Optional list too
    assert KEYS.team.speeds.at(0) == "team.speeds.0"
    assert KEYS.world.obstacles.at(2).at(1) == "world.obstacles.2.1"
    with pytest.raises(AttributeError, match=r"world.sources is a list; .*world.sources.at\(0\).motion"):
        _ = KEYS.world.sources.motion  # a list's keys are its items'
    with pytest.raises(AttributeError, match=r"team\.robots is not a list"):
        KEYS.team.robots.at(0)
    with pytest.raises(AttributeError):
        _ = KEYS.team.speeds.at(0).factor  # a plain item has no keys below it


def test_no_field_is_hidden_by_a_method_of_a_key():
    """A field named like a str method (count, index, ...) or Key.at would read as the method, not as its key."""
    seen, todo = set(), [RiskplanConf]
    while todo:
        node = todo.pop()
        seen.add(node)
        for name, value in _fields(node).items():
            assert not hasattr(Key, name), f"{node.__name__}.{name}"
            while isinstance(value, Items):
                value = value.node
            if value is not None and value not in seen:
                todo.append(value)
    assert MotionConf in seen  # reached through the list world.sources


@pytest.mark.parametrize("module", READ_FROM_SCHEMA)
def test_the_module_writes_out_no_config_key(module):
    assert [m.group(0) for m in DOTTED.finditer((PACKAGE / module).read_text())] == []
