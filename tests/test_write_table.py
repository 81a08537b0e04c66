"""The fast table writer of the result folder writes what pandas' to_csv writes, byte for
byte (the reference is pandas' own writer, not the code under test)."""

from __future__ import annotations

import numpy as np
import pandas as pd
from hypothesis import given, settings
from hypothesis import strategies as st

from volcal.outputs.results import write_table


def _same_as_pandas(df: pd.DataFrame, tmp_path) -> None:
    ours, ref = tmp_path / "ours.csv", tmp_path / "ref.csv"
    write_table(df, ours)
    df.to_csv(ref, index=False)
    assert ours.read_bytes() == ref.read_bytes()


def test_awkward_values_as_pandas(tmp_path):
    f = [
        0.0,
        -0.0,
        1e16,
        1e15,
        123456789012345678.0,
        1e-5,
        1e-4,
        0.1,
        np.nan,
        np.inf,
        -np.inf,
        5e-324,
        1.7976931348623157e308,
        -2.5,
        214.26497988927164,
        3.0,
    ]
    n = len(f)
    df = pd.DataFrame(
        {
            "station": pd.array([f"LT{i}" for i in range(n - 1)] + [None], dtype="string"),
            "point": [f"p{i:05d}" for i in range(n)],
            "length_mm": f,
            "count": np.arange(n) - 3,
            "rejected": np.arange(n) % 3 == 0,
        }
    )
    _same_as_pandas(df, tmp_path)


def test_falls_back_where_pandas_quotes(tmp_path):
    df = pd.DataFrame({"station": ["a,b", 'say "x"', "plain"], "value_um": [1.0, 2.0, 3.0]})
    _same_as_pandas(df, tmp_path)
    _same_as_pandas(df.iloc[:0], tmp_path)
    _same_as_pandas(pd.DataFrame({"t_s": pd.array([1, None, 3], dtype="Int64")}), tmp_path)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=1, max_size=40))
def test_any_float_as_pandas(tmp_path_factory, values):
    tmp = tmp_path_factory.mktemp("w")
    _same_as_pandas(pd.DataFrame({"x_mm": values, "flag": [v > 0 for v in values]}), tmp)


def test_written_in_blocks_as_pandas(tmp_path, monkeypatch):
    """Blocks of rows (a long table's texts are not held at once): block edges anywhere,
    and a text needing quotes only in a later block after earlier blocks were written."""
    import volcal.outputs.results as results

    monkeypatch.setattr(results, "_WRITE_BLOCK_ROWS", 3)
    n = 11
    df = pd.DataFrame(
        {
            "station": [f"LT{i % 4}" for i in range(n)],
            "length_mm": np.linspace(-1.0, 1.0, n) ** 3 * 1e3,
            "rejected": np.arange(n) % 2 == 0,
        }
    )
    for rows in (1, 3, 4, 11):
        _same_as_pandas(df.iloc[:rows], tmp_path)
    late = df.copy()
    late.loc[9, "station"] = "LT,9"
    _same_as_pandas(late, tmp_path)
