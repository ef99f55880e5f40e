"""`run.mcap`, the log of record of a run: an append-only MCAP writer and a reader that survives truncation.

Channels (message encoding "json", schema encoding "jsonschema"; schema names in brackets):

- `/metrics` [riskplan.Metrics]: one message per metrics.parquet row, the row itself as a JSON object
  ({"iteration", "robot", "mean", ..., "theta_0", ..., "samples", "seconds"}, keys in the caller's order).
- `/theta` [riskplan.Theta]: one message per row of an iteration: {"iteration", "robot", "theta": [...]}.
- `/consensus_error` [riskplan.ConsensusError]: one per iteration, {"iteration", "consensus_error"}. It is written
  last and marks the iteration as complete: the reader keeps only iterations that have it.
- `/trajectories`, `/eval` [riskplan.TableBatch]: a table in batches of at most `BATCH_ROWS` rows, columnar:
  {"table", "offset", "rows", "dtypes": {col: pandas dtype name}, "columns": {col: [values]}}.
- `/summary` [riskplan.Summary]: the summary dict, once.
- `/world/map` [foxglove.Grid], `/world/markers` [foxglove.SceneUpdate]: the world, frame "grid" (see
  `riskplan.run.foxglove_scene`); `/paths` [foxglove.SceneUpdate]: sampled paths replayed step by step.

JSON numbers: floats are written in their shortest round-trip form (bit-exact on reading back). JSON has no
NaN or infinity, so a non-finite float is written as null (NaN), "Infinity" or "-Infinity"; the reader turns them
back into floats in float columns (NaN payload bits are not kept). In the free-form `/summary` and metadata dicts,
they read back as None / those strings.

Metadata records: name -> {"json": <JSON text of the dict>}. `world_map` also writes a "world" record holding the
world dict (arrays as nested lists, indexed [x][y]).

Durability: every public writing method ends by finishing the MCAP chunk in progress (chunk record + its message
indexes) and flushing the file object to the OS, so the bytes survive a SIGKILL of the process as soon as the
method returns (not a power cut: only `sync` and `close` fsync; training syncs before every checkpoint, and
`resume_log` before it replaces the old log). The reader (the mcap package's StreamReader) reads
records sequentially and stops at the first one that is cut short or fails its CRC, so everything before it is
readable.
"""

from __future__ import annotations

import io
import json
import math
import os
import stat
import threading
import time as _time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mcap.writer
import numpy as np
import orjson
import zstandard
from mcap.opcode import Opcode
from mcap.records import Channel, Footer, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from riskplan.run import foxglove_scene as fx
from riskplan.run.log_format import (
    CONSENSUS,
    EVAL,
    ITERATION_TOPICS,
    METRICS,
    NETWORK,
    NETWORK_SCENE,
    PATHS,
    SUMMARY,
    THETA,
    TOPIC_SCHEMA,
    TRAJECTORIES,
    WORLD_MAP,
    WORLD_MARKERS,
    WORLD_TOPICS,
    schema_bytes,
)
from riskplan.run.run_files import RESUMING
from riskplan.util.errors import BadInput
from riskplan.version import __version__

MAGIC = b"\x89MCAP0\r\n"
BATCH_ROWS = 20_000
CHUNK_SIZE = 8 * 1024 * 1024  # larger than any iteration, so each iteration is one chunk (flushed explicitly)
STEP_SECONDS = 0.25  # playback time between two steps on /paths
CHUNK_LEVEL = 1  # zstd level of every MCAP chunk riskplan writes (ChunkCompressor)


class ChunkCompressor:
    """What mcap's Writer compresses its chunks with. The writer calls `zstandard.compress(chunk)`, at zstd's
    default level 3 and with no option for another, and that call builds a new compressor each time. This one
    stands in for the zstandard module there (mcap.writer.zstandard, set below): level 1, the level the Go
    writer's and rosbag2's live recorders use, on one compressor per thread, reused. A team's 900,000 evaluation
    rows compress in 65 ms instead of 190 ms, into 9% more bytes; any reader decompresses either."""

    def __init__(self, level: int = CHUNK_LEVEL) -> None:
        self.level = level
        self._own = threading.local()  # a ZstdCompressor is not to be shared between threads

    def compress(self, data: bytes) -> bytes:
        compressor = getattr(self._own, "compressor", None)
        if compressor is None:
            compressor = self._own.compressor = zstandard.ZstdCompressor(level=self.level)
        return compressor.compress(data)

    def __getattr__(self, name: str):
        return getattr(zstandard, name)  # the rest of the module, should a later mcap call more of it


