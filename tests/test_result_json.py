"""result.json's writer (:func:`volcal.outputs.results.json_text`) against the standard
library's: the same text, byte for byte, as ``json.dumps(_json_safe(doc), indent=1)``
(numpy arrays and scalars, NaN / inf as null, nesting, empty containers, text that json
escapes), so that the faster writer changes no result file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from volcal.outputs.results import _json_safe, json_text


def _reference(obj) -> str:
    return json.dumps(_json_safe(obj), indent=1, allow_nan=False)


floats = st.floats(allow_nan=True, allow_infinity=True)
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    floats,
    st.text(max_size=6),  # unicode, quotes, control characters
    floats.map(np.float64),
    st.integers(-1000, 1000).map(np.int32),
    st.booleans().map(np.bool_),
)
arrays = st.one_of(
    hnp.arrays(np.float64, hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4)),
    hnp.arrays(np.float32, hnp.array_shapes(max_dims=2, max_side=4)),
    hnp.arrays(np.int64, hnp.array_shapes(max_dims=2, max_side=4)),
    hnp.arrays(np.bool_, hnp.array_shapes(max_dims=2, max_side=4)),
)
documents = st.recursive(
    st.one_of(scalars, arrays),
    lambda inner: st.one_of(
        st.lists(inner, max_size=5),
        st.lists(floats, max_size=6),  # a tolist() of floats, NaN among them
        st.lists(inner, max_size=3).map(tuple),
        st.dictionaries(st.one_of(st.text(max_size=5), st.integers(0, 9)), inner, max_size=5),
    ),
    max_leaves=25,
)


@settings(max_examples=300, deadline=None)
@given(documents)
def test_same_text_as_json_dumps(doc):
    assert json_text(doc) == _reference(doc)


def test_same_text_on_edge_cases():
    doc = {
        "cov": np.array([[1.0, np.nan], [np.inf, -0.0]]),
        "empty": [np.zeros((0, 3)), np.zeros((3, 0)), [], {}, ()],
        "scalar_array": np.array(2.5),
        "path": Path("a/b.csv"),
        "complex": np.array([1 + 2j]),
        "text": 'tab\t"quote" µm \u2028',
        "tiny": [5e-324, 1e16, 1.0, -1.5e-7, float("nan")],
        3: {"nested": [[1, 2.0], [True, None]]},
    }
    assert json_text(doc) == _reference(doc)
    json.loads(json_text(doc))  # valid JSON (no NaN)
