"""The kernel cache guard: a change to any engine source removes every cached kernel, once."""

import os

import pytest

from riskplan.engine import kernel_cache


def _package(tmp_path):
    engine = tmp_path / "engine"
    (engine / "team" / "__pycache__").mkdir(parents=True)
    (engine / "__pycache__").mkdir()
    (tmp_path / "run" / "__pycache__").mkdir(parents=True)
    (engine / "rng.py").write_text("X = 1\n")
    (engine / "team" / "kernels.py").write_text("Y = 2\n")
    caches = [
        engine / "__pycache__" / "rollout_kernels._simulate-266.py311.nbi",
        engine / "team" / "__pycache__" / "kernels.mix-10.py311.1.nbc",
        tmp_path / "run" / "__pycache__" / "intervals.f-3.py311.nbi",
    ]
    for path in caches:
        path.write_bytes(b"cached")
    keep = engine / "__pycache__" / "rng.cpython-311.pyc"
    keep.write_bytes(b"bytecode")
    return engine, caches, keep


def test_a_changed_helper_file_clears_every_cached_kernel_once(tmp_path):
    engine, caches, keep = _package(tmp_path)
    stamp = engine / "__pycache__" / "stamp"
    assert kernel_cache.clear_stale(tmp_path, stamp) == 3  # no stamp yet: nothing vouches for the cache
    assert not any(path.exists() for path in caches) and keep.exists()
    for path in caches:
        path.write_bytes(b"compiled again")
    assert kernel_cache.clear_stale(tmp_path, stamp) == 0  # sources unchanged: the cache stays
    assert all(path.exists() for path in caches)

    helper = engine / "team" / "kernels.py"
    info = helper.stat()
    os.utime(helper, ns=(info.st_atime_ns, info.st_mtime_ns + 1_000_000))  # an edit in place, same size
    assert kernel_cache.clear_stale(tmp_path, stamp) == 3
    assert kernel_cache.clear_stale(tmp_path, stamp) == 0


def test_the_stamp_names_each_source_by_path_size_and_time(tmp_path):
    engine, _, _ = _package(tmp_path)
    before = kernel_cache.sources_stamp(engine)
    assert kernel_cache.sources_stamp(engine) == before
    (engine / "rng.py").write_text("X = 10\n")  # one byte longer
    assert kernel_cache.sources_stamp(engine) != before


def test_a_read_only_cache_is_left_as_it_is(tmp_path):
    engine, caches, _ = _package(tmp_path)
    for folder in {path.parent for path in caches}:
        folder.chmod(0o555)
    try:
        if os.access(caches[0].parent, os.W_OK):
            pytest.skip("this user writes into a read-only folder (root): nothing to check")
        assert kernel_cache.clear_stale(tmp_path, engine / "__pycache__" / "stamp") == 0
        assert all(path.exists() for path in caches)
    finally:
        for folder in {path.parent for path in caches}:
            folder.chmod(0o755)
