"""Shared fixtures: a fast config for end-to-end runs, and helpers to build tiny worlds."""

from __future__ import annotations

import pytest

FAST = ["train.iterations=5", "train.samples=500", "train.eval_episodes=2000", "train.bootstrap=50", "train.paths=3"]


@pytest.fixture
def fast_overrides() -> list[str]:
    """Overrides that make a run take well under a second."""
    return list(FAST)
