"""Reading `run.mcap` back (the format is riskplan.run.record's): its metadata, the metrics rows of every complete
iteration, the evaluation and trajectory tables and the summary, from a closed or a truncated log, as DataFrames."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from riskplan.run.log_format import EVAL, EVAL_COLUMNS, METRICS, METRICS_BASE, SUMMARY, TRAJECTORIES, TRAJECTORY_COLUMNS
from riskplan.run.record import (
    _decode_metadata,
    _iteration_messages,
    _read_bytes,
    _scan,
)


@dataclass
class LogData:
    metadata: dict[str, dict]
    metrics: pd.DataFrame
    eval: pd.DataFrame
    trajectories: pd.DataFrame
    summary: dict | None
    complete: bool
    problem: str | None


def _float(v: Any) -> float:
    if v is None:
        return math.nan
    if isinstance(v, str):
        return {"Infinity": math.inf, "-Infinity": -math.inf}.get(v, math.nan)
    return float(v)


def _decode_column(dtype: str, values: list) -> Any:
    try:
        dt = pd.api.types.pandas_dtype(dtype)
    except (TypeError, ValueError):
        dt = np.dtype(object)
    if isinstance(dt, np.dtype):
        if dt.kind in "iub":
            return np.asarray(values, dtype=dt)
        if dt.kind == "f":
            try:  # None -> nan, "Infinity" -> inf
                arr = np.asarray(values, dtype=np.float64)
            except (TypeError, ValueError):
                arr = np.asarray([_float(v) for v in values], dtype=np.float64)
            return arr.astype(dt, copy=False)
        if dt == np.dtype(object):
            return pd.Series(values, dtype=object)
    try:
        return pd.array(values, dtype=dt)
    except (TypeError, ValueError):
        return pd.Series(values, dtype=object)


def _empty(columns: dict[str, str]) -> pd.DataFrame:
    return pd.DataFrame({c: pd.Series([], dtype=d) for c, d in columns.items()})


def _column(values: list) -> Any:
    if values and all(type(v) is int for v in values):
        return np.asarray(values, dtype=np.int64)
    if values and all(type(v) is bool for v in values):
        return np.asarray(values, dtype=bool)
    if all(v is None or (type(v) in (int, float)) or v in ("Infinity", "-Infinity") for v in values):
        return np.asarray([_float(v) for v in values], dtype=np.float64)
    return pd.Series(values, dtype=object)


def _metrics_frame(rows: list[dict]) -> pd.DataFrame:
    if not rows:
        return _empty(METRICS_BASE)
    cols = list(dict.fromkeys(k for r in rows for k in r))
    df = pd.DataFrame({c: _column([r.get(c) for r in rows]) for c in cols})
    return df.sort_values(["iteration", "robot"], kind="stable").reset_index(drop=True)


def _table_frame(batches: list[dict], empty: dict[str, str]) -> pd.DataFrame:
    if not batches:
        return _empty(empty)
    dtypes = batches[0]["dtypes"]
    cols: dict[str, list] = {c: [] for c in dtypes}
    for b in batches:
        for c in cols:
            cols[c].extend(b["columns"].get(c, [None] * int(b["rows"])))
    return pd.DataFrame({c: _decode_column(dtypes[c], v) for c, v in cols.items()})


def read_log(path: Path | str) -> LogData:
    """Everything decodable in run.mcap, closed or truncated. BadInput only if it is not an MCAP file."""
    scan = _scan(_read_bytes(path), str(path))
    metadata = {name: _decode_metadata(m) for name, m in scan.metadata}

    by_topic, done = _iteration_messages(scan.messages)
    seen: set[tuple[int, int]] = set()
    rows = []
    for _, r in by_topic[METRICS]:
        key = (int(r["iteration"]), int(r.get("robot", 0)))
        if key[0] in done and key not in seen:
            seen.add(key)
            rows.append(r)
    metrics = _metrics_frame(rows)

    tables: dict[str, list[dict]] = {EVAL: [], TRAJECTORIES: []}
    summary = None
    for m in scan.messages:
        if m.topic in tables:
            try:
                tables[m.topic].append(json.loads(m.data))
            except ValueError:
                pass
        elif m.topic == SUMMARY:
            try:
                summary = json.loads(m.data)
            except ValueError:
                pass

    last = max(done) if done else None
    after = f"after iteration {last}" if last is not None else "before any iteration was complete"
    if not scan.closed:
        problem = f"truncated {after} ({scan.stop})"
    elif summary is None:
        problem = f"no /summary: the run stopped {after}"
    else:
        problem = None
    return LogData(
        metadata=metadata,
        metrics=metrics,
        eval=_table_frame(tables[EVAL], EVAL_COLUMNS),
        trajectories=_table_frame(tables[TRAJECTORIES], TRAJECTORY_COLUMNS),
        summary=summary,
        complete=problem is None,
        problem=problem,
    )
