"""One typed, frozen config: the composed config checked against the schema, resolved, and turned into the frozen
dataclasses of `riskplan.config.schema` once (gymnax's EnvParams). Below this module nothing reads raw config dicts.

Every problem is BadInput naming the key path (`key 'risk.beta': got 'abc'; expected a number`).
"""

from __future__ import annotations

import collections
import collections.abc
import dataclasses
import functools
import itertools
import json
import re
import types
import typing

from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from riskplan.config import schema
from riskplan.config.hydra_safety import interpolation_reason
from riskplan.config.schema import CONF_DIR
from riskplan.util.errors import BadInput, did_you_mean


def typed(cfg: DictConfig | dict | schema.RiskplanConf) -> schema.RiskplanConf:
    """The frozen RiskplanConf of a composed config (or of a run's saved config dict); BadInput on a bad key.

    Remembered for the last few configs: `riskplan train` types one config three times (its checks, the run, and
    the .hydra/config.yaml Hydra wrote), and typing one is not free (`riskplan bench` times the start-up). The result
    is frozen, so sharing it is safe."""
    if isinstance(cfg, schema.RiskplanConf):
        return cfg
    node = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)
    key = _memo_key(node)
    if key in _TYPED:
        _TYPED.move_to_end(key)
        return _TYPED[key]
    params = OmegaConf.to_object(
        _composed(node) if OmegaConf.get_type(node) is schema.RiskplanConf else check_schema(node)
    )
    if key is not None:
        _TYPED[key] = params
        while len(_TYPED) > TYPED_MEMO:
            _TYPED.popitem(last=False)
    return params


TYPED_MEMO = 16
_TYPED: collections.OrderedDict[str, schema.RiskplanConf] = collections.OrderedDict()


def _memo_key(node: DictConfig) -> str | None:
    """The config as resolved JSON (what typing it depends on), or None when it does not resolve: typing it then
    says why."""
    try:
        return json.dumps(OmegaConf.to_container(node, resolve=True), sort_keys=True, default=repr)
    except (OmegaConfBaseException, TypeError, ValueError, RecursionError):
        return None


def as_dict(params: schema.RiskplanConf) -> dict:
    """The frozen config as plain data (lists and dicts), as it is recorded in .hydra/config.yaml and run.mcap."""
    return dataclasses.asdict(params, dict_factory=lambda items: {k: _plain(v) for k, v in items})


def _plain(value: typing.Any) -> typing.Any:
    """A Choice as its value (the string users type); lists of them likewise; anything else as it is."""
    if isinstance(value, schema.Choice):
        return value.value
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def check_schema(cfg) -> DictConfig:
    """The config merged onto the typed schema: keys added with `+key=...` or written by hand must exist there too.

    Hydra lets `+foo=1` add a key the schema does not have; a run directory's .hydra/config.yaml is untyped. Both
    pass through here, so an unknown key or a value of the wrong type is BadInput before anything runs.
    """
    plain = OmegaConf.to_container(cfg) if isinstance(cfg, DictConfig) else cfg  # a typed node would let extras in
    plain = _metres_written(plain)
    _unknown_keys(plain, schema.RiskplanConf, "")
    try:
        merged = OmegaConf.merge(schema.structured(), plain)
    except OmegaConfBaseException as err:
        raise BadInput(*explain(err)) from None
    resolved(merged)
    return merged


def _metres_written(data: typing.Any) -> typing.Any:
    """A recorded config's positions in metres, resolved to {metres: [x, y]} (a run's config as load_run reads it),
    written back as ${metres:x,y}: a mapping cannot replace the schema's cell [x, y] when merged, a string can."""
    if isinstance(data, dict):
        point = data.get("metres")
        if len(data) == 1 and isinstance(point, list) and all(isinstance(v, (int, float)) for v in point):
            return "${metres:" + ",".join(str(v) for v in point) + "}"
        return {k: _metres_written(v) for k, v in data.items()}
    if isinstance(data, list):
        return [_metres_written(v) for v in data]
    return data


def _composed(node: DictConfig) -> DictConfig:
    """A node composed onto the schema (Hydra's, with conf/config.yaml extending it) has every value typed and
    checked already: only a key added with `+key=...` and the interpolations are left to check. Merging it onto the
    schema again would change nothing and cost time."""
    _unknown_keys(OmegaConf.to_container(node), schema.RiskplanConf, "")
    resolved(node)
    return node