mcap.writer.zstandard = ChunkCompressor()  # the mcap Writers of a process that imported this module


# --------------------------------------------------------------------------------------- JSON values
def _nonfinite(f: float) -> Any:
    if f != f:
        return None
    return "Infinity" if f > 0 else "-Infinity"


def _scalar(v: Any) -> Any:
    if isinstance(v, float):  # includes np.float64
        return v if math.isfinite(v) else _nonfinite(v)
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, np.floating):
        f = float(v)
        return f if math.isfinite(f) else _nonfinite(f)
    return v


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, Path):
        return str(obj)
    return _scalar(obj)


def _json(obj: Any) -> bytes:
    """Compact JSON of a message: orjson, whose shortest round-trip floats are much quicker to write than the json
    module's (a run's evaluation rows are mostly floats). Values reach it finite (`_scalar`)."""
    return orjson.dumps(obj, default=_plain)


def _plain(v: Any) -> Any:
    """What orjson does not write itself: numbers of numpy's (and other) subclasses as numbers, anything else as
    its text (a Path), as the json module's writer did."""
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _scalar(float(v))
    return str(v)


def _json_table(obj: Any) -> bytes:
    """`_json` of a table batch, whose columns may be numpy arrays (`_encode_column`): orjson writes those from their
    buffers, quicker than from their Python lists."""
    return orjson.dumps(obj, default=_plain, option=orjson.OPT_SERIALIZE_NUMPY)


def _dumps(obj: Any) -> str:
    return _json(obj).decode()


def _isna(v: Any) -> bool:
    """None, NaN, or pandas' NA and NaT (by name: the writer does not import pandas)."""
    return v is None or (isinstance(v, float) and v != v) or type(v).__name__ in ("NAType", "NaTType")


def _encode_column(values: Any) -> tuple[str, Any]:
    """(dtype name, JSON values) of a column: a numpy array, or a pandas Series (its dtype's name as pandas gives
    it). Text in a numpy object array is "str", pandas' name for its text columns. Integers, booleans and finite
    float64 stay a numpy array, which `_json_table` writes as the same text as their Python values (a float32
    would not be: orjson writes its own shortest form, not the double's)."""
    dt = values.dtype
    if isinstance(dt, np.dtype) and dt.kind in "iub":
        return str(dt), np.ascontiguousarray(values)
    if isinstance(dt, np.dtype) and dt.kind == "f":
        arr = np.asarray(values)
        if not np.isfinite(arr).all():
            return str(dt), [_scalar(v) for v in arr.tolist()]
        return str(dt), np.ascontiguousarray(arr) if dt == np.float64 else arr.tolist()
    name = "str" if isinstance(values, np.ndarray) and dt.kind == "O" else str(dt)
    return name, [None if _isna(v) else _scalar(v) for v in values.tolist()]


