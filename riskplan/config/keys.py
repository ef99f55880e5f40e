"""Config keys read from the schema, not written out: `KEYS.team.delay.max` is the string "team.delay.max", and
reading it checks each step against the dataclasses of `riskplan.config.schema`, so a renamed or misspelt key fails
where it is named (when its module is imported), never later in a label or a message. A list's item is `at(i)`.

    from riskplan.config.keys import KEYS
    DEFAULTS = {KEYS.train.samples: 6000.0}        # "train.samples"
    f"{KEYS.risk.beta}={beta}"                     # "risk.beta=0.1"
    KEYS.world.sources.at(j).motion.prob           # "world.sources.<j>.motion.prob"
"""

from __future__ import annotations

import dataclasses
import functools
import typing

from riskplan.config.schema import RiskplanConf


@dataclasses.dataclass(frozen=True)
class Items:
    """A list's items: their dataclass, Items again for a list of lists, or None for plain values."""

    node: type | Items | None


class Key(str):
    """A dotted config key (a plain str everywhere), whose attributes are the keys of the fields below it."""

    node: type | Items | None  # the dataclass of this key's value, Items for a list, or None for a leaf

    def __getattr__(self, name: str) -> Key:
        if name.startswith("_") or self.node is None:
            raise AttributeError(name)
        if isinstance(self.node, Items):
            raise AttributeError(f"{self} is a list; name an item's key with at(i): {self}.at(0).{name}")
        fields = _fields(self.node)
        if name not in fields:
            raise AttributeError(f"{self or 'the config'} has no key {name!r}; its keys: {', '.join(fields)}")
        child = self.__dict__[name] = _key(f"{self}.{name}" if self else name, fields[name])  # found at once next time
        return child

    def at(self, index: int) -> Key:
        """The key of item `index` of a list: KEYS.team.risk.at(2) is "team.risk.2", with a RiskConf's keys."""
        if not isinstance(self.node, Items):
            raise AttributeError(f"{self or 'the config'} is not a list")
        return _key(f"{self}.{index}", self.node.node)


def _key(path: str, node: type | Items | None) -> Key:
    key = Key(path)
    key.node = node
    return key


@functools.cache
def _fields(node: type) -> dict[str, type | Items | None]:
    """A dataclass's field names, each with what its value is (see _node)."""
    hints = typing.get_type_hints(node)
    return {field.name: _node(hints[field.name]) for field in dataclasses.fields(node)}


def _node(hint: typing.Any) -> type | Items | None:
    """A value's dataclass, Items for a list, or None for a leaf (Optional unwrapped)."""
    for kind in (hint, *typing.get_args(hint)):
        if typing.get_origin(kind) is list:
            return Items(_node(typing.get_args(kind)[0]))
        if isinstance(kind, type) and dataclasses.is_dataclass(kind):
            return kind
    return None


KEYS = _key("", RiskplanConf)  # the config's root: KEYS.<group>.<field>...
