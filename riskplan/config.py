"""Compose a config exactly as the CLI does, and turn every Hydra/OmegaConf failure into BadInput."""

from __future__ import annotations

import dataclasses
import re
import typing
from pathlib import Path

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import DictConfig, open_dict
from omegaconf.errors import OmegaConfBaseException

from riskplan import schema
from riskplan.errors import BadInput

CONF_DIR = Path(__file__).resolve().parent / "conf"
GRAMMAR = "expected key=value (e.g. risk.beta=0.2), key=a,b for sweeps, or group=option (e.g. risk=neutral)"


def parse_overrides(overrides: list[str]) -> list:
    """Parse Hydra overrides; a syntax error is BadInput naming the override."""
    parser = OverridesParser.create()
    parsed = []
    for text in overrides:
        try:
            parsed.extend(parser.parse_overrides([text]))
        except HydraException:
            raise BadInput(f"override '{text}'", f"malformed; {GRAMMAR}") from None
        except RecursionError:  # the override grammar recurses once per bracket
            raise BadInput(f"override '{_short(text)}'", "is nested too deeply to parse; reward programs may nest "
                                                         "at most 32 levels") from None
        if not parsed[-1].key_or_group:  # `=5`: Hydra parses an empty key
            raise BadInput(f"override '{text}'", f"malformed; {GRAMMAR}")
    return parsed


def _short(text: str, limit: int = 60) -> str:
    """A long value shortened for a one-line message."""
    return text if len(text) <= limit else text[:limit] + "..."


def check_groups(parsed: list) -> None:
    """A config group set to null (`experiment=null`) is bad input naming the group's options, not a crash."""
    for override in parsed:
        group = override.key_or_group
        if override.value() is None and not override.is_delete() and group_options(group) is not None:
            raise BadInput(f"key '{group}'", f"cannot be null; available: {', '.join(group_options(group))}")


def group_options(group: str) -> list[str] | None:
    """The options of one of riskplan's own config groups (experiment, risk), None for anything else."""
    folder = CONF_DIR / group
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else None


def expand_overrides(overrides: list[str]) -> list[str]:
    """Make `...reward={...}` replace a distribution instead of merging into it (Hydra merges dicts)."""
    expanded = []
    for text, parsed in zip(overrides, parse_overrides(overrides)):
        key = parsed.key_or_group
        if key.endswith("reward") and not parsed.is_sweep_override() and isinstance(parsed.value(), dict):
            expanded.append(f"{key}=0")
        expanded.append(text)
    return expanded


def compose(overrides: list[str] | tuple[str, ...] = (), *, validate: bool = True) -> DictConfig:
    """Compose conf/ with overrides, check the schema, then (optionally) the model's own constraints."""
    overrides = list(overrides)
    parsed = parse_overrides(overrides)
    check_groups(parsed)
    expanded = expand_overrides(overrides)
    schema.register()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = hydra_compose(config_name="config", overrides=expanded, return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as err:
        raise BadInput(*explain(err)) from None
    except ValueError as err:  # Hydra's defaults list rejects some values outside its grammar
        raise BadInput("config", f"{_first_line(err)}; {GRAMMAR}") from None
    except RecursionError:
        raise BadInput("config", "is nested too deeply; reward programs may nest at most 32 levels") from None
    finally:
        GlobalHydra.instance().clear()
    from riskplan.hydra_checks import check_hydra_node

    check_hydra_node(cfg, [o for o in parsed if o.is_hydra_override()])
    with open_dict(cfg):
        del cfg["hydra"]
    check_schema(cfg)
    if validate:
        from riskplan.setup import build_setup

        build_setup(cfg)
    return cfg


def check_hydra_args(args: list[str]) -> None:
    """The overrides among a command line with Hydra's flags (--cfg job ...), composed and checked: a bad one, or a
    Hydra setting that names code, is BadInput before Hydra sees it."""
    valued = {"--cfg", "-c", "--package", "-p", "--info", "-i"}
    overrides, skip = [], False
    for arg in args:
        if skip and "=" not in arg:
            skip = False
            continue
        skip = arg in valued
        if not arg.startswith("-"):
            overrides.append(arg)
    compose(overrides, validate=False)


def check_schema(cfg) -> DictConfig:
    """The config merged onto the typed schema: keys added with `+key=...` or written by hand must exist there too.

    Hydra lets `+foo=1` add a key the schema does not have; a run directory's .hydra/config.yaml is untyped. Both
    pass through here, so an unknown key or a value of the wrong type is BadInput before anything runs.
    """
    from omegaconf import OmegaConf

    plain = OmegaConf.to_container(cfg) if isinstance(cfg, DictConfig) else cfg  # a typed node would let extras in
    _unknown_keys(plain, schema.RiskplanConf, "")
    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema.RiskplanConf), plain)
    except OmegaConfBaseException as err:
        raise BadInput(*explain(err)) from None
    resolved(merged)
    return merged


def resolved(cfg: DictConfig) -> dict:
    """The config with every interpolation resolved; one that cannot be (an unset variable, a missing key, a
    self-reference, a value of the wrong type) is BadInput naming its key and the interpolation."""
    from omegaconf import OmegaConf

    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as err:
        key = _dotted(getattr(err, "full_key", "") or "")
        text = OmegaConf.to_container(cfg, resolve=False)
        for part in filter(None, key.split(".")):
            text = text[int(part)] if isinstance(text, list) else text.get(part) if isinstance(text, dict) else text
        from riskplan.hydra_checks import interpolation_reason

        raise BadInput(f"key '{key}'" if key else "config",
                       f"the interpolation {text} cannot be resolved ({interpolation_reason(err)}); give a plain "
                       f"value or an interpolation of another key") from None


