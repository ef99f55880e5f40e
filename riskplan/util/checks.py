"""The one way every domain check reports a problem: BadInput naming the key path, what is wrong, what is valid.

The checks themselves stay next to their concept (world, consensus, distributions, setup); these are the shapes
they share.
"""

from __future__ import annotations

import importlib.util
import math
import numbers
from typing import Any

from riskplan.util.errors import BadInput, MissingExtra


def require(ok: bool, key: str, problem: str) -> None:
    """BadInput(key, problem) unless ok."""
    if not ok:
        raise BadInput(key, problem)


def is_whole(value: Any) -> bool:
    """An integer (numpy's too) that is not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def integer_at_least(value: Any, key: str, low: int, meaning: str) -> int:
    """An integer >= low, or BadInput naming the key and what the value means."""
    require(is_whole(value) and value >= low, key, f"is {value!r}; {meaning} must be an integer >= {low}")
    return int(value)


def finite(value: Any, key: str) -> float:
    """A finite real number (a huge YAML integer included), or BadInput."""
    require(isinstance(value, numbers.Real) and not isinstance(value, bool), key, f"got {value!r}; expected a number")
    try:
        number = float(value)
    except OverflowError:  # a YAML integer with hundreds of digits
        raise BadInput(
            key,
            f"got an integer of about 2^{int(value).bit_length()}; expected a number a float can hold (|x| < 1.8e308)",
        ) from None
    require(math.isfinite(number), key, f"got {value!r}; expected a finite number")
    return number


def one_of(value: Any, key: str, valid: tuple[str, ...]) -> str:
    """One of the valid names, or BadInput listing them."""
    require(value in valid, key, f"unknown value {value!r}; valid: {', '.join(valid)}")
    return str(value)


def installed(module: str) -> bool:
    """Whether an optional module can be imported, without importing it (a dotted name imports its parents)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent that is missing, or a module whose __spec__ is unset
        return False


def require_installed(module: str, where: str, needs: str, extra: str, note: str = "") -> None:
    """MissingExtra unless `module` is installed: '<where>: needs <needs>, which is not installed; pip install
    'riskplan[<extra>]' <note>'."""
    if not installed(module):
        raise MissingExtra(
            where,
            f"needs {needs}, which is not installed; pip install 'riskplan[{extra}]'" + (f" {note}" if note else ""),
        )
