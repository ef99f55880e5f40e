"""riskplan.run.columns: a run's tables as numpy columns, typed as pandas types the same rows, and parquet files
that read back as the DataFrames pandas would have written."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from riskplan.run.columns import concat, from_rows, rows_where, sorted_by, write_parquet

ROWS = [  # what metrics rows hold: ints, bools, Python and numpy floats, NaN, a key some rows lack, None
    {"iteration": 1, "robot": 0, "healthy": True, "cvar": 1.5, "error": np.float64(np.nan), "staleness": 2},
    {"iteration": 0, "robot": -1, "healthy": False, "cvar": np.float64(-0.25), "error": 0.5},
    {"iteration": 0, "robot": 0, "healthy": np.bool_(True), "cvar": 3, "error": None, "staleness": np.int64(0)},
]


def test_from_rows_types_and_orders_columns_as_pandas_does():
    table = from_rows(ROWS)
    frame = pd.DataFrame(ROWS)
    assert list(table) == list(frame.columns)
    for name, values in table.items():
        assert values.dtype == frame[name].dtype, name
        np.testing.assert_array_equal(values, frame[name].to_numpy(), err_msg=name)


def test_text_and_mixed_columns_are_objects():
    table = from_rows([{"policy": "initial", "mixed": 1}, {"policy": "final", "mixed": True}])
    assert table["policy"].dtype == object and table["policy"].tolist() == ["initial", "final"]
    assert table["mixed"].dtype == object  # pandas keeps 1 and True apart too


def test_sorted_by_is_pandas_sort_values():
    table = sorted_by(from_rows(ROWS), "iteration", "robot")
    frame = pd.DataFrame(ROWS).sort_values(["iteration", "robot"], ignore_index=True)
    for name, values in table.items():
        np.testing.assert_array_equal(values, frame[name].to_numpy(), err_msg=name)


def test_concat_and_rows_where():
    a = {"x": np.array([1, 2]), "y": np.array([0.5, 1.5])}
    b = {"x": np.array([3]), "y": np.array([2.5])}
    both = concat([a, b])
    assert both["x"].tolist() == [1, 2, 3] and both["y"].tolist() == [0.5, 1.5, 2.5]
    kept = rows_where(both, both["x"] != 2)
    assert kept["x"].tolist() == [1, 3] and kept["y"].tolist() == [0.5, 2.5]


@pytest.mark.parametrize("rows", [0, 1, 9, 1000])  # bools pack 8 to a byte: lengths on either side of it
def test_parquet_files_are_what_pandas_writes(tmp_path, rows):
    rng = np.random.default_rng(rows)
    reward = rng.normal(size=rows)
    reward[::7] = np.nan  # pandas writes NaN as null
    table = {
        "policy": np.array([["initial", "final", "ü 源"][i % 3] for i in range(rows)], dtype=object),
        "episode": np.arange(rows, dtype=np.int64),
        "healthy": rng.random(rows) < 0.5,
        "reward": reward,
    }
    write_parquet(table, tmp_path / "ours.parquet")
    pd.DataFrame(table).to_parquet(tmp_path / "pandas.parquet", index=False)
    ours, theirs = pq.read_table(tmp_path / "ours.parquet"), pq.read_table(tmp_path / "pandas.parquet")
    assert ours.replace_schema_metadata(None).equals(theirs.replace_schema_metadata(None))
    pd.testing.assert_frame_equal(
        pd.read_parquet(tmp_path / "ours.parquet"), pd.read_parquet(tmp_path / "pandas.parquet")
    )


def test_parquet_integers_are_delta_encoded_and_pages_zstd_compressed(tmp_path):
    """An evaluation's columns (episode numbers counting up, small counts, robots, rewards) are written with their
    integers delta-encoded and every page zstd-compressed: the same values as pyarrow's defaults give, in a file
    at least a fifth smaller."""
    rng = np.random.default_rng(3)
    rows = 60_000
    table = {
        "episode": np.tile(np.arange(rows // 3, dtype=np.int64), 3),
        "robot": np.repeat(np.arange(3, dtype=np.int64), rows // 3),
        "total_reward": rng.normal(2000.0, 300.0, rows),
        "steps": rng.integers(5, 40, rows),
        "healthy": rng.random(rows) < 0.9,
    }
    write_parquet(table, tmp_path / "ours.parquet")
    pd.DataFrame(table).to_parquet(tmp_path / "defaults.parquet", index=False)
    ours = pq.ParquetFile(tmp_path / "ours.parquet")
    columns = [ours.metadata.row_group(0).column(i) for i in range(ours.metadata.num_columns)]
    assert {column.compression for column in columns} == {"ZSTD"}
    encodings = {column.path_in_schema: set(column.encodings) for column in columns}
    assert all("DELTA_BINARY_PACKED" in encodings[name] for name in ("episode", "robot", "steps"))
    assert not any("DELTA_BINARY_PACKED" in encodings[name] for name in ("total_reward", "healthy"))
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "ours.parquet"), pd.DataFrame(table))
    assert (tmp_path / "ours.parquet").stat().st_size < 0.8 * (tmp_path / "defaults.parquet").stat().st_size