# --------------------------------------------------------------------------------------- writer
class RunLog:
    """Append-only writer of run.mcap. Every method returns only once its data is durable (see module doc)."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self._setup(open(self.path, "wb"))

    def _setup(self, fh) -> None:
        self._fh = fh
        self._w = Writer(fh, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        self._w.start(profile="", library=f"riskplan {__version__}")
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self._t = 0
        self._world: dict | None = None
        self._closed = False
        self.last_iteration: int | None = None
        self._durable()

    # -- internals
    def _now(self) -> int:
        t = max(_time.time_ns(), self._t)
        self._t = t
        return t

    def _channel(self, topic: str) -> int:
        cid = self._channel_ids.get(topic)
        if cid is None:
            name = TOPIC_SCHEMA[topic]
            sid = self._schema_ids.get(name)
            if sid is None:
                sid = self._w.register_schema(name=name, encoding="jsonschema", data=schema_bytes(name))
                self._schema_ids[name] = sid
            cid = self._w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            self._channel_ids[topic] = cid
            self._seq[topic] = 0
        return cid

    def _add_raw(self, topic: str, data: bytes, t: int) -> None:
        cid = self._channel(topic)
        seq = self._seq[topic]
        self._seq[topic] = (seq + 1) & 0xFFFFFFFF
        self._w.add_message(channel_id=cid, log_time=t, data=data, publish_time=t, sequence=seq)

    def _add(self, topic: str, obj: Any, t: int) -> None:
        self._add_raw(topic, _json(obj), t)

    def _durable(self) -> None:
        flush = getattr(self._w, "flush", None)
        if flush is not None:  # mcap >= 1.3: finishes the chunk in progress, writes it out, flushes the stream
            flush()
        else:  # older mcap: same thing through the private method
            self._w._Writer__finalize_chunk()
        self._fh.flush()

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"{self.path}: RunLog is closed")

    def _table(self, topic: str, table: str, columns: Mapping[str, Any], t: int) -> None:
        """A table (columns: numpy arrays, or a DataFrame) in batches of BATCH_ROWS rows."""
        names = list(columns)  # a dict's keys, a DataFrame's column names
        n = len(columns[names[0]]) if names else 0
        starts = range(0, n, BATCH_ROWS) if n else [0]
        for start in starts:
            dtypes, encoded = {}, {}
            for name in names:
                values = columns[name]
                part = (
                    values.iloc[start : start + BATCH_ROWS]
                    if hasattr(values, "iloc")
                    else values[start : start + BATCH_ROWS]
                )
                dtypes[str(name)], encoded[str(name)] = _encode_column(part)
            rows = min(BATCH_ROWS, n - start)
            batch = {"table": table, "offset": start, "rows": rows, "dtypes": dtypes, "columns": encoded}
            self._add_raw(topic, _json_table(batch), t)

    # -- public
    def metadata(self, name: str, data: dict) -> None:
        """MCAP Metadata record `name` -> {"json": JSON text of `data`}."""
        self._check_open()
        self._w.add_metadata(name, {"json": _dumps(_jsonable(data))})
        self._durable()

    def world_map(self, world: dict) -> None:
        """Metadata "world", a foxglove.Grid on /world/map and a foxglove.SceneUpdate on /world/markers."""
        self._check_open()
        self._world = world
        self._w.add_metadata("world", {"json": _dumps(_jsonable(world))})
        t = self._now()
        self._add(WORLD_MAP, fx.grid(world, t), t)
        self._add(WORLD_MARKERS, fx.world_markers(world, t), t)
        self._durable()

    def network(self, network: dict) -> None:
        """Metadata "network", the graph as JSON on /team/network and as a foxglove.SceneUpdate on /team/graph."""
        self._check_open()
        data = _jsonable(network)
        self._w.add_metadata("network", {"json": _dumps(data)})
        t = self._now()
        self._add(NETWORK, data, t)
        self._add(NETWORK_SCENE, fx.network_scene(data, t), t)
        self._durable()

    def iteration(self, rows: list[dict]) -> None:
        """Log one training iteration (its metrics.parquet rows) and make it durable before returning."""
        if not rows:
            raise ValueError("iteration(): no rows")
        if len({int(r["iteration"]) for r in rows}) > 1:
            raise ValueError("iteration(): rows of more than one iteration")
        self.rows(rows, complete=(int(rows[0]["iteration"]), rows[0].get("consensus_error")))

    def rows(self, rows: list[dict], complete: tuple[int, Any] | None = None) -> None:
        """Metrics rows on /metrics and /theta, stamped with the wall-clock time now, durable before returning; with
        `complete` ((iteration, consensus error)) the /consensus_error message that marks that iteration complete.
        `iteration` logs a whole iteration at once; the ray team logs each robot's rows as they arrive."""
        self._check_open()
        t = self._now()
        encoded = [{k: _scalar(v) for k, v in row.items()} for row in rows]
        for row in encoded:
            self._add(METRICS, row, t)
        for row in encoded:
            names = sorted((k for k in row if k.startswith("theta_")), key=lambda k: int(k[6:]))
            self._add(
                THETA, {"iteration": row["iteration"], "robot": row["robot"], "theta": [row[k] for k in names]}, t
            )
        if complete is not None:
            self._add(CONSENSUS, {"iteration": complete[0], "consensus_error": _scalar(complete[1])}, t)
            self.last_iteration = complete[0]
        self._durable()

    def trajectories(self, df: Mapping[str, Any], step_seconds: float = STEP_SECONDS) -> None:
        """Raw rows on /trajectories (exact rebuild) and a step-by-step replay on /paths."""
        self._check_open()
        t = self._now()
        self._table(TRAJECTORIES, "trajectories", df, t)
        w = h = None
        if self._world is not None:
            w, h = int(self._world["width"]), int(self._world["height"])
        step_ns = max(1, round(step_seconds * 1e9))
        for ts, msg in fx.path_scenes(df, t + step_ns, step_ns, w, h):
            self._add(PATHS, msg, ts)
            self._t = max(self._t, ts + 1)
        self._durable()

    def evaluation(self, df: Mapping[str, Any]) -> None:
        """eval.parquet rows on /eval, columnar batches of BATCH_ROWS rows (zstd-compressed chunks)."""
        self._check_open()
        self._table(EVAL, "eval", df, self._now())
        self._durable()

    def summary(self, summary: dict) -> None:
        self._check_open()
        self._add(SUMMARY, _jsonable(summary), self._now())
        self._durable()

    def sync(self) -> None:
        """Make everything written so far survive a power cut (fsync). Training calls it before each checkpoint,
        so a checkpoint on disk never gets ahead of the log that resume needs."""
        self._check_open()
        self._durable()
        os.fsync(self._fh.fileno())

    def close(self, durable: bool = True) -> None:
        """Write the summary section and indexes, fsync (unless the caller syncs the file system itself: a
        batch's group commit) and close. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._w.finish()
            self._fh.flush()
            if durable:
                os.fsync(self._fh.fileno())
        finally:
            self._fh.close()

    def __enter__(self) -> RunLog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------------------- scanning (the reader is riskplan.run.log_reader)
@dataclass
class _Raw:
    topic: str
    log_time: int
    publish_time: int
    data: bytes


@dataclass
class _Scan:
    metadata: list[tuple[str, dict[str, str]]]
    messages: list[_Raw]
    closed: bool  # footer and trailing magic present
    stop: str | None  # why reading stopped early


def _read_bytes(path: Path | str) -> bytes:
    """The file's bytes; a run's log is a regular file, never a device or a pipe (a link to /dev/zero would be read
    until memory ran out, a FIFO until someone wrote to it)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # before opening it: opening a FIFO would wait for a writer
            raise BadInput(str(path), "is not a regular file (a device, a pipe or a folder); a run's log is a file")
        return Path(path).read_bytes()
    except OSError as e:
        raise BadInput(str(path), f"cannot read MCAP file: {e.strerror or e}") from None


