"""A user's config folder (`-cd DIR`) read as YAML before Hydra composes it: a file Hydra would fail on with a
traceback, or expand without end, is one line naming the file, its line and what is wrong."""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from riskplan.util.errors import BadInput

MAX_BYTES = 10_000_000  # a config file's size: far above any experiment, far below what composes in minutes
MAX_NODES = 1_000_000  # values a file holds once its aliases (*name) are expanded: a "billion laughs" holds 9^9
CODE_TAGS = "tag:yaml.org,2002:python/"  # !!python/object and the like: constructors that run code
HEADER = re.compile(r"\s*#\s*@")  # Hydra's header line, `# @package world`
PACKAGE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")  # _global_, _group_, world.sources
MAX_FOLDERS = 2_000  # folders a -cd DIR may hold outside those skipped: a config folder holds a few, `-cd /` millions
OUTPUTS = "outputs"  # riskplan's runs and sweeps, written beside a project's configs
ENVIRONMENT = ("pyvenv.cfg", "conda-meta")  # what a virtualenv's or a conda environment's folder holds


def check_config_files(folder: Path, check_value: Callable[[str, Any], None] | None = None) -> None:
    """BadInput for the first YAML file Hydra could load from `folder` (`config_files`) that is not UTF-8, not
    valid YAML, gives a key twice, holds a tag that makes Python objects, or expands (through its aliases) past
    MAX_NODES values; then `check_value(key, value)` on each top-level value under the dotted key Hydra puts it at
    (riskplan.config.typed.check_file_value: a boolean given another integer), its BadInput naming the file and
    line. The caller passes it: the schema it reads imports Hydra, which `riskplan --help` does not."""
    for path in config_files(folder):
        _check_file(path, folder, check_value)


def config_files(folder: Path) -> list[Path]:
    """The `*.yaml` files of `folder` that Hydra could load from it as a search-path entry, sorted by folder.

    Hydra loads DIR/<group>/<option>.yaml for a group at any depth (`experiment=sub/mine`, `+mine=x`) and DIR's own
    top-level files through a defaults list (`- /name`), so every folder is walked (through links, each once)
    except those that are never config groups: hidden ones (Hydra's run records in .hydra, .git, .venv), outputs/
    and Python environments. More than MAX_FOLDERS left is BadInput: not a config folder (`-cd /`, a home)."""
    found, seen = [], set()
    for root, dirs, files in os.walk(folder, followlinks=True):
        here = _folder_id(root)
        if here is None or here in seen or any(mark in files or mark in dirs for mark in ENVIRONMENT):
            dirs.clear()  # gone, a link back to a folder walked already, or a Python environment
            continue
        seen.add(here)
        if len(seen) > MAX_FOLDERS:
            raise BadInput(
                str(folder),
                f"holds more than {MAX_FOLDERS:,} folders (besides hidden ones, {OUTPUTS}/ and Python environments), "
                f"and Hydra could load a config from any of them; give the folder that holds your config groups "
                f"(e.g. my_configs, with my_configs/experiment/mine.yaml)",
            )
        dirs[:] = sorted(name for name in dirs if not name.startswith(".") and name != OUTPUTS)
        found += [Path(root, name) for name in sorted(files) if name.endswith(".yaml") and Path(root, name).is_file()]
    return found


def _folder_id(path: str) -> tuple[int, int] | None:
    """(device, inode) of a folder, the same through every link to it; None once it is gone (a process's in /proc)."""
    try:
        info = os.stat(path)
    except OSError:
        return None
    return info.st_dev, info.st_ino


