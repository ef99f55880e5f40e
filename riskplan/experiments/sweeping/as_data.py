"""A sweep's jobs as data: the config composed once per choice of config groups, and each job's plain key
overrides (seed=3, risk.beta=0.1) applied to that composition's frozen config and plain dict, instead of one
Hydra composition (or deep copy) per job, which costs milliseconds a job and seconds a sweep.

An override's value is converted once by OmegaConf itself, on a scratch copy of the composition, so each job gets
exactly the value and type Hydra would give it (0.1 on a float key, an Enum member on a Choice key, a list of typed
entries on a list key, a mapping merged into the key's own as Hydra merges it). Anything else (a config group, a
`+key` or `~key`, an interpolation, a key inside a list, a list or mapping set after a key inside it, or a
composition that interpolates) is composed by Hydra as before: `job` returns None for it.
"""

from __future__ import annotations

import collections
import copy
import dataclasses
import enum
import os
from dataclasses import dataclass
from typing import Any

from hydra._internal.config_loader_impl import ConfigLoaderImpl
from hydra.core.override_parser.types import Override, OverrideType
from hydra.errors import HydraException
from omegaconf import (
    BooleanNode,
    Container,
    DictConfig,
    FloatNode,
    IntegerNode,
    OmegaConf,
    StringNode,
    open_dict,
    read_write,
)
from omegaconf.errors import OmegaConfBaseException

from riskplan.config.schema import CONF_DIR, RiskplanConf
from riskplan.config.typed import typed
from riskplan.util.errors import BadInput

HYDRA = "hydra"  # Hydra's own node: no part of a run's config (its interpolations are Hydra's)


@dataclass(frozen=True)
class JobConfig:
    """One job's config without a composition: frozen (what build_setup takes) and plain (resolved, Choice keys
    as Enum members: what run_identity hashes; `yaml_ready` turns it into what .hydra/config.yaml holds)."""

    params: RiskplanConf
    plain: dict


@dataclass(frozen=True)
class Change:
    """A job's plain key override: its key's path, the value typed (what RiskplanConf holds there) and plain (what
    the plain dict holds), and whether it sets a whole list or mapping."""

    path: tuple[str, ...]
    typed: Any
    plain: Any
    whole: bool = False


class Composition:
    """One composition of the config (a choice of config groups) and the jobs that differ from it in plain keys."""

    def __init__(self, cfg: DictConfig):
        self.cfg = _task(cfg)
        self._values: dict[str, Change | None] = {}  # override line -> its change
        self._scratch: dict[str, DictConfig] = {}  # key -> a copy of cfg that its overrides are tried on
        self.params: RiskplanConf | None = None
        self.plain: dict = {}
        if _interpolates(OmegaConf.to_container(self.cfg, resolve=False)):
            return  # a key may depend on another: setting one alone would not update the other
        try:
            self.params = typed(self.cfg)
        except BadInput:  # its jobs fail through Hydra's path, which names the key
            return
        self.plain = OmegaConf.to_container(self.cfg, resolve=True)

    def job(self, overrides: list[Override]) -> JobConfig | None:
        """The config of the job that sets these plain keys on this composition; None when one of them needs
        Hydra (see the module docstring)."""
        if self.params is None:
            return None
        changes = []
        for override in overrides:
            change = self._values.get(override.input_line, ...)
            if change is ...:
                change = self._values[override.input_line] = self._convert(override)
            if change is None or (change.whole and any(_within(done.path, change.path) for done in changes)):
                return None  # a list or mapping set after a key inside it: computed on the composition, it would
                # drop what that key set, where Hydra keeps it
            changes.append(change)
        params, plain = self.params, dict(self.plain)
        for change in changes:
            params = _replaced(params, change.path, change.typed)
            plain = _set(plain, change.path, change.plain)
        return JobConfig(params, plain)

    def _convert(self, override: Override) -> Change | None:
        """The change a plain key override makes, its value as OmegaConf types it on this key; None otherwise."""
        key = override.key_or_group
        path = tuple(key.split("."))
        if (
            override.type != OverrideType.CHANGE
            or override.package is not None
            or override.is_sweep_override()
            or path[0] == HYDRA
            or not all(part.isidentifier() for part in path)
            or "${" in override.input_line
            or OmegaConf.select(self.cfg, key, default=...) is ...
        ):
            return None
        value = _as_typed(self.cfg, path, override.value())
        if value is not None:
            return Change(path, value, value)
        whole = isinstance(OmegaConf.select(self.cfg, key), Container) or isinstance(override.value(), (list, dict))
        if whole:  # Hydra merges a mapping into the key's own: each on a fresh copy, so no job's merge is another's
            scratch = copy.deepcopy(self.cfg)
        else:
            scratch = self._scratch.get(key)
            if scratch is None:
                scratch = self._scratch[key] = copy.deepcopy(self.cfg)
        try:
            ConfigLoaderImpl._apply_overrides_to_config([override], scratch)
            value = OmegaConf.select(scratch, key)
            if not isinstance(value, Container):
                return Change(path, value, value, whole)
            return Change(path, OmegaConf.to_object(value), OmegaConf.to_container(value, resolve=True), whole)
        except (HydraException, OmegaConfBaseException):
            return None  # a value the key refuses: Hydra's path says why


