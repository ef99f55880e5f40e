"""Compose a config exactly as the CLI does, and turn every Hydra/OmegaConf failure into BadInput."""

from __future__ import annotations

from pathlib import Path

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from riskplan import schema
from riskplan.errors import BadInput

CONF_DIR = Path(__file__).resolve().parent / "conf"


def parse_overrides(overrides: list[str]) -> list:
    """Parse Hydra overrides; a syntax error is BadInput naming the override."""
    parser = OverridesParser.create()
    parsed = []
    for text in overrides:
        try:
            parsed.extend(parser.parse_overrides([text]))
        except HydraException as err:
            reason = str(err).strip().splitlines()[-1] if str(err).strip() else "unparsable"
            raise BadInput(f"override '{text}'", f"malformed ({reason}); expected key=value, e.g. risk.beta=0.2") from None
    return parsed


def compose(overrides: list[str] | tuple[str, ...] = (), *, validate: bool = True) -> DictConfig:
    """Compose conf/ with overrides, check the schema, then (optionally) the model's own constraints."""
    overrides = list(overrides)
    parse_overrides(overrides)
    schema.register()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = hydra_compose(config_name="config", overrides=overrides)
    except (HydraException, OmegaConfBaseException) as err:
        raise BadInput(*_explain(err, overrides)) from None
    finally:
        GlobalHydra.instance().clear()
    if validate:
        from riskplan.setup import build_setup

        build_setup(cfg)
    return cfg


def _explain(err: Exception, overrides: list[str]) -> tuple[str, str]:
    """Name the key behind a composition error in one line."""
    key = getattr(err, "full_key", None) or ""
    message = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    if not key:
        for text in overrides:
            name = text.lstrip("+~").split("=", 1)[0]
            if name and name in message:
                key = name
                break
    return (f"key '{key}'" if key else "config"), message


def to_container(cfg: DictConfig) -> dict:
    """Plain dict of a resolved config."""
    return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