def resolved(cfg: DictConfig) -> dict:
    """The config with every interpolation resolved; one that cannot be (an unset variable, a missing key, a
    self-reference, a value of the wrong type) is BadInput naming its key and the interpolation."""
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as err:
        key = _dotted(getattr(err, "full_key", "") or "")
        text = OmegaConf.to_container(cfg, resolve=False)
        for part in filter(None, key.split(".")):
            text = text[int(part)] if isinstance(text, list) else text.get(part) if isinstance(text, dict) else text
        raise BadInput(
            f"key '{key}'" if key else "config",
            f"the interpolation {text} cannot be resolved ({interpolation_reason(err)}); give a plain "
            f"value or an interpolation of another key",
        ) from None


def _unknown_keys(data: typing.Any, node: typing.Any, path: str) -> None:
    """BadInput naming the first key of `data` that the schema type `node` does not have (lists descended)."""
    node = _unwrapped(node)
    if dataclasses.is_dataclass(node) and isinstance(data, dict):
        hints = _hints(node)
        for key, value in data.items():
            here = f"{path}.{key}" if path else str(key)
            if key not in hints:
                valid = [f.name for f in dataclasses.fields(node)]
                raise BadInput(
                    f"key '{here}'",
                    f"unknown key '{key}'; valid keys under '{path or 'top level'}': {', '.join(valid)}"
                    + did_you_mean(key, valid),
                )
            _unknown_keys(value, hints[key], here)
    elif typing.get_origin(node) is list and isinstance(data, list) and typing.get_args(node):
        for i, item in enumerate(data):
            _unknown_keys(item, typing.get_args(node)[0], f"{path}.{i}")


EXPECTED_TYPE = {"Integer": "a whole number", "Float": "a number", "Bool": "true or false", "Str": "a string"}


def choice_problem(err: Exception) -> tuple[str, str] | None:
    """(key, problem) when a composition error is a value outside a key's Choices (a schema Enum), else None: the
    same line as any other value outside a key's range, and like those it fails only its own job in a sweep."""
    cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
    key = getattr(cause, "full_key", None) or ""
    lines = str(cause).strip().splitlines()
    choice = re.match(r"Invalid value '(.*)', expected one of \[(.*)\]$", lines[0]) if lines else None
    if choice and key:
        got, valid = choice.groups()
        return _dotted(key), f"got '{got}'; expected one of {valid}" + did_you_mean(got, valid.split(", "))
    return None


def explain(err: Exception) -> tuple[str, str]:
    """One line naming the key behind a composition error and what would be valid. An error in a config file Hydra
    reports as "In 'experiment/mine': ConfigKeyError raised while composing config:" with the error on the lines
    below: that error is explained, and the file named after it."""
    cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
    key = getattr(cause, "full_key", None) or ""
    text = str(cause).strip()
    in_file = re.match(r"In '([^']+)': \w+ raised while composing config:\n(.+)", text, re.S)
    if in_file:
        found = re.search(r"full_key: (\S+)", in_file.group(2))
        where, problem = _explained(err, cause, found.group(1) if found else key, in_file.group(2).strip())
        return where, f"{problem} (in the config file {in_file.group(1)}.yaml)"
    return _explained(err, cause, key, text)


def _explained(err: Exception, cause: Exception, key: str, text: str) -> tuple[str, str]:
    message = text.splitlines()[0] if text else type(cause).__name__
    where = f"key '{_dotted(key)}'"
    choice = choice_problem(err)
    if choice:
        return choice
    if "Cannot merge DictConfig with ListConfig" in text:
        return _container_mismatch(text, key)
    if re.match(r"field '.*' is not Optional", message) and key:
        return where, f"got null; expected {expected_at(_dotted(key))}"
    if "is incompatible with type hint" in message and key:  # an item of a typed list: team.edges=[[0.5, 1]]
        return where, f"got {shown(getattr(cause, 'value', '?'))}; expected {expected_at(_dotted(key))}"
    sweep = re.match(r"(?:Ambiguous value for argument|Sweep parameters) '(.+?)'", message)
    if sweep:
        return (
            f"override '{sweep.group(1)}'",
            "gives several values (a sweep); train and check take one value "
            "per key: run a grid with riskplan sweep, or write a list as [a,b]",
        )
    converted = re.match(r"Value '(.*)' of type '\w+' could not be converted to (\w+)", message)
    if converted and key:
        value, kind = converted.groups()
        return where, f"got '{value}'; expected {EXPECTED_TYPE.get(kind, kind)}"
    if re.match(r"Value '.*' is not a valid bool", message) and key:
        return where, f"got '{getattr(cause, 'value', '?')}'; expected true or false"
    if message.startswith("Invalid value assigned:") and "is not a ListConfig, list or tuple" in message and key:
        return where, f"got {getattr(cause, 'value', '?')!r}; expected a list, e.g. [1, 2]"
    if re.match(r"Invalid type assigned: \w+ is not a subclass of \w+", message) and key:
        return _not_a_mapping(cause, key)
    if "not in struct" in message or (" not in '" in message and key):
        return _unknown_key(err, cause, key)
    missing = re.search(r"Could not find '([\w/]+?)/(/[^']*|[^'/]+)'", message)  # an option that is a path: //
    if missing:
        return _no_option(*missing.groups(), text)
    if "Could not override" in message:
        return f"key '{message.split(chr(39))[1]}'", "unknown key; run `riskplan check` to list the config's keys"
    return (f"key '{_dotted(key)}'" if key else "config"), message


