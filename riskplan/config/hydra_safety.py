"""Checks of Hydra's own config node before Hydra runs: config strings are never code.

Hydra instantiates `_target_` classes (callbacks, launchers, sweepers) and hands its logging sections to
`logging.config.dictConfig`, which imports `class` and calls `()` factories. A user override can put any dotted
name there (`+hydra.callbacks.x._target_=os.makedirs`), so every such name is checked against an allow-list of
exact classes before anything is imported or run: Hydra's own plugins and callbacks, installed `hydra_plugins`
launchers and sweepers, the standard logging handlers and formatters, and riskplan's own classes.
"""

from __future__ import annotations

import functools
import importlib
import inspect
import re
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import InterpolationToMissingValueError, MissingMandatoryValue, OmegaConfBaseException

from riskplan.config.schema import CONF_DIR
from riskplan.util.errors import BadInput

# Modules whose classes may be named by _target_ (checked as exact classes of these modules, see _allowed_class).
TARGET_MODULES = (
    "hydra._internal.core_plugins.",
    "hydra.experimental.callbacks",
    "hydra_plugins.",
    "riskplan.",
    "optuna.samplers",
    "optuna.pruners",
)
# Modules whose classes logging's dictConfig may import (`class:`) or call (`():`).
LOGGING_MODULES = ("logging", "logging.handlers", "colorlog", "riskplan.")
STREAMS = ("ext://sys.stdout", "ext://sys.stderr")
CALLABLE_KEYS = ("_target_", "()", "class")
DOTTED = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)+")


OUTPUT_SUBDIR = ".hydra"  # the one hydra.output_subdir riskplan takes: where every reader of a run's config looks
PLAIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]*")
# a log inside the run's (or sweep's) directory, as Hydra's own config and riskplan's sweeps (job.log, sweep.log)
# name it
RUN_LOG_FILE = re.compile(
    r"\$\{hydra\.(runtime\.output_dir|sweep\.dir)\}/(\$\{hydra\.job\.name\}|[A-Za-z0-9_][A-Za-z0-9._-]*)\.log"
)


def check_hydra_node(cfg: DictConfig, hydra_overrides: list) -> None:
    """BadInput for a Hydra override that fails to resolve, names a file outside the run's directory, or names code
    to run."""
    for override in hydra_overrides:
        key = override.key_or_group
        if "/" in key or override.is_delete():
            continue
        try:
            value = OmegaConf.select(cfg, key, throw_on_missing=False)
        except (MissingMandatoryValue, InterpolationToMissingValueError):
            continue  # refers to a value Hydra sets when the job starts (hydra.runtime.output_dir, hydra.job.num, ...)
        except OmegaConfBaseException as err:
            reason = interpolation_reason(err)
            raise BadInput(
                f"key '{key}'",
                f"the interpolation {override.value()} cannot be resolved ({reason}); give a plain value",
            ) from None
        check_path_setting(key, value)
    hydra = OmegaConf.to_container(cfg.hydra, resolve=False)
    check_composed_paths(hydra)
    check_directories(hydra, {override.key_or_group for override in hydra_overrides})
    check_callables(hydra, "hydra")


DIRECTORIES = {"hydra.run.dir": ("run", "dir"), "hydra.sweep.dir": ("sweep", "dir")}


def check_directories(hydra: dict, typed: set[str]) -> None:
    """BadInput for a run's or a sweep's directory set in a config file (of -cd DIR): riskplan claims a fresh one
    itself or takes the one typed on the command line (`typed`: the Hydra keys given there), and the file's was
    silently ignored."""
    for key, (section, name) in DIRECTORIES.items():
        value = (hydra.get(section) or {}).get(name)
        if key not in typed and value != _defaults()[key]:
            raise BadInput(
                f"key '{key}'",
                f"got {value!r} from a config file; riskplan chooses where a run or sweep goes (a fresh folder under "
                f"outputs/): drop it from the file, or give it on the command line, {key}=DIR",
            )


@functools.cache
def _defaults() -> dict[str, str]:
    """riskplan's own hydra.run.dir and hydra.sweep.dir, as conf/config.yaml writes them."""
    hydra = yaml.safe_load((CONF_DIR / "config.yaml").read_text())["hydra"]
    return {key: hydra[section][name] for key, (section, name) in DIRECTORIES.items()}


def check_composed_paths(hydra: dict) -> None:
    """The file settings as composed, wherever they were set: a config file of `-cd DIR` (`# @package hydra`) sets
    them as an override does, so each is held to check_path_setting's rule."""
    job = hydra.get("job") or {}
    if isinstance(job, dict) and "name" in job:
        check_path_setting("hydra.job.name", job["name"])
    if "output_subdir" in hydra:
        check_path_setting("hydra.output_subdir", hydra["output_subdir"])
    for section in ("job_logging", "hydra_logging"):
        handlers = (hydra.get(section) or {}).get("handlers") or {}
        for name, handler in handlers.items() if isinstance(handlers, dict) else ():
            filename = handler.get("filename") if isinstance(handler, dict) else None
            if filename is not None and not (isinstance(filename, str) and RUN_LOG_FILE.fullmatch(filename)):
                check_path_setting(f"hydra.{section}.handlers.{name}.filename", filename)


