"""Config keys read from the schema, not written out: `KEYS.team.delay.max` is the string "team.delay.max", and
reading it checks each step against the dataclasses of `riskplan.config.schema`, so a renamed or misspelt key fails
where it is named (when its module is imported), never later in a label or a message.

    from riskplan.config.keys import KEYS
    DEFAULTS = {KEYS.train.samples: 6000.0}        # "train.samples"
    f"{KEYS.risk.beta}={beta}"                     # "risk.beta=0.1"
"""

from __future__ import annotations

import dataclasses
import functools
import typing

from riskplan.config.schema import RiskplanConf


class Key(str):
    """A dotted config key (a plain str everywhere), whose attributes are the keys of the fields below it."""

    node: type | None  # the dataclass of this key's value, or None for a leaf

    def __getattr__(self, name: str) -> Key:
        if name.startswith("_") or self.node is None:
            raise AttributeError(name)
        fields = _fields(self.node)
        if name not in fields:
            raise AttributeError(f"{self or 'the config'} has no key {name!r}; its keys: {', '.join(fields)}")
        return _key(f"{self}.{name}" if self else name, fields[name])


def _key(path: str, node: type | None) -> Key:
    key = Key(path)
    key.node = node
    return key


@functools.cache
def _fields(node: type) -> dict[str, type | None]:
    """A dataclass's field names, each with its value's dataclass (None for a leaf; Optional unwrapped)."""
    hints = typing.get_type_hints(node)
    out: dict[str, type | None] = {}
    for field in dataclasses.fields(node):
        kinds = (hints[field.name], *typing.get_args(hints[field.name]))
        out[field.name] = next((k for k in kinds if isinstance(k, type) and dataclasses.is_dataclass(k)), None)
    return out


KEYS = _key("", RiskplanConf)  # the config's root: KEYS.<group>.<field>...