def _not_a_mapping(cause: Exception, key: str) -> tuple[str, str]:
    """A plain value where the schema has a node (a mapping), or an entry past a list's end."""
    where = f"key '{_dotted(key)}'"
    index = re.fullmatch(r"(.*)\[(\d+)\]", key)
    if index and getattr(cause, "value", None) == {}:
        return where, (
            f"the list '{_dotted(index.group(1))}' has no entry {index.group(2)}; replace the whole list to add entries"
        )
    valid = valid_keys(re.sub(r"\[\d+\]", ".0", key).replace("..", "."))
    keys = f" with keys {', '.join(valid)}" if valid else ""
    return where, f"got {getattr(cause, 'value', '?')!r}; expected a mapping{keys}"


def _unknown_key(err: Exception, cause: Exception, key: str) -> tuple[str, str]:
    """A key the schema does not have: the keys its parent takes, and the nearest of them."""
    parent, _, name = _dotted(key).rpartition(".")
    valid = valid_keys(parent)
    entry, override = getattr(cause, "object_type", None), re.match(r"Could not override '(.+?)'", str(err))
    item = ""
    if not parent and override and dataclasses.is_dataclass(entry) and entry is not schema.RiskplanConf:
        # a mapping in a list (world.regions=[{nme: a}]): OmegaConf names its key without the list's path
        parent, valid = override.group(1), [f.name for f in dataclasses.fields(entry)]
        index = _item_holding(str(err), name)
        item = "" if index is None else f"{index}."
    node = getattr(cause, "parent_node", None)
    if valid is None and isinstance(node, collections.abc.Mapping):  # a node of Hydra's config: its own keys
        valid = sorted(str(k) for k in node.keys())
    if not valid:
        return f"key '{_dotted(key)}'", "unknown key; this node takes no new keys"
    return (
        f"key '{parent + '.' if parent else ''}{item}{name}'",
        f"unknown key '{name}'; valid keys under '{parent or 'top level'}': {', '.join(valid)}"
        + did_you_mean(name, valid),
    )


def _item_holding(text: str, name: str) -> int | None:
    """The index of the first mapping that holds the key `name` in the list an override gave, read back from
    Hydra's "To append to your config use +key=[...]" (OmegaConf's own error names no index); None when unknown."""
    from hydra.core.override_parser.overrides_parser import OverridesParser  # lazy: a rare error's path

    given = re.search(r"use \+(.+)$", text)
    try:
        value = OverridesParser.create().parse_override(given.group(1)).value() if given else None
    except Exception:  # a value Hydra parsed once already: anything odd just names no index
        return None
    items = value if isinstance(value, list) else []
    return next((i for i, item in enumerate(items) if isinstance(item, dict) and name in item), None)


def _no_option(group: str, option: str, text: str) -> tuple[str, str]:
    """A config group's option that does not exist: the group's options, riskplan's or (hydra/...) Hydra's. An
    option that is an absolute path reaches Hydra only through an interpolation (experiment=${oc.env:HOME})."""
    listed = re.search(r"Available options in '[^']*':\n((?:\t.*(?:\n|$))+)", text)
    options = sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))  # riskplan's own (not the schema's)
    if group.startswith("hydra/") and listed:  # Hydra's and its plugins' groups (with riskplan's additions)
        options = [o.strip() for o in listed.group(1).splitlines() if o.strip()]
    if option.startswith("/"):
        return f"key '{group}'", (
            f"got {option!r}, a path out of its folder (an interpolation gives one); give one of its options by "
            f"name: {', '.join(options)}, or your own with -cd DIR"
        )
    available = f"available: {', '.join(options) or 'none'}{did_you_mean(option, options)}"
    return f"key '{group}'", f"no option '{option}'; {available}"


METRES_HINT = "a position in metres over an [x, y] is written ${metres:X,Y}, which stands for {metres: [X, Y]}"