def _check_file(path: Path, folder: Path, check_value: Callable[[str, Any], None] | None) -> None:
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise BadInput(str(path), f"is {size / 1e6:.0f} MB; a config file holds at most {MAX_BYTES / 1e6:.0f} MB")
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        line = data[: err.start].count(b"\n") + 1
        raise BadInput(
            str(path), f"is not UTF-8 text (byte 0x{data[err.start]:02x} on line {line}); save it as UTF-8"
        ) from None
    _check_header(text, path)
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)  # the node graph: aliases shared, nothing expanded
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise BadInput(str(path), f"is not valid YAML{at}: {err.problem or err.context}") from None
    except RecursionError:  # PyYAML's composer recurses once per level
        raise BadInput(str(path), "is nested too deeply to read (thousands of levels); flatten it") from None
    if root is not None and not isinstance(root, yaml.MappingNode):
        what = "a list" if isinstance(root, yaml.SequenceNode) else "a single value"
        raise BadInput(str(path), f"holds {what} at its top level; a config file is a mapping of keys, e.g. seed: 3")
    if root is not None:
        _check_nodes(root, path)
        if check_value is not None:
            _check_values(root, path, _package(text, path, folder), check_value)


def _check_header(text: str, path: Path) -> None:
    """The `# @package` header, read as Hydra reads it (the `# @key value` lines before anything else): a value
    that is no package (`../../etc`) failed later as "Key '' not in 'RiskplanConf'"."""
    for line in text.splitlines():
        line = line.strip()
        if not line:
            continue
        if not HEADER.match(line):
            return  # Hydra's header ends at the first other line
        words = line.lstrip("#").split()
        if words[0] == "@package" and not (len(words) == 2 and PACKAGE.fullmatch(words[1])):
            raise BadInput(
                str(path),
                f"has the header '{line}'; a package is _global_, _group_ or a dotted key such as world.sources "
                f"(e.g. # @package _global_)",
            )


def _package(text: str, path: Path, folder: Path) -> str:
    """The dotted key the file's values land under, as Hydra places them: its `# @package` header, else its group
    (`world/mine.yaml` -> world); a file at the folder's top level is global."""
    group = ".".join(path.parent.relative_to(folder).parts)
    for line in filter(None, map(str.strip, text.splitlines())):
        if not HEADER.match(line):
            break
        words = line.lstrip("#").split()
        if words[0] == "@package":
            return {"_global_": "", "_group_": group}.get(words[1], words[1])
    return group


def _check_values(root: yaml.MappingNode, path: Path, package: str, check_value: Callable[[str, Any], None]) -> None:
    """check_value on each top-level value of the file (its defaults list aside), under its dotted key."""
    for key, value in root.value:
        if isinstance(key, yaml.ScalarNode) and key.value != "defaults":
            full = f"{package}.{key.value}" if package else key.value
            try:
                check_value(full, yaml.safe_load(yaml.serialize(value)))
            except BadInput as err:
                raise BadInput(str(path), f"line {key.start_mark.line + 1}: {err.where}: {err.problem}") from None


def _check_nodes(root: yaml.Node, path: Path) -> None:
    """Duplicate keys, code tags and the expanded size, each node visited once (an alias is a shared node)."""
    sizes: dict[int, int] = {}
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:  # post-order without recursion: a file nested 100,000 deep is no RecursionError
        node, children_done = stack.pop()
        if id(node) in sizes:
            continue
        if node.tag.startswith(CODE_TAGS):
            raise BadInput(
                str(path),
                f"line {node.start_mark.line + 1}: the tag {node.tag.replace('tag:yaml.org,2002:', '!!')} makes a "
                f"Python object; a config file holds plain values",
            )
        children = _children(node, path)
        if not children_done:
            stack.append((node, True))
            stack.extend((child, False) for child in children if id(child) not in sizes)
            continue
        sizes[id(node)] = 1 + sum(sizes[id(child)] for child in children)
        if sizes[id(node)] > MAX_NODES:
            raise BadInput(
                str(path),
                f"line {node.start_mark.line + 1}: expands to more than {MAX_NODES:,} values through its aliases "
                f"(*name); write the values out, or use fewer aliases",
            )


def _children(node: yaml.Node, path: Path) -> list[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        seen: dict[object, int] = {}
        for key, _ in node.value:
            if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                if key.value in seen:
                    raise BadInput(
                        str(path),
                        f"line {key.start_mark.line + 1}: the key '{key.value}' is given twice (first on line "
                        f"{seen[key.value]}); give it once",
                    )
                seen[key.value] = key.start_mark.line + 1
        return [child for pair in node.value for child in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []
