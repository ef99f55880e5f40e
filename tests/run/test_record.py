"""The run's log, run.mcap (riskplan.run.record, riskplan.run.foxglove_scene): round trips, truncation and SIGKILL
survival, resume, Foxglove schema conformance."""

from __future__ import annotations

import base64
import hashlib
import itertools
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import jsonschema
import mcap.writer
import numpy as np
import pandas as pd
import pytest
import zstandard
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader

from riskplan.run import foxglove_scene as fx
from riskplan.run.log_reader import read_log
from riskplan.run.record import BATCH_ROWS, RunLog, _encode_column, _json, _json_table, _jsonable, resume_log
from riskplan.util.errors import BadInput

SCHEMAS = Path(fx.__file__).parent / "schemas"
W, H, N, M = 12, 8, 3, 2


# ------------------------------------------------------------------------------------------------ fixtures
def make_world() -> dict:
    rng = np.random.default_rng(1)
    region = np.full((W, H), -1, dtype=np.int64)
    region[2:5, 1:4] = 0
    region[7:10, 4:7] = 1
    return {
        "width": W,
        "height": H,
        "cell_region": region,
        "region_names": ["A", "B"],
        "risky": region >= 0,
        "obstacles": rng.random((W, H)) < 0.1,
        "sources": [{"name": "safe", "x": 9, "y": 3}, {"name": "risky", "x": 3, "y": 6}],
        "start": [[0, 0], [1, 0], [0, 1]],
    }


def make_rows(it: int, rng: np.random.Generator, n: int = N, m: int = M) -> list[dict]:
    rows = []
    ce = float(rng.random()) if n > 1 else float("nan")
    for r in [*range(n), -1]:
        d = {"iteration": it, "robot": r}
        for k in ("mean", "cvar", "value_at_risk", "std"):
            d[k] = float(rng.normal() * 10.0 ** rng.integers(-300, 300))
        for j in range(m):
            d[f"theta_{j}"] = rng.normal()  # np.float64
        d.update(grad_norm=float(rng.random()), step_size=0.1, consensus_error=ce, samples=np.int64(64), seconds=1e-3)
        rows.append(d)
    return rows


def expected_metrics(rows: list[dict]) -> pd.DataFrame:
    df = pd.DataFrame(rows)
    return df.sort_values(["iteration", "robot"], kind="stable").reset_index(drop=True)


def nasty_floats(n: int, rng: np.random.Generator) -> np.ndarray:
    """Random bit patterns (subnormals, huge, -0.0) plus NaN and +-inf; NaN payloads normalised."""
    x = rng.integers(0, 2**64, size=n, dtype=np.uint64).view(np.float64).copy()
    x[np.isnan(x)] = np.nan
    special = [0.0, -0.0, np.inf, -np.inf, np.nan, 5e-324, 1.7976931348623157e308, 0.1, 1 / 3]
    k = min(n, len(special))
    x[:k] = special[:k]
    return x


def make_eval(n: int, rng: np.random.Generator) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "episode": np.arange(n, dtype=np.int64),
            "robot": rng.integers(-1, N, n),
            "total_reward": nasty_floats(n, rng),
            "risky_steps": rng.integers(0, 50, n),
            "source_reached": rng.integers(-1, 2, n),
            "steps": rng.integers(1, 2**62, n),
        }
    )


def make_trajectories(rng: np.random.Generator, episodes: int = 2, steps: int = 6) -> pd.DataFrame:
    rows = []
    for policy in ("initial", "final"):
        for e in range(episodes):
            for r in range(N):
                x, y = 0, r
                for s in range(steps):
                    rows.append((policy, e, r, s, x, y, float(rng.normal())))
                    x = min(W - 1, x + int(rng.integers(0, 2)))
                    y = min(H - 1, y + int(rng.integers(0, 2)))
    return pd.DataFrame(rows, columns=["policy", "episode", "robot", "step", "x", "y", "reward"])


