"""The Python API's arguments checked where they enter (riskplan/__init__.py): a wrong type is BadInput naming the
argument, as the CLI's bad input is, never a TypeError from deep inside Hydra or pathlib."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from riskplan.util.errors import BadInput


def overrides_list(value: Any, name: str = "overrides") -> list[str]:
    """A list of override strings (a tuple or other iterable of them is fine); a lone string is refused, since it
    would be taken character by character."""
    if isinstance(value, (str, bytes)):
        raise BadInput(name, f"got the string {value!r}; give a list of overrides, e.g. [{value!r}]")
    if isinstance(value, Mapping):  # its keys alone would be taken for overrides
        shown = [f"{key}={item}" for key, item in value.items()][:2]
        raise BadInput(name, f"got a mapping {value!r}; give a list of overrides key=value, e.g. {shown}")
    try:
        items = list(value)
    except TypeError:
        raise BadInput(name, f"got {value!r}; give a list of overrides, e.g. ['risk=neutral', 'seed=3']") from None
    for item in items:
        if not isinstance(item, str):
            raise BadInput(name, f"holds {item!r}; every override is a string key=value, e.g. 'seed=3'")
    return items


def a_path(value: Any, name: str) -> Path:
    """A non-empty str or os.PathLike as a Path."""
    if isinstance(value, Path) or (isinstance(value, str) and value.strip()):
        return Path(value)
    if hasattr(value, "__fspath__") and not isinstance(value, bytes):
        return Path(value)
    raise BadInput(name, f"got {value!r}; give a directory path (a str or a pathlib.Path)")


def paths_list(value: Any, name: str) -> list[Path]:
    """One path, or a non-empty list of them."""
    if isinstance(value, (str, Path)):
        return [a_path(value, name)]
    try:
        items = list(value)
    except TypeError:
        raise BadInput(name, f"got {value!r}; give a path or a list of paths") from None
    if not items:
        raise BadInput(name, "is empty; give a run, sweep or reproduce directory")
    return [a_path(item, name) for item in items]


def optional_count(value: Any, name: str) -> int | None:
    """None, or a whole number >= 1."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise BadInput(name, f"got {value!r}; give a whole number >= 1, or None")
    return int(value)


def optional_flag(value: Any, name: str) -> bool | None:
    """None, True or False (a string such as 'no' is not taken for true)."""
    if value is None or isinstance(value, bool):
        return value
    raise BadInput(name, f"got {value!r}; give True, False or None")


def a_flag(value: Any, name: str) -> bool:
    """True or False (a string such as 'no' is not taken for true)."""
    if isinstance(value, bool):
        return value
    raise BadInput(name, f"got {value!r}; give True or False")


def formats_list(value: Any, name: str = "formats") -> list[str]:
    """Figure formats: a list of names, or one comma-separated string ('png,pdf')."""
    if isinstance(value, str):
        return [part.strip() for part in value.split(",")]
    try:
        items = list(value)
    except TypeError:
        raise BadInput(name, f"got {value!r}; give a list of formats, e.g. ['png', 'pdf']") from None
    if not all(isinstance(item, str) for item in items):
        raise BadInput(name, f"got {value!r}; give a list of formats, e.g. ['png', 'pdf']")
    return items