def _scan(data: bytes, where: str) -> _Scan:
    """Read records in order with the mcap package's StreamReader, stopping (without raising) at the first record
    that is cut short or fails its CRC: everything before it is kept."""
    out = _Scan([], [], False, None)
    if data[:8] != MAGIC:
        if len(data) < 8 and MAGIC.startswith(data):
            out.stop = f"file ends at byte {len(data)}, inside the MCAP magic"
            return out
        raise BadInput(where, "not an MCAP file (bad magic bytes)")
    if len(data) >= 9 and data[8] != Opcode.HEADER:
        raise BadInput(where, "not an MCAP file (no header record after the magic)")
    stream = io.BytesIO(data)
    topics: dict[int, str] = {}
    pos, footer = 8, False  # pos: where the record being read starts (after the last record handed out)
    try:
        for record in StreamReader(stream, validate_crcs=True).records:
            if isinstance(record, Channel):
                topics[record.id] = record.topic
            elif isinstance(record, Message):
                topic = topics.get(record.channel_id)
                if topic is not None:
                    out.messages.append(_Raw(topic, record.log_time, record.publish_time, record.data))
            elif isinstance(record, Metadata):
                out.metadata.append((record.name, dict(record.metadata)))
            footer = isinstance(record, Footer)
            pos = stream.tell()
    except Exception as err:
        out.stop = _stop_reason(data, pos, footer, err)
        return out
    out.closed = True
    return out


