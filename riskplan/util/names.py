"""Names made safe for a destination that takes fewer characters (a ROS topic, an MLflow key) stay distinct."""

from __future__ import annotations


def unique(token: str, taken: set[str]) -> str:
    """token, or token_1, token_2, ... : the first not in `taken`, which it joins. Two names that became the same
    token (a source 'x?' and a source 'x!', both 'x_') keep apart, the first keeping the plain token."""
    name, n = token, 1
    while name in taken:
        name, n = f"{token}_{n}", n + 1
    taken.add(name)
    return name
