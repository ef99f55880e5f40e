"""Compose a config exactly as the CLI does, and turn every Hydra/OmegaConf failure into BadInput."""

from __future__ import annotations

import copy

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import DictConfig, open_dict
from omegaconf.errors import OmegaConfBaseException

from riskplan.config import schema
from riskplan.config.hydra_safety import check_hydra_node, check_resolvers
from riskplan.config.schema import CONF_DIR
from riskplan.config.typed import check_flags, explain, typed
from riskplan.config.validate import EXTRAS, check_extra
from riskplan.engine.step import RunSetup
from riskplan.run.build import build_setup
from riskplan.util.errors import BadInput, first_line

__all__ = [
    "CONF_DIR",
    "GRAMMAR",
    "check_extras",
    "check_hydra_args",
    "compose",
    "expand_overrides",
    "expand_shorthands",
    "explain",
    "parse_overrides",
]
GRAMMAR = "expected key=value (e.g. risk.beta=0.2), key=a,b for sweeps, or group=option (e.g. risk=neutral)"


def parse_overrides(overrides: list[str]) -> list:
    """Parse Hydra overrides; a syntax error is BadInput naming the override."""
    parser = OverridesParser.create()
    parsed = []
    for text in overrides:
        try:
            parsed.extend(parser.parse_overrides([text]))
        except HydraException:
            raise BadInput(f"override '{text}'", unquoted_problem(text) or f"malformed; {GRAMMAR}") from None
        except RecursionError:  # the override grammar recurses once per bracket
            raise BadInput(
                f"override '{_short(text)}'",
                "is nested too deeply to parse; reward programs may nest at most 32 levels",
            ) from None
        if not parsed[-1].key_or_group:  # `=5`: Hydra parses an empty key
            raise BadInput(f"override '{text}'", f"malformed; {GRAMMAR}")
    return parsed


# What Hydra's override grammar (OverrideLexer.g4) takes in an unquoted value, besides its structure ([]{}(),:=)
UNQUOTED = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-/\\+.$%*@?| \t[]{}(),:=~'\"")


def unquoted_problem(text: str) -> str | None:
    """Why a key=value override with characters Hydra takes only inside quotes (non-ASCII letters, symbols) does
    not parse, with the quoted form that does; None when that is not the problem."""
    key, equals, value = text.partition("=")
    if not equals or value[:1] in ("'", '"'):
        return None
    outside = list(dict.fromkeys(c for c in value if c not in UNQUOTED))
    if not outside and "=" in value[1:] and value[:1] not in ("=", "{", "["):  # a=b=c, not a==b or a mapping
        outside = ["="]
    if not outside:
        return None
    shown = ", ".join(f"'{c}'" for c in outside)
    quoted = f"{key}='" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"
    return (
        f"the value holds {shown}, which Hydra's override grammar takes only inside quotes; write {quoted} "
        f'(in a shell: "{quoted}")'
    )


def _short(text: str, limit: int = 60) -> str:
    """A long value shortened for a one-line message."""
    return text if len(text) <= limit else text[:limit] + "..."


def check_override_values(parsed: list) -> None:
    """What the parsed overrides give that composing would turn into something else, as bad input: a boolean key
    given an integer other than 0 or 1 (check_flags: OmegaConf makes it true); a config group set to null
    (`experiment=null`), naming the group's options, not a crash; an option given as a path out of the group's
    folder (`risk=../experiment/paper_team`, `experiment=/etc/x`), which Hydra would load from elsewhere. A sweep's
    values are checked each."""
    check_flags(parsed)
    for override in parsed:
        group = override.key_or_group
        if override.is_delete() or group_options(group) is None:
            continue
        value = override.value()
        if value is None:
            raise BadInput(f"key '{group}'", f"cannot be null; available: {', '.join(group_options(group))}")
        for option in getattr(value, "list", None) or [value]:
            text = str(option)
            if text.startswith("/") or ".." in text.split("/"):
                raise BadInput(
                    f"key '{group}'",
                    f"got {text!r}; give one of its options (no path out of its folder): "
                    f"{', '.join(group_options(group))}, or your own with -cd DIR",
                )


def group_options(group: str) -> list[str] | None:
    """The options of one of riskplan's own config groups (experiment, risk), None for anything else."""
    folder = CONF_DIR / group
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else None


EXTRA_KEYS = frozenset(key for key, _ in EXTRAS)  # team.backend, hydra/launcher, hydra/sweeper