def _stop_reason(data: bytes, pos: int, after_footer: bool, err: Exception) -> str:
    """Why reading stopped at the record that starts at byte `pos` (or at the closing magic after the footer)."""
    n = len(data)
    if after_footer:
        return f"file ends at byte {n}, inside the closing magic"
    if pos + 9 > n:
        return f"file ends at byte {n}, inside a record header"
    if pos + 9 + int.from_bytes(data[pos + 1 : pos + 9], "little") > n:
        return f"file ends at byte {n}, inside a record that starts at byte {pos}"
    return f"corrupt record at byte {pos} ({type(err).__name__})"


def _decode_metadata(m: dict[str, str]) -> Any:
    if set(m) == {"json"}:
        try:
            return json.loads(m["json"])
        except ValueError:
            pass
    return dict(m)


def _iteration_messages(msgs: Iterable[_Raw]) -> tuple[dict[str, list[tuple[_Raw, dict]]], set[int]]:
    by_topic: dict[str, list[tuple[_Raw, dict]]] = {t: [] for t in ITERATION_TOPICS}
    done: set[int] = set()
    for m in msgs:
        if m.topic in by_topic:
            try:
                obj = json.loads(m.data)
                int(obj["iteration"])
            except (ValueError, KeyError, TypeError):
                continue
            by_topic[m.topic].append((m, obj))
            if m.topic == CONSENSUS:
                done.add(int(obj["iteration"]))
    return by_topic, done


def log_header(path: Path | str) -> tuple[dict[str, Any], int]:
    """run.mcap's metadata records, decoded (a later record of a name replaces an earlier one), and how many
    iterations it holds whole: what a resume checks before it reads the rows."""
    scan = _scan(_read_bytes(path), str(path))
    _, done = _iteration_messages(scan.messages)
    return {name: _decode_metadata(m) for name, m in scan.metadata}, len(done)


def resume_log(src: Path | str, dst: Path | str, last_iteration: int) -> RunLog:
    """A RunLog on `dst` holding `src`'s metadata, world map and iterations <= last_iteration, open for appending.

    `src` may be truncated, and may be the same path as `dst` (the copy is written to a temporary file next to
    `dst`, then renamed over it). Trajectories, evaluation and summary messages of `src` are not copied. Raises
    BadInput if `src` lacks a complete iteration in 0..last_iteration.
    """
    scan = _scan(_read_bytes(src), str(src))
    by_topic, done = _iteration_messages(scan.messages)
    missing = [i for i in range(int(last_iteration) + 1) if i not in done]
    if missing:
        have = f"its last complete iteration is {max(done)}" if done else "it has no complete iteration"
        raise BadInput(str(src), f"cannot resume after iteration {last_iteration}: {have}")
    keep: dict[int, dict] = {}  # id(raw) -> parsed, for iteration messages to copy
    seen: set[tuple] = set()
    for topic, items in by_topic.items():
        for raw, obj in items:
            it = int(obj["iteration"])
            key = (topic, it) if topic == CONSENSUS else (topic, it, obj.get("robot"))
            if it <= last_iteration and it in done and key not in seen:
                seen.add(key)
                keep[id(raw)] = obj

    dst = Path(dst)
    tmp = dst.with_name(dst.name + RESUMING)
    log = RunLog.__new__(RunLog)
    log.path = dst
    log._setup(open(tmp, "wb"))
    try:
        for name, m in scan.metadata:
            log._w.add_metadata(name, m)
            if name == "world":
                world = _decode_metadata(m)
                log._world = world if isinstance(world, dict) and "width" in world else None
        t_max = 0
        for raw in scan.messages:
            if raw.topic in WORLD_TOPICS or id(raw) in keep:
                log._add_raw(raw.topic, raw.data, raw.log_time)
                t_max = max(t_max, raw.log_time)
        log._t = t_max
        log.last_iteration = int(last_iteration) if last_iteration >= 0 else None
        log.sync()  # on disk before it replaces the old log: a power cut leaves one or the other, whole
        os.replace(tmp, dst)
    except BaseException:
        log._fh.close()
        tmp.unlink(missing_ok=True)
        raise
    return log


__all__ = ["BATCH_ROWS", "RunLog", "log_header", "resume_log"]