def _container_mismatch(text: str, key: str) -> tuple[str, str]:
    """A list given where the schema has a mapping (risk.schedule=[linear]), or a mapping where it has a list
    (world.size={a: 1}): what the key takes. A mapping over a position an earlier config gives as [x, y]
    (world.start={metres: [x, y]}), which OmegaConf merges into the list and cannot: how to write metres instead."""
    if key:
        hint = hint_at(_dotted(key))
        if dataclasses.is_dataclass(hint):
            return f"key '{_dotted(key)}'", f"got a list; expected {expected(hint)}"
        if typing.get_origin(hint) is list:
            return f"key '{_dotted(key)}'", f"got a mapping; expected {expected(hint)}"
        return f"key '{_dotted(key)}'", f"a mapping cannot replace the list an earlier config gives it; {METRES_HINT}"
    source = re.match(r"In '([^']+)'", text)
    where = f"In '{source.group(1)}': " if source else ""
    return "config", f"{where}a mapping cannot replace a list an earlier config gives the same key; {METRES_HINT}"


def metres(*point: float) -> dict:
    """The resolver ${metres:X,Y} (or four numbers, a rect's corners): {metres: [X, Y]}, a position in metres of
    world.map's frame. A string until resolved, it can replace a cell [x, y] that an earlier config gave, which a
    mapping cannot (OmegaConf merges a mapping into a list, and refuses)."""
    return {"metres": list(point)}


def register_metres() -> None:
    """Register the ${metres:...} resolver, once per process: before any config that may hold one is resolved (this
    module's import does it; riskplan.run.results, which resolves a run's saved config, calls it too)."""
    if not OmegaConf.has_resolver("metres"):
        OmegaConf.register_new_resolver("metres", metres)


register_metres()


def valid_keys(path: str) -> list[str] | None:
    """Field names of the schema node at a dotted path (list indices allowed), or None if it is not a dataclass."""
    node = hint_at(path)
    return [f.name for f in dataclasses.fields(node)] if dataclasses.is_dataclass(node) else None


def hint_at(path: str) -> typing.Any:
    """The schema's type at a dotted path (list indices allowed, Optional unwrapped); None where it has none."""
    node: typing.Any = schema.RiskplanConf
    for part in filter(None, path.split(".")):
        if part.isdigit() and typing.get_origin(node) is list:
            node = _unwrapped(typing.get_args(node)[0])
        elif dataclasses.is_dataclass(node) and not part.isdigit():
            node = _unwrapped(_hints(node).get(part))
        else:
            return None
    return node


@functools.cache
def _hints(node: type) -> dict[str, typing.Any]:
    return typing.get_type_hints(node)


def _unwrapped(hint: typing.Any) -> typing.Any:
    """X of Optional[X] (X | None); any other type as it is."""
    while typing.get_origin(hint) in (typing.Union, types.UnionType):
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    return hint


SCALARS = {bool: "true or false", int: "a whole number", float: "a number", str: "a string"}
PLURAL = {bool: "true or false values", int: "whole numbers", float: "numbers", str: "strings"}


def expected(hint: typing.Any, plural: bool = False) -> str:
    """What a value of a schema type is, as a message says it: "a list of whole numbers", "one of line, ring"."""
    hint = _unwrapped(hint)
    if typing.get_origin(hint) is list:
        return f"{'lists' if plural else 'a list'} of {expected(typing.get_args(hint)[0], plural=True)}"
    if dataclasses.is_dataclass(hint):
        return (
            f"{'mappings' if plural else 'a mapping'} with keys {', '.join(f.name for f in dataclasses.fields(hint))}"
        )
    if isinstance(hint, type) and issubclass(hint, schema.Choice):
        return f"{'names from' if plural else 'one of'} {', '.join(hint.names())}"
    return (PLURAL if plural else SCALARS).get(hint, "values" if plural else "a value")


def expected_at(path: str) -> str:
    """What the key at a dotted path takes: its field's own words (metadata `valid`), else its type's."""
    parent, _, name = path.rpartition(".")
    owner = hint_at(parent)
    if dataclasses.is_dataclass(owner):
        valid = next((f.metadata.get("valid") for f in dataclasses.fields(owner) if f.name == name), None)
        if valid:
            return valid
    return expected(hint_at(path))


def shown(value: typing.Any) -> str:
    """A value as a config writes it ([[1], [2]], {a: 1}, [signals]), not as Python prints it."""
    if isinstance(value, collections.abc.Mapping):
        return "{" + ", ".join(f"{k}: {shown(v)}" for k, v in value.items()) + "}"
    if isinstance(value, collections.abc.Sequence) and not isinstance(value, (str, bytes)):  # a ListConfig too
        return "[" + ", ".join(shown(v) for v in value) + "]"
    if isinstance(value, bool) or value is None:
        return {True: "true", False: "false", None: "null"}[value]
    return str(value)  # a Choice as its value