def check_extras(overrides: list[str]) -> None:
    """An override choosing what an optional extra provides (team.backend=ray, hydra/launcher=submitit_slurm or
    ray, hydra/sweeper=optuna; a sweep's values included) when the extra is not installed: MissingExtra naming it
    and the pip install that fixes it, before anything is composed or written. An override that does not parse is
    left to the command's own checks."""
    parser = OverridesParser.create()
    for text in overrides:
        try:
            (override,) = parser.parse_overrides([text])
        except (HydraException, RecursionError, ValueError):
            continue
        if override.is_delete() or override.key_or_group not in EXTRA_KEYS:
            continue
        if not override.is_sweep_override():
            values = [override.value()]
        elif override.is_choice_sweep():
            try:
                values = list(override.sweep_string_iterator())
            except HydraException:  # glob(...) over a config group: its options are on disk, not in the override
                continue
        else:
            continue
        for value in values:
            check_extra(override.key_or_group, value)


def expand_overrides(overrides: list[str]) -> list[str]:
    """Make `...reward={...}` replace a distribution instead of merging into it (Hydra merges dicts), and expand
    the shorthands (`risk.schedule=linear` is `risk.schedule.kind=linear`)."""
    overrides = expand_shorthands(overrides)
    expanded = []
    for text, parsed in zip(overrides, parse_overrides(overrides)):
        key = parsed.key_or_group
        if key.endswith("reward") and not parsed.is_sweep_override() and isinstance(parsed.value(), dict):
            expanded.append(f"{key}=0")
        expanded.append(text)
    return expanded


SHORTHANDS = {"risk.schedule": "risk.schedule.kind"}  # a key given a plain value (or a sweep of them) -> its key


def expand_shorthands(overrides: list[str]) -> list[str]:
    """`risk.schedule=linear` (or `=none,linear` in a sweep) -> `risk.schedule.kind=...`; a mapping value
    (`risk.schedule={kind:linear,iterations:50}`) and every other override are left as they are."""
    out = []
    for text, parsed in zip(overrides, parse_overrides(overrides)):
        key = parsed.key_or_group
        if (
            key in SHORTHANDS
            and not parsed.is_delete()
            and (parsed.is_sweep_override() or not isinstance(parsed.value(), (dict, list)))
        ):
            prefix, _, value = text.partition("=")
            text = prefix.replace(key, SHORTHANDS[key], 1) + "=" + value
        out.append(text)
    return out


def compose(
    overrides: list[str] | tuple[str, ...] = (), *, validate: bool = True, with_hydra: bool = False
) -> DictConfig:
    """Compose conf/ with overrides, check the schema, then (optionally) the model's own constraints.

    With `with_hydra`, the config checked is returned with its hydra node (what Hydra would run)."""
    return _compose(overrides, validate, with_hydra)[0]


def compose_run(overrides: list[str] | tuple[str, ...] = ()) -> tuple[DictConfig, RunSetup]:
    """`riskplan train`'s one route: the config composed and typed once, with its hydra node, and the RunSetup built
    from it once; riskplan.experiments.hydra_app.run_composed runs both as they are."""
    return _compose(overrides, True, True)


def _compose(overrides, validate: bool, with_hydra: bool) -> tuple[DictConfig, RunSetup | None]:
    """compose(), and the RunSetup it built to validate (None without `validate`)."""
    overrides = list(overrides)
    parsed = parse_overrides(overrides)
    check_override_values(parsed)
    check_extras(overrides)  # before composing: Hydra would only say that a plugin's option does not exist
    for override in parsed:
        if override.key_or_group == "hydra.mode":
            raise BadInput(
                f"override '{override.input_line}'",
                "riskplan train and check run one experiment; run several with riskplan sweep (e.g. seed=0,1,2)",
            )
    expanded = expand_overrides(overrides)
    schema.register()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = hydra_compose(config_name="config", overrides=expanded, return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as err:
        raise BadInput(*explain(err)) from None
    except ValueError as err:  # Hydra's defaults list rejects some values outside its grammar
        raise BadInput("config", f"{first_line(err)}; {GRAMMAR}") from None
    except RecursionError:
        raise BadInput(
            "config",
            "is nested too deeply: a config file whose defaults include itself, or values nested past Python's limit "
            "(reward programs may nest at most 32 levels)",
        ) from None
    finally:
        GlobalHydra.instance().clear()
    check_hydra_node(cfg, [o for o in parsed if o.is_hydra_override()])
    full = copy.deepcopy(cfg) if with_hydra else None
    with open_dict(cfg):
        del cfg["hydra"]
    check_resolvers(cfg)
    if validate:  # the schema's checks, then the model's, as the RunSetup is built
        setup = build_setup(cfg)
    else:
        typed(cfg)  # the schema's checks alone
        setup = None
    return (cfg if full is None else full), setup


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
