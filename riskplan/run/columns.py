"""A run's tables while it is written: columns, an ordered dict of equal-length numpy arrays, and their parquet
files written by pyarrow. `riskplan train` builds, logs and writes its tables without pandas (a quarter of a
second to import); `load_run` reads the files back as DataFrames, with the dtypes pandas gave them before.

Every parquet file is read and written through an open file (`read_parquet`, `write_parquet`, `frame_to_parquet`):
arrow encodes a path it is given as UTF-8, which fails for a folder whose name the system's locale decoded with
escapes (a non-ASCII name under LC_ALL=C without UTF-8 mode); Python's open() takes every name the system gave."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

Columns = dict[str, np.ndarray]


def concat(parts: list[Columns]) -> Columns:
    """The rows of each part in turn (every part has the first one's columns)."""
    return {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}


def rows_where(table: Columns, mask: np.ndarray) -> Columns:
    """The rows where mask is true, in order."""
    return {name: values[mask] for name, values in table.items()}


def from_rows(rows: list[dict]) -> Columns:
    """Columns of row dicts, in the order the keys first appear, typed as pandas.DataFrame(rows) types them: all
    bool -> bool, all integer -> int64, numbers with gaps (a missing key or None) -> float64 with NaN, else
    object."""
    names = list(dict.fromkeys(key for row in rows for key in row))
    return {name: _column([row.get(name) for row in rows]) for name in names}


def sorted_by(table: Columns, *keys: str) -> Columns:
    """The rows sorted by keys[0], then keys[1], ... (stable)."""
    order = np.lexsort([table[key] for key in reversed(keys)])
    return {name: values[order] for name, values in table.items()}


def write_parquet(table: Mapping[str, np.ndarray], path: Path) -> None:
    """One parquet file of the columns, as pandas writes a DataFrame of them (text as large_string, NaN as null).

    Integer columns are delta-encoded and every page is zstd-compressed (level 1): an evaluation's episode numbers
    count up and its counts are small, so a run's eval.parquet is about 40% smaller (a 9-robot team's 900,000 rows:
    10.5 MB -> 7.6 MB) in the same time to write, and quicker to read back, than with pyarrow's defaults
    (dictionaries and snappy). The values are the same either way."""
    names = list(table)
    integers = [name for name in names if table[name].dtype.kind in "iu"]
    with open(path, "wb") as handle:
        pq.write_table(
            pa.Table.from_arrays([_arrow(values) for values in table.values()], names=names),
            handle,
            compression="zstd",
            compression_level=1,
            use_dictionary=[name for name in names if name not in integers],  # a delta-encoded column has none
            column_encoding=dict.fromkeys(integers, "DELTA_BINARY_PACKED"),
        )


def read_parquet(path: Path, columns: list[str] | None = None):
    """A parquet file as a pandas DataFrame (only `columns`, when given), read through an open file."""
    import pandas as pd  # lazy: `riskplan train` never reads a table back (pandas takes a quarter of a second)

    with open(path, "rb") as handle:
        return pd.read_parquet(handle, columns=columns)


def frame_to_parquet(frame, path: Path) -> None:
    """A pandas DataFrame as a parquet file, without its index, written through an open file."""
    with open(path, "wb") as handle:
        frame.to_parquet(handle, index=False)


def _arrow(values: np.ndarray) -> pa.Array:
    """An arrow array of a column, built from its buffers: pa.array() imports pandas to ask whether its argument
    is a pandas object, an import `riskplan train` does not pay for (a test checks it never imports pandas)."""
    n = len(values)
    if values.dtype.kind == "O" and n == 0:  # pandas cannot tell an empty column's type: arrow's null type
        return pa.nulls(0)
    if values.dtype.kind == "O":  # text
        encoded = [str(v).encode() for v in values]
        offsets = np.zeros(n + 1, dtype=np.int64)
        np.cumsum([len(b) for b in encoded], out=offsets[1:])
        return pa.Array.from_buffers(
            pa.large_string(), n, [None, pa.py_buffer(offsets), pa.py_buffer(b"".join(encoded))]
        )
    if values.dtype.kind == "b":
        return pa.Array.from_buffers(pa.bool_(), n, [None, pa.py_buffer(np.packbits(values, bitorder="little"))])
    values = np.ascontiguousarray(values)
    valid = None
    if values.dtype.kind == "f" and np.isnan(values).any():  # pandas' missing value: null in the file
        valid = pa.py_buffer(np.packbits(~np.isnan(values), bitorder="little"))
    return pa.Array.from_buffers(pa.from_numpy_dtype(values.dtype), n, [valid, pa.py_buffer(values)])


def _column(values: list) -> np.ndarray:
    """One column of Python (or numpy) scalars, typed as pandas infers it."""
    if values and all(isinstance(v, (bool, np.bool_)) for v in values):
        return np.asarray(values, dtype=bool)
    if values and all(isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)) for v in values):
        return np.asarray(values, dtype=np.int64)
    if all(
        v is None or (isinstance(v, (int, float, np.number)) and not isinstance(v, (bool, np.bool_))) for v in values
    ):
        return np.asarray([np.nan if v is None else v for v in values], dtype=np.float64)
    return np.asarray(values, dtype=object)