def write_full(path: Path, iterations: int = 5, n_eval: int = 100, seed: int = 0):
    rng = np.random.default_rng(seed)
    meta = {
        "config": {"seed": seed, "risk": {"beta": 0.1}, "list": [1, 2.5, "x"], "none": None},
        "provenance": {"git": "abc", "versions": {"numpy": np.__version__}},
        "network": {
            "robots": 3,
            "graph": "line",
            "edges": [[0, 1], [1, 0], [1, 2], [2, 1]],
            "weights": np.full((3, 3, 2), 1 / 3),
            "positions": None,
            "gamma": 1 / 3,
            "slem": 0.5,
        },
    }
    rows: list[dict] = []
    traj = make_trajectories(rng)
    ev = make_eval(n_eval, rng)
    summary = {"mean": 1.25, "cvar": {"0.1": -3.5, "ci": [-4.0, -3.0]}, "schema_version": 1, "sha": None}
    with RunLog(path) as log:
        for name, d in meta.items():
            if name != "network":
                log.metadata(name, d)
        log.world_map(make_world())
        log.network(meta["network"])
        for it in range(iterations):
            rr = make_rows(it, rng)
            rows += rr
            log.iteration(rr)
        log.trajectories(traj)
        log.evaluation(ev)
        log.summary(summary)
    meta["network"]["weights"] = np.full((3, 3, 2), 1 / 3).tolist()
    return meta, rows, traj, ev, summary


def mcap_messages(path: Path):
    with open(path, "rb") as f:
        yield from make_reader(f).iter_messages()


# ------------------------------------------------------------------------------------------------ round trips
def test_round_trip_every_table(tmp_path):
    path = tmp_path / "run.mcap"
    meta, rows, traj, ev, summary = write_full(path, iterations=7, n_eval=2 * BATCH_ROWS + 123)
    d = read_log(path)
    assert d.complete and d.problem is None
    pd.testing.assert_frame_equal(d.metrics, expected_metrics(rows), check_exact=True)
    pd.testing.assert_frame_equal(d.eval, ev, check_exact=True)
    pd.testing.assert_frame_equal(d.trajectories, traj, check_exact=True)
    assert d.summary == summary
    for name, value in meta.items():
        assert d.metadata[name] == value
    assert d.metadata["world"]["width"] == W and d.metadata["world"]["sources"][0]["name"] == "safe"
    assert np.array_equal(np.array(d.metadata["world"]["obstacles"]), make_world()["obstacles"])
    # eval went out in batches of BATCH_ROWS rows
    batches = [json.loads(m.data) for _, c, m in mcap_messages(path) if c.topic == "/eval"]
    assert [b["rows"] for b in batches] == [BATCH_ROWS, BATCH_ROWS, 123]
    assert [b["offset"] for b in batches] == [0, BATCH_ROWS, 2 * BATCH_ROWS]


def test_floats_are_bit_exact_and_ints_stay_ints(tmp_path):
    rng = np.random.default_rng(7)
    ev = make_eval(5000, rng)
    path = tmp_path / "run.mcap"
    with RunLog(path) as log:
        log.evaluation(ev)
        log.summary({})
    got = read_log(path).eval
    a, b = ev["total_reward"].to_numpy(), got["total_reward"].to_numpy()
    nan = np.isnan(a)
    assert np.array_equal(nan, np.isnan(b))
    assert np.array_equal(a[~nan].view(np.uint64), b[~nan].view(np.uint64))  # -0.0 and subnormals too
    assert got["steps"].dtype == np.int64 and np.array_equal(got["steps"], ev["steps"])


def test_other_dtypes_round_trip(tmp_path):
    df = pd.DataFrame(
        {
            "policy": pd.Series(["initial", "final", "final"]),  # pandas' default string dtype
            "episode": np.array([0, 1, 2], dtype=np.int32),
            "robot": np.array([0, -1, 1], dtype=np.int8),
            "step": np.array([0, 1, 2], dtype=np.uint16),
            "x": np.array([1.5, -0.0, np.inf], dtype=np.float32),
            "y": np.array([True, False, True]),
            "reward": pd.Series(["a", None, "c"], dtype=object),
        }
    )
    path = tmp_path / "run.mcap"
    with RunLog(path) as log:
        log.evaluation(df)  # the table writer keeps whatever dtypes it is given
    pd.testing.assert_frame_equal(read_log(path).eval, df, check_exact=True)


