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
from omegaconf import DictConfig
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
    return parsed


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
    expanded = expand_overrides(overrides)
    schema.register()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = hydra_compose(config_name="config", overrides=expanded)
    except (HydraException, OmegaConfBaseException) as err:
        raise BadInput(*explain(err)) from None
    finally:
        GlobalHydra.instance().clear()
    if validate:
        from riskplan.setup import build_setup

        build_setup(cfg)
    return cfg


def explain(err: Exception) -> tuple[str, str]:
    """One line naming the key behind a composition error and what would be valid."""
    cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
    key = getattr(cause, "full_key", None) or ""
    message = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
    if "not in struct" in message or (" not in '" in message and key):
        parent, _, name = _dotted(key).rpartition(".")
        valid = valid_keys(parent)
        if valid is None:
            return f"key '{_dotted(key)}'", "unknown key; this node takes no new keys"
        return f"key '{_dotted(key)}'", f"unknown key '{name}'; valid keys under '{parent or 'top level'}': {', '.join(valid)}"
    missing = re.search(r"Could not find '([\w/]+)/([^']+)'", message)
    if missing:
        group, option = missing.groups()
        options = sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))
        return f"key '{group}'", f"no option '{option}'; available: {', '.join(options)}"
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