def check_flat_lists(node: typing.Any, path: str = "") -> None:
    """BadInput naming the first list of scalars of a typed config (train.theta0, world.size, policy.features,
    team.speeds, ...) that holds a list or a mapping: OmegaConf's typed lists take one as an item (theta0=[[1],[2]]),
    and the code that reads them would fail on it. Lists of lists (world.obstacles) OmegaConf checks itself."""
    for f in dataclasses.fields(node):
        value, hint, here = getattr(node, f.name), _unwrapped(_hints(type(node))[f.name]), f"{path}{f.name}"
        if dataclasses.is_dataclass(value):
            check_flat_lists(value, f"{here}.")
        elif isinstance(value, list) and typing.get_origin(hint) is list:
            item = _unwrapped(typing.get_args(hint)[0])
            for i, entry in enumerate(value):
                if dataclasses.is_dataclass(entry):
                    check_flat_lists(entry, f"{here}.{i}.")
                elif _scalar(item) and isinstance(entry, (list, dict)):
                    raise BadInput(here, f"got {shown(value)}; expected {expected(hint)}")


def _scalar(hint: typing.Any) -> bool:
    """A number, string, bool or Choice: what a flat list holds."""
    return hint in SCALARS or (isinstance(hint, type) and issubclass(hint, schema.Choice))


FLAG_NUMBERS = (0, 1)  # the integers a boolean key takes (OmegaConf takes any, and 5 or -1 is surely a slip)


def check_flags(overrides: list) -> None:
    """BadInput for a parsed override that gives a boolean key an integer other than 0 or 1 (`train.baseline=5`), or
    one inside the list or mapping it sets (`world.regions=[{risky: 2, ...}]`); a sweep's values each. OmegaConf
    would turn it into true before any later check could see it, so this looks at the override itself."""
    for override in overrides:
        hint = None if override.is_delete() or override.is_hydra_override() else hint_at(override.key_or_group)
        if not holds_flag(hint):  # most keys: nothing to enumerate (a sweep's range may have no end)
            continue
        try:
            values = override.sweep_iterator() if override.is_sweep_override() else [override.value()]
            for value in itertools.islice(values, FLAGS_CHECKED):
                check_flag(value, hint, override.key_or_group)
        except HydraException:  # glob(...) and interval(...) enumerate nothing here; no boolean key takes them
            continue


def check_file_value(key: str, value: typing.Any) -> None:
    """check_flags for a value a `-cd` config file puts at the dotted `key` (riskplan.config.user_files): Hydra's
    merge onto the schema would make any integer of a boolean key true."""
    hint = hint_at(key)
    if holds_flag(hint):
        check_flag(value, hint, key)


FLAGS_CHECKED = 10_000  # a sweep's values checked at most (a range of a boolean key past 1 fails at its 3rd)


def holds_flag(hint: typing.Any) -> bool:
    """Whether a value of the schema type `hint` is or holds a boolean."""
    hint = _unwrapped(hint)
    if hint is bool:
        return True
    if dataclasses.is_dataclass(hint):
        return any(holds_flag(h) for h in _hints(hint).values())
    return typing.get_origin(hint) is list and holds_flag(typing.get_args(hint)[0])


def check_flag(value: typing.Any, hint: typing.Any, key: str) -> None:
    """check_flags for one value of the schema type `hint`, descending into the lists and mappings it holds."""
    if hint is bool:
        number = value if isinstance(value, int) and not isinstance(value, bool) else None
        if isinstance(value, str) and re.fullmatch(r"[+-]?\d+", value.strip()):
            number = int(value)  # OmegaConf reads a string of digits as its integer
        if number is not None and number not in FLAG_NUMBERS:
            raise BadInput(f"key '{key}'", f"got {value!r}; expected true or false (or 1 or 0)")
    elif dataclasses.is_dataclass(hint) and isinstance(value, collections.abc.Mapping):
        for name, item in value.items():
            check_flag(item, _unwrapped(_hints(hint).get(name)), f"{key}.{name}")
    elif typing.get_origin(hint) is list and isinstance(value, list):
        for i, item in enumerate(value):
            check_flag(item, _unwrapped(typing.get_args(hint)[0]), f"{key}.{i}")


def _dotted(key: str) -> str:
    """world.regions[0].rect -> world.regions.0.rect, as users type it."""
    return key.replace("[", ".").replace("]", "")