def test_metrics_nonfinite_and_single_robot(tmp_path):
    rng = np.random.default_rng(3)
    rows = []
    path = tmp_path / "run.mcap"
    with RunLog(path) as log:
        for it in range(3):
            rr = make_rows(it, rng, n=1, m=3)
            rr[0]["std"] = float("inf") if it == 1 else rr[0]["std"]
            rr[1]["cvar"] = float("-inf")
            rows += rr
            log.iteration(rr)
    d = read_log(path)
    exp = expected_metrics(rows)
    assert exp["consensus_error"].isna().all()
    pd.testing.assert_frame_equal(d.metrics, exp, check_exact=True)
    assert not d.complete and d.problem.startswith("no /summary")


def test_empty_tables(tmp_path):
    path = tmp_path / "never.mcap"
    RunLog(path).close()
    d = read_log(path)
    assert d.metrics.empty and d.eval.empty and d.trajectories.empty and d.summary is None
    assert list(d.eval.columns) == [
        "episode",
        "robot",
        "healthy",
        "total_reward",
        "risky_steps",
        "source_reached",
        "steps",
    ]
    assert d.eval["total_reward"].dtype == np.float64 and d.metrics["iteration"].dtype == np.int64
    assert not d.complete

    path = tmp_path / "empty.mcap"
    ev = make_eval(0, np.random.default_rng(0))
    tr = make_trajectories(np.random.default_rng(0)).iloc[:0]
    with RunLog(path) as log:
        log.evaluation(ev)
        log.trajectories(tr)
        log.summary({"mean": 0.0})
    d = read_log(path)
    pd.testing.assert_frame_equal(d.eval, ev)
    pd.testing.assert_frame_equal(d.trajectories, tr.reset_index(drop=True))
    assert d.complete


# ------------------------------------------------------------------------------------------------ truncation
@pytest.mark.slow  # reads the log cut at some 200 offsets: about a second
def test_truncated_at_any_offset_keeps_every_durable_iteration(tmp_path):
    rng = np.random.default_rng(5)
    path = tmp_path / "run.mcap"
    log = RunLog(path)
    log.metadata("config", {"a": 1})
    log.world_map(make_world())
    durable: list[int] = []  # file size when iteration i had returned
    rows: list[dict] = []
    for it in range(12):
        rr = make_rows(it, rng)
        rows += rr
        log.iteration(rr)
        durable.append(path.stat().st_size)
    log.evaluation(make_eval(50, rng))
    open_bytes = path.read_bytes()  # what a SIGKILL right now would leave
    log.summary({"mean": 1.0})
    log.close()
    closed_bytes = path.read_bytes()
    assert closed_bytes.startswith(open_bytes)

    cuts = set(range(0, 64)) | set(rng.integers(0, len(open_bytes), 150).tolist())
    for s in durable:
        cuts |= {s - 1, s, s + 1}
    cuts |= {len(open_bytes), len(closed_bytes) - 1, len(closed_bytes) - 8, len(closed_bytes) - 200}
    cut_path = tmp_path / "cut.mcap"
    for cut in sorted(c for c in cuts if 0 <= c < len(closed_bytes)):
        cut_path.write_bytes(closed_bytes[:cut])
        d = read_log(cut_path)  # never raises
        k = sum(1 for s in durable if s <= cut)  # iterations durable before the cut
        got = sorted(set(d.metrics["iteration"])) if len(d.metrics) else []
        # every durable iteration, in full; the next one too if its chunk got out whole (its indexes did not)
        assert got == list(range(len(got))) and k <= len(got) <= k + 1, (cut, got, k)
        k = len(got)
        if k:
            pd.testing.assert_frame_equal(d.metrics, expected_metrics(rows[: (N + 1) * k]), check_exact=True)
        else:
            assert d.metrics.empty and "before any iteration" in d.problem
        assert not d.complete
        assert d.problem.startswith("truncated"), d.problem
        if k:
            assert f"after iteration {k - 1}" in d.problem
        if cut >= durable[0]:
            assert d.metadata["config"] == {"a": 1}

    cut_path.write_bytes(closed_bytes)
    assert read_log(cut_path).complete