def _first_line(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def _unknown_keys(data: typing.Any, node: typing.Any, path: str) -> None:
    """BadInput naming the first key of `data` that the schema type `node` does not have (lists descended)."""
    while typing.get_origin(node) is typing.Union:  # Optional[X]
        node = next(a for a in typing.get_args(node) if a is not type(None))
    if dataclasses.is_dataclass(node) and isinstance(data, dict):
        hints = typing.get_type_hints(node)
        for key, value in data.items():
            here = f"{path}.{key}" if path else str(key)
            if key not in hints:
                valid = ", ".join(f.name for f in dataclasses.fields(node))
                raise BadInput(f"key '{here}'", f"unknown key '{key}'; valid keys under '{path or 'top level'}': {valid}")
            _unknown_keys(value, hints[key], here)
    elif typing.get_origin(node) in (list, typing.List) and isinstance(data, list) and typing.get_args(node):
        for i, item in enumerate(data):
            _unknown_keys(item, typing.get_args(node)[0], f"{path}.{i}")


EXPECTED_TYPE = {"Integer": "a whole number", "Float": "a number", "Bool": "true or false", "Str": "a string"}


def explain(err: Exception) -> tuple[str, str]:
    """One line naming the key behind a composition error and what would be valid."""
    cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
    key = getattr(cause, "full_key", None) or ""
    text = str(cause).strip()
    message = text.splitlines()[0] if text else type(cause).__name__
    where = f"key '{_dotted(key)}'"
    sweep = re.match(r"(?:Ambiguous value for argument|Sweep parameters) '(.+?)'", message)
    if sweep:
        return (f"override '{sweep.group(1)}'", "gives several values (a sweep); train and check take one value "
                                                 "per key: run a grid with riskplan sweep, or write a list as [a,b]")
    converted = re.match(r"Value '(.*)' of type '\w+' could not be converted to (\w+)", message)
    if converted and key:
        value, kind = converted.groups()
        return where, f"got '{value}'; expected {EXPECTED_TYPE.get(kind, kind)}"
    if re.match(r"Value '.*' is not a valid bool", message) and key:
        return where, f"got '{getattr(cause, 'value', '?')}'; expected true or false"
    if message.startswith("Invalid value assigned:") and "is not a ListConfig, list or tuple" in message and key:
        return where, f"got {getattr(cause, 'value', '?')!r}; expected a list, e.g. [1, 2]"
    subclass = re.match(r"Invalid type assigned: \w+ is not a subclass of (\w+)", message)
    if subclass and key:
        index = re.fullmatch(r"(.*)\[(\d+)\]", key)
        if index and getattr(cause, "value", None) == {}:
            return where, (f"the list '{_dotted(index.group(1))}' has no entry {index.group(2)}; "
                           f"replace the whole list to add entries")
        valid = valid_keys(re.sub(r"\[\d+\]", ".0", key).replace("..", "."))
        keys = f" with keys {', '.join(valid)}" if valid else ""
        return where, f"got {getattr(cause, 'value', '?')!r}; expected a mapping{keys}"
    if "not in struct" in message or (" not in '" in message and key):
        parent, _, name = _dotted(key).rpartition(".")
        valid = valid_keys(parent)
        if valid is None:
            return f"key '{_dotted(key)}'", "unknown key; this node takes no new keys"
        return f"key '{_dotted(key)}'", f"unknown key '{name}'; valid keys under '{parent or 'top level'}': {', '.join(valid)}"
    missing = re.search(r"Could not find '([\w/]+)/([^']+)'", message)
    if missing:
        group, option = missing.groups()
        listed = re.search(r"Available options in '[^']*':\n((?:\t.*(?:\n|$))+)", text)
        options = sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))  # riskplan's own (not the schema's)
        if not options and listed:  # a group of Hydra or its plugins, e.g. hydra/launcher
            options = [o.strip() for o in listed.group(1).splitlines() if o.strip()]
        return f"key '{group}'", f"no option '{option}'; available: {', '.join(options) or 'none'}"
    if "Could not override" in message:
        return f"key '{message.split(chr(39))[1]}'", "unknown key; run `riskplan check` to list the config's keys"
    return (f"key '{_dotted(key)}'" if key else "config"), message


def valid_keys(path: str) -> list[str] | None:
    """Field names of the schema node at a dotted path (list indices allowed), or None if it is not a dataclass."""
    node: typing.Any = schema.RiskplanConf
    for part in filter(None, path.split(".")):
        if part.isdigit():
            node = typing.get_args(node)[0] if typing.get_args(node) else None
        elif dataclasses.is_dataclass(node):
            hints = typing.get_type_hints(node)
            node = hints.get(part)
            while typing.get_origin(node) is typing.Union:  # Optional[X]
                node = next(a for a in typing.get_args(node) if a is not type(None))
        else:
            return None
    return [f.name for f in dataclasses.fields(node)] if dataclasses.is_dataclass(node) else None


def _dotted(key: str) -> str:
    """world.regions[0].rect -> world.regions.0.rect, as users type it."""
    return key.replace("[", ".").replace("]", "")
