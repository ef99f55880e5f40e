"""Names made safe for a destination that takes fewer characters (a ROS topic, an MLflow key) stay distinct."""

from __future__ import annotations

import re


def unique(token: str, taken: set[str]) -> str:
    """token, or token_1, token_2, ... : the first not in `taken`, which it joins. Two names that became the same
    token (a source 'x?' and a source 'x!', both 'x_') keep apart, the first keeping the plain token."""
    name, n = token, 1
    while name in taken:
        name, n = f"{token}_{n}", n + 1
    taken.add(name)
    return name


def mlflow_key(key: str) -> str:
    """A param or metric name as MLflow takes it: ASCII letters, digits and _-./ and spaces; any other character of
    a user's name (a source called 'sáfe 😀') becomes '_', as the TensorBoard and ROS 2 names do."""
    return re.sub(r"[^A-Za-z0-9_\-./ ]", "_", key)


def mlflow_keys(keys: dict) -> dict[str, str]:
    """Each key's MLflow name, distinct: sources named 'x?' and 'x!' are source_reached.x_ and source_reached.x__1,
    not one metric holding both."""
    taken: set[str] = set()
    return {key: unique(mlflow_key(key), taken) for key in keys}