KEPT = 32  # compositions a process keeps (a reproduction's sweeps and checks choose about ten sets of groups)
_kept: collections.OrderedDict[tuple, tuple[tuple, Composition]] = collections.OrderedDict()


def shared(groups: tuple[str, ...], searchpath: list, compose) -> Composition:
    """The Composition of these config-group choices (`compose()` composes them), kept for this process while the
    config files it reads are unchanged: a reproduction's checks and sweeps choose the same few groups again and
    again, and a composition costs about 70 ms. `searchpath`: the parsed hydra.searchpath overrides (--config-dir);
    a search path that is not a local directory (pkg://) is composed every time."""
    files = _config_files(searchpath)
    if files is None:
        return Composition(compose())
    key = (groups, tuple(o.input_line for o in searchpath))
    found = _kept.get(key)
    if found is not None and found[0] == files:
        _kept.move_to_end(key)
        return found[1]
    composition = Composition(compose())
    _kept[key] = (files, composition)
    while len(_kept) > KEPT:
        _kept.popitem(last=False)
    return composition


def _config_files(searchpath: list) -> tuple | None:
    """Every file under conf/ and the search path's directories, with its modification time and size (what a
    composition may read); None when the search path holds anything but local directories."""
    roots = [str(CONF_DIR)]
    for override in searchpath:
        value = override.value()
        for entry in value if isinstance(value, list) else [value]:
            if not isinstance(entry, str) or not entry.startswith("file://"):
                return None
            roots.append(entry.removeprefix("file://"))
    listing = []
    for root in roots:
        for folder, _, names in os.walk(root, followlinks=True):
            for name in sorted(names):
                path = os.path.join(folder, name)
                try:
                    stat = os.stat(path)
                except OSError:
                    return None
                listing.append((path, stat.st_mtime_ns, stat.st_size))
    return tuple(listing)


def _as_typed(cfg: DictConfig, path: tuple[str, ...], value: Any) -> Any:
    """A number, string or bool as OmegaConf would store it on the typed key at `path` (an int on a float key
    becomes a float), without trying it on a copy; None when only OmegaConf can tell (an Enum key, None, a
    string on a number key)."""
    node = cfg
    for part in path:
        node = node._get_node(part)
    kind = type(value)
    if isinstance(node, IntegerNode) and kind is int:
        return value
    if isinstance(node, FloatNode) and kind in (int, float):
        return float(value)
    if (isinstance(node, StringNode) and kind is str) or (isinstance(node, BooleanNode) and kind is bool):
        return value
    return None


def _task(cfg: DictConfig) -> DictConfig:
    """The run's part of a composition: without Hydra's node (a copy, as run_job hands it to the task)."""
    if HYDRA not in cfg:
        return cfg
    task = copy.deepcopy(cfg)
    with read_write(task), open_dict(task):
        del task[HYDRA]
    return task


def yaml_ready(data: Any) -> Any:
    """A plain config as OmegaConf saves it: Enum members by their names."""
    if isinstance(data, dict):
        return {k: yaml_ready(v) for k, v in data.items()}
    if isinstance(data, list):
        return [yaml_ready(v) for v in data]
    return data.name if isinstance(data, enum.Enum) else data


def _replaced(node: Any, path: tuple[str, ...], value: Any) -> Any:
    """A frozen dataclass with the field at `path` set to `value` (the nodes above it copied, nothing changed)."""
    head, rest = path[0], path[1:]
    inner = value if not rest else _replaced(getattr(node, head), rest, value)
    return dataclasses.replace(node, **{head: inner})


def _within(path: tuple[str, ...], outer: tuple[str, ...]) -> bool:
    """Whether `path` is `outer` or a key inside it."""
    return path[: len(outer)] == outer


def _set(data: dict, path: tuple[str, ...], value: Any) -> dict:
    """A copy of the dict with `path` set: the dicts along the path are copied, the rest shared."""
    data = dict(data)
    head, rest = path[0], path[1:]
    data[head] = value if not rest else _set(data[head], rest, value)
    return data


def _interpolates(data: Any) -> bool:
    """Whether any string in the data holds an interpolation."""
    if isinstance(data, dict):
        return any(_interpolates(v) for v in data.values())
    if isinstance(data, list):
        return any(_interpolates(v) for v in data)
    return isinstance(data, str) and "${" in data