def check_path_setting(key: str, value: Any) -> None:
    """Hydra's settings that name files: each stays a plain name inside the run's directory, so a value with path
    syntax cannot write (or break) a file elsewhere."""
    if key == "hydra.job.name" and not (isinstance(value, str) and PLAIN_NAME.fullmatch(value)):
        raise BadInput(
            f"key '{key}'",
            f"got {value!r}; it names the run's log file <name>.log in its directory: give a plain name of letters, "
            f"digits, '.', '_' and '-', e.g. riskplan",
        )
    if key == "hydra.output_subdir" and value != OUTPUT_SUBDIR:
        raise BadInput(f"key '{key}'", f"got {value!r}; riskplan keeps a run's config in {OUTPUT_SUBDIR}: drop it")
    if key.startswith(("hydra.job_logging.", "hydra.hydra_logging.")) and key.endswith(".filename"):
        raise BadInput(f"key '{key}'", f"got {value!r}; the run's log is <run directory>/<hydra.job.name>.log: drop it")


RESOLVER_CALL = re.compile(r"\$\{\s*([^\s:{}]+)\s*:")
FIXED_RESOLVERS = ("metres",)  # resolvers whose value depends on their arguments alone (riskplan.config.typed)


def check_resolvers(node: Any, path: str = "") -> None:
    """BadInput for a task value that calls a resolver whose answer can change between reads (${now:...},
    ${oc.env:...}): a run keeps its config's text in .hydra/config.yaml, and resuming, reporting or sweeping it again
    must read the same config."""
    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=False)
    if isinstance(node, dict):
        for key, value in node.items():
            check_resolvers(value, f"{path}.{key}" if path else str(key))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            check_resolvers(value, f"{path}.{index}")
    elif isinstance(node, str):
        for name in RESOLVER_CALL.findall(node):
            if name not in FIXED_RESOLVERS:
                raise BadInput(
                    f"key '{path}'",
                    f"got {node!r}; ${{{name}:...}} may give another value each time the config is read, so the run "
                    f"could not be resumed or reported as it ran: give a plain value (or ${{metres:...}} for a position)",
                )


def interpolation_reason(err: Exception) -> str:
    """The first line of an OmegaConf resolution error, without its wrapper text."""
    text = str(err).strip()
    line = text.splitlines()[0] if text else type(err).__name__
    return line.replace("KeyError raised while resolving interpolation: ", "").replace('"', "")


def check_callables(node: Any, path: str) -> None:
    """Walk Hydra's node: every _target_, logging class and () factory must be an allowed class."""
    if isinstance(node, dict):
        for key, value in node.items():
            here = f"{path}.{key}"
            if key in CALLABLE_KEYS:
                logging_section = "logging" in path.split(".")[1] if "." in path else False
                modules = LOGGING_MODULES if (logging_section or key != "_target_") else TARGET_MODULES
                if not _allowed_class(value, modules):
                    raise BadInput(
                        f"key '{here}'",
                        f"got {value!r}; config strings are never code: only Hydra's "
                        f"own, Hydra plugin, logging and riskplan classes are allowed "
                        f"here (see the README's security note)",
                    )
            elif key == "stream" and isinstance(value, str) and value.startswith("ext://") and value not in STREAMS:
                raise BadInput(f"key '{here}'", f"got {value!r}; a logging stream must be one of {', '.join(STREAMS)}")
            else:
                check_callables(value, here)
    elif isinstance(node, list):
        for index, value in enumerate(node):
            check_callables(value, f"{path}.{index}")


def _allowed_class(name: Any, modules: tuple[str, ...]) -> bool:
    """Whether `name` is exactly `module.Class` for an allowed module (checked before the module is imported)."""
    if not isinstance(name, str) or not DOTTED.fullmatch(name):
        return False
    module, _, attribute = name.rpartition(".")
    if not any(module == m.rstrip(".") or (m.endswith(".") and module.startswith(m)) for m in modules):
        return False
    try:
        found = getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError):
        return False
    # an attribute of an allowed module that is itself imported from elsewhere (os.system...) is refused; a class
    # a package re-exports from its own submodules (optuna.samplers.TPESampler, from optuna.samplers._tpe) is not
    home = getattr(found, "__module__", None) or ""
    return (
        inspect.isclass(found) and (home == module or home.startswith(module + ".")) and found.__qualname__ == attribute
    )
