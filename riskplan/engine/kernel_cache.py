"""Keep numba's on-disk kernel cache in step with the engine's sources.

numba checks a cached kernel against its own file's time stamp only, and it unpickles the cache's index (whose
types name engine classes) before that check. So an edit to a helper in another file (rng.py, dynamics.py) keeps
a stale kernel, and a renamed class makes the load fail outright. Once per process, this compares a stamp of
every engine source (path, size, mtime) with the one saved beside the cache, and on a change removes riskplan's
cached kernels, so that they compile afresh from the sources as they are. A cache that NUMBA_CACHE_DIR puts
elsewhere is the user's, and left alone.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1]  # riskplan/
ENGINE = PACKAGE / "engine"
STAMP = ENGINE / "__pycache__" / "riskplan-kernels.stamp"
CACHE_SUFFIXES = (".nbi", ".nbc")  # numba's index and data files


def sources_stamp(root: Path = ENGINE) -> str:
    """A digest of every .py file under `root`: its path, size and modification time."""
    digest = hashlib.sha1()
    for path in sorted(root.rglob("*.py")):
        info = path.stat()
        digest.update(f"{path.relative_to(root)}\0{info.st_size}\0{info.st_mtime_ns}\n".encode())
    return digest.hexdigest()


def clear_stale(package: Path = PACKAGE, stamp_file: Path = STAMP, stamp: str | None = None) -> int:
    """Remove the package's cached kernels when the engine's sources changed since the stamp was written; return
    how many files went. Nothing is raised: a read-only install keeps its cache (it cannot have been edited)."""
    stamp = sources_stamp(package / "engine") if stamp is None else stamp
    try:
        if stamp_file.read_text() == stamp:
            return 0
    except OSError:
        pass
    removed = 0
    for cache in package.rglob("__pycache__"):
        for entry in cache.iterdir():
            if entry.suffix in CACHE_SUFFIXES:
                try:
                    entry.unlink()
                    removed += 1
                except OSError:  # another process removed it first, or the install is read-only
                    pass
    try:
        stamp_file.parent.mkdir(exist_ok=True)
        temp = stamp_file.with_name(f"{stamp_file.name}.{os.getpid()}")
        temp.write_text(stamp)
        os.replace(temp, stamp_file)  # whole or absent for a process starting beside this one
    except OSError:
        pass
    return removed