@pytest.mark.slow  # a writer in a subprocess, SIGKILLed
def test_sigkill_mid_run_keeps_reported_iterations(tmp_path):
    path = tmp_path / "run.mcap"
    script = textwrap.dedent(
        f"""
        import sys, time
        import numpy as np
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_record import make_rows, make_world
        from riskplan.run.record import RunLog
        rng = np.random.default_rng(0)
        log = RunLog({str(path)!r})
        log.metadata("config", {{"n": 1}})
        log.world_map(make_world())
        for it in range(100000):
            log.iteration(make_rows(it, rng))
            print(it, flush=True)
            time.sleep(0.002)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    k = 25
    try:
        for line in proc.stdout:
            if int(line) >= k:
                break
        proc.send_signal(signal.SIGKILL)  # no chance to close or flush anything
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    d = read_log(path)
    iters = sorted(set(d.metrics["iteration"]))
    assert iters == list(range(len(iters))) and len(iters) >= k + 1
    assert (d.metrics.groupby("iteration").size() == N + 1).all()
    assert not d.complete and d.problem.startswith(f"truncated after iteration {iters[-1]}")
    assert d.metadata["config"] == {"n": 1}


# ------------------------------------------------------------------------------------------------ resume
def test_resume_copies_and_continues_without_duplicates(tmp_path):
    rng = np.random.default_rng(11)
    src = tmp_path / "run.mcap"
    log = RunLog(src)
    log.metadata("config", {"a": 1})
    log.world_map(make_world())
    rows = []
    for it in range(8):
        if it == 7:
            cut = src.stat().st_size + 40  # killed while writing the chunk of iteration 7
        rr = make_rows(it, rng)
        rows += rr
        log.iteration(rr)
    log.close()
    src.write_bytes(src.read_bytes()[:cut])
    assert sorted(set(read_log(src).metrics["iteration"])) == list(range(7))

    with pytest.raises(BadInput, match="last complete iteration is 6"):
        resume_log(src, tmp_path / "x.mcap", 7)

    dst = tmp_path / "resumed.mcap"
    log = resume_log(src, dst, 4)
    mid = read_log(dst)  # durable already
    assert sorted(set(mid.metrics["iteration"])) == list(range(5)) and mid.metadata["config"] == {"a": 1}
    kept = rows[: 5 * (N + 1)]
    for it in range(5, 9):
        rr = make_rows(it, rng)
        kept += rr
        log.iteration(rr)
    ev = make_eval(10, rng)
    log.evaluation(ev)
    log.summary({"mean": 2.0})
    log.close()
    assert not (tmp_path / "resumed.mcap.resume-tmp").exists()

    d = read_log(dst)
    assert d.complete
    pd.testing.assert_frame_equal(d.metrics, expected_metrics(kept), check_exact=True)
    pd.testing.assert_frame_equal(d.eval, ev)
    topics = [c.topic for _, c, _ in mcap_messages(dst)]
    assert topics.count("/consensus_error") == 9 and topics.count("/theta") == 9 * (N + 1)
    assert topics.count("/world/map") == 1 and topics.count("/world/markers") == 1
    times = [m.log_time for _, c, m in mcap_messages(dst) if c.topic == "/consensus_error"]
    assert times == sorted(times)


def test_resume_in_place_and_from_scratch(tmp_path):
    path = tmp_path / "run.mcap"
    meta, rows, *_ = write_full(path, iterations=4)
    log = resume_log(path, path, 2)  # same file: rewritten through a temporary file
    log.close()
    d = read_log(path)
    pd.testing.assert_frame_equal(d.metrics, expected_metrics(rows[: 3 * (N + 1)]), check_exact=True)
    assert d.eval.empty and d.trajectories.empty and d.summary is None and not d.complete
    assert d.metadata["config"] == meta["config"]

    log = resume_log(path, tmp_path / "fresh.mcap", -1)
    log.close()
    assert read_log(tmp_path / "fresh.mcap").metrics.empty


# ------------------------------------------------------------------------------------------------ Foxglove
def official(name: str) -> dict:
    return json.loads((SCHEMAS / f"foxglove.{name}.json").read_text())


def test_shipped_schemas_are_the_vendored_official_files():
    """Byte-for-byte the files extracted from @foxglove/schemas 2.1.0 (riskplan/schemas/README.md)."""
    digests = {
        "Grid": "bca365b784614d9c60e3e03e3b4a0ef67975c80670f16d80e0e1e40df37f3b3d",
        "SceneUpdate": "bc563208a8b4bb2eaecd17713405ef2d9ba87264ac73ae375ba5ab30368c8991",
    }
    for name, digest in digests.items():
        assert hashlib.sha256((SCHEMAS / f"foxglove.{name}.json").read_bytes()).hexdigest() == digest
        assert official(name)["title"] == f"foxglove.{name}"
    assert fx.schema(fx.GRID) == official("Grid")


@pytest.mark.slow  # validates every message of a log: over a second
def test_every_message_validates_against_its_schema(tmp_path):
    path = tmp_path / "run.mcap"
    write_full(path, iterations=3, n_eval=30)
    validators = {
        "foxglove.Grid": jsonschema.Draft202012Validator(official("Grid")),
        "foxglove.SceneUpdate": jsonschema.Draft202012Validator(official("SceneUpdate")),
    }
    seen: dict[str, int] = {}
    for schema, channel, message in mcap_messages(path):
        assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
        embedded = json.loads(schema.data)
        jsonschema.Draft202012Validator.check_schema(embedded)
        obj = json.loads(message.data)
        if schema.name.startswith("foxglove."):
            assert embedded == official(schema.name.split(".")[1])
            validators[schema.name].validate(obj)
        jsonschema.Draft202012Validator(embedded).validate(obj)
        seen[channel.topic] = seen.get(channel.topic, 0) + 1
    assert {
        "/world/map",
        "/world/markers",
        "/paths",
        "/metrics",
        "/theta",
        "/consensus_error",
        "/trajectories",
        "/eval",
        "/summary",
        "/team/network",
        "/team/graph",
    } <= set(seen)
    schemas = {c.topic: s.name for s, c, _ in mcap_messages(path)}
    assert schemas["/world/map"] == "foxglove.Grid"
    assert schemas["/world/markers"] == schemas["/paths"] == "foxglove.SceneUpdate"


def test_grid_and_markers_encode_the_world(tmp_path):
    world = make_world()
    path = tmp_path / "run.mcap"
    with RunLog(path) as log:
        log.world_map(world)
    msgs = {c.topic: json.loads(m.data) for _, c, m in mcap_messages(path)}
    grid = msgs["/world/map"]
    assert grid["frame_id"] == "grid" and grid["cell_size"] == {"x": 1.0, "y": 1.0}
    assert grid["column_count"] == W and grid["pose"]["position"] == {"x": 0.0, "y": 0.0, "z": 0.0}
    codes = fx.decode_grid(grid)
    expect = np.where(world["obstacles"], 2, np.where(world["risky"], 1, 0))
    assert np.array_equal(codes, expect)
    raw = np.frombuffer(base64.b64decode(grid["data"]), dtype=np.dtype([("c", "u1"), ("p", "u1"), ("r", "<i2")]))
    # row-major, y-major: element y * W + x is cell (x, y)
    assert np.array_equal(raw["r"].reshape(H, W).T, world["cell_region"])
    ents = {e["id"]: e for e in msgs["/world/markers"]["entities"]}
    src = [s["pose"]["position"] for s in ents["sources"]["spheres"]]
    assert (src[0]["x"], src[0]["y"]) == (9.5, 3.5)
    assert len(ents["obstacles"]["cubes"]) == int(world["obstacles"].sum())
    assert len(ents["start"]["cubes"]) == 3


def test_paths_replay_moves_robots_over_time(tmp_path):
    rng = np.random.default_rng(2)
    traj = make_trajectories(rng, episodes=2, steps=5)
    path = tmp_path / "run.mcap"
    with RunLog(path) as log:
        log.world_map(make_world())
        log.trajectories(traj, step_seconds=0.5)
    paths = [(m.log_time, json.loads(m.data)) for _, c, m in mcap_messages(path) if c.topic == "/paths"]
    assert len(paths) == 4 * 5  # one per step of each (policy, episode)
    times = [t for t, _ in paths]
    assert all(b > a for a, b in itertools.pairwise(times))
    assert times[1] - times[0] == 500_000_000
    first = traj[(traj.policy == "initial") & (traj.episode == 0)]
    for s in range(5):
        ents = {e["id"]: e for e in paths[s][1]["entities"]}
        for r in range(N):
            row = first[(first.robot == r) & (first.step == s)].iloc[0]
            pos = ents[f"robot/{r}"]["spheres"][0]["pose"]["position"]
            assert (pos["x"], pos["y"]) == (row.x + 0.5, row.y + 0.5)
    ents0 = {e["id"]: e for e in paths[0][1]["entities"]}
    assert len(ents0["path/0"]["lines"][0]["points"]) == 5 and paths[0][1]["deletions"][0]["type"] == 1
    assert "initial policy, episode 0" in ents0["label"]["texts"][0]["text"]


def test_closed_file_is_standard_mcap_with_summary(tmp_path):
    path = tmp_path / "run.mcap"
    write_full(path, iterations=3)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count > 0
        assert {c.topic for c in summary.channels.values()} >= {"/metrics", "/world/map", "/paths"}
        assert {m.name for m in reader.iter_metadata()} == {"config", "provenance", "network", "world"}


def test_chunks_are_zstd_at_level_1_from_threads_alike(tmp_path):
    """Every chunk is zstd's level-1 frame of its records (ChunkCompressor), not the writer's default level 3,
    also when logs are written from other threads (a compressor each); and the file reads back whole."""
    paths = [tmp_path / f"run{k}.mcap" for k in range(3)]
    workers = [
        threading.Thread(target=write_full, args=(path,), kwargs={"n_eval": 3000, "seed": k})
        for k, path in enumerate(paths)
    ]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    level = {n: zstandard.ZstdCompressor(level=n) for n in (1, 3)}
    for path in paths:
        with open(path, "rb") as f:
            chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
        assert chunks and {chunk.compression for chunk in chunks} == {"zstd"}
        for chunk in chunks:
            records = zstandard.decompress(chunk.data, max_output_size=chunk.uncompressed_size)
            assert chunk.data == level[1].compress(records)
        biggest = max(chunks, key=lambda chunk: chunk.uncompressed_size)  # the evaluation's: level 3 differs there
        records = zstandard.decompress(biggest.data, max_output_size=biggest.uncompressed_size)
        assert level[3].compress(records) != biggest.data
        assert read_log(path).complete
    assert mcap.writer.zstandard.ZstdDecompressor is zstandard.ZstdDecompressor  # the module's other names pass


# ------------------------------------------------------------------------------------------------ bad input, cost
def test_not_mcap_is_bad_input(tmp_path):
    bad = tmp_path / "metrics.parquet"
    bad.write_bytes(b"PAR1 this is not an mcap file at all")
    with pytest.raises(BadInput) as e:
        read_log(bad)
    assert str(bad) in str(e.value)
    with pytest.raises(BadInput):
        read_log(tmp_path / "missing.mcap")
    with pytest.raises(BadInput):
        resume_log(bad, tmp_path / "out.mcap", 0)
    empty = tmp_path / "empty.mcap"  # killed before the first byte: an (empty) truncated log
    empty.write_bytes(b"")
    d = read_log(empty)
    assert not d.complete and d.problem.startswith("truncated") and d.metrics.empty


def test_writing_after_close_is_an_error(tmp_path):
    log = RunLog(tmp_path / "run.mcap")
    log.close()
    log.close()  # idempotent
    with pytest.raises(ValueError):
        log.iteration(make_rows(0, np.random.default_rng(0)))


def test_per_iteration_cost_is_reported(tmp_path):
    rng = np.random.default_rng(0)
    batches = [make_rows(it, rng) for it in range(200)]
    with RunLog(tmp_path / "run.mcap") as log:
        log.world_map(make_world())
        t0 = time.perf_counter()
        for rr in batches:
            log.iteration(rr)
        per = (time.perf_counter() - t0) / len(batches)
    print(f"\nRunLog.iteration: {per * 1e6:.0f} us per iteration ({N + 1} rows, {M} thetas), durable each time")


def test_durability_without_writer_flush_method(tmp_path):
    """mcap < 1.6 has no Writer.flush(); the private chunk finaliser is used instead, with the same effect."""
    rng = np.random.default_rng(4)
    path = tmp_path / "run.mcap"
    log = RunLog(path)
    log._w.flush = None  # hide the public method, as on an older mcap
    rows = []
    for it in range(4):
        rr = make_rows(it, rng)
        rows += rr
        log.iteration(rr)
    killed = tmp_path / "killed.mcap"
    killed.write_bytes(path.read_bytes())
    log.close()
    d = read_log(killed)
    pd.testing.assert_frame_equal(d.metrics, expected_metrics(rows), check_exact=True)
    assert (
        d.problem == f"truncated after iteration 3 (file ends at byte {killed.stat().st_size}, inside a record header)"
    )


def test_messages_hold_the_values_the_json_module_wrote():
    """orjson writes the messages: numpy scalars are numbers (even those no writer converted first), floats read
    back bit for bit at any magnitude, and text and paths are text, as the json module wrote the writer's values."""
    rng = np.random.default_rng(9)
    floats = (rng.normal(size=500) * 10.0 ** rng.integers(-300, 300, 500)).tolist() + [5e-324, 1e-5, 1e16, -0.0]
    message = {
        "value": np.float64(1418.029753422557),
        "count": np.int64(7),
        "ok": np.bool_(True),
        "path": Path("/runs/a"),
        "name": "Quelle ☢ 源",
        "floats": floats,
        "nested": [{"x": np.float32(0.5)}],
    }
    written = json.loads(_json(message))
    assert written == json.loads(json.dumps(_jsonable(message), default=str))
    assert isinstance(written["value"], float) and isinstance(written["count"], int) and written["ok"] is True
    assert [math.copysign(1.0, x) for x in written["floats"]] == [math.copysign(1.0, x) for x in floats]
    assert written["floats"] == floats  # bit for bit: the shortest round-trip form


def test_a_tables_numpy_columns_are_written_as_their_python_values_were():
    """A table batch's integer, boolean and finite float64 columns go to orjson as numpy arrays: the same bytes as
    their Python lists, at any magnitude; a float32 or a column with NaN or infinity goes as the Python values."""
    rng = np.random.default_rng(4)
    wide = rng.normal(size=2000) * 10.0 ** rng.integers(-320, 300, 2000)
    columns = {
        "float64": np.concatenate([wide, [0.0, -0.0, 5e-324, 1.7976931348623157e308, 0.1, 1e16, 1e-7]]),
        "float32": np.array([0.1, 1 / 3, 1e-30], dtype=np.float32),
        "nonfinite": np.array([1.5, np.nan, np.inf, -np.inf]),
        "int8": np.array([-128, 0, 127], dtype=np.int8),
        "int64": np.array([-(2**63), 0, 2**63 - 1]),
        "uint64": np.array([0, 2**64 - 1], dtype=np.uint64),
        "bool": np.array([True, False]),
        "empty": np.array([], dtype=float),
        "every other": np.arange(10.0)[::2],  # not contiguous
    }
    for name, values in columns.items():
        dtype, encoded = _encode_column(values)
        as_python = [_jsonable(v) for v in values.tolist()]
        assert dtype == str(values.dtype)
        assert _json_table({"columns": {name: encoded}}) == _json({"columns": {name: as_python}}), name
    assert isinstance(_encode_column(columns["float64"])[1], np.ndarray)
    assert isinstance(_encode_column(columns["float32"])[1], list)


@pytest.mark.parametrize("kind", ["device", "fifo", "folder"])
def test_a_log_that_is_no_regular_file_is_refused_before_it_is_read(tmp_path, kind):
    """run.mcap linked to /dev/zero was read until memory ran out (13 GB in 30 s), and a FIFO waited for a writer."""
    path = tmp_path / "run.mcap"
    {"device": lambda: path.symlink_to("/dev/zero"), "fifo": lambda: os.mkfifo(path), "folder": path.mkdir}[kind]()
    with pytest.raises(BadInput) as refused:
        read_log(path)
    assert str(refused.value) == f"{path}: is not a regular file (a device, a pipe or a folder); a run's log is a file"
