"""Output folders: fresh timestamped directories, and paths written as Hydra override values."""

from __future__ import annotations

import datetime as dt
from pathlib import Path


def claim_dir(root: Path, suffix: str = "") -> Path:
    """Create root/<YYYY-MM-DD_HH-MM-SS><suffix>, or with _1, _2, ... when taken: mkdir is the lock."""
    base = Path(root) / f"{dt.datetime.now():%Y-%m-%d_%H-%M-%S}{suffix}"
    candidate, number = base, 1
    while True:
        try:
            candidate.mkdir(parents=True)
            return candidate
        except FileExistsError:
            candidate = base.with_name(f"{base.name}_{number}")
            number += 1


def hydra_quote(value: Path | str) -> str:
    """A path (or key) as a quoted Hydra override value."""
    return "'" + str(value).replace("\\", "\\\\").replace("'", "\\'") + "'"
