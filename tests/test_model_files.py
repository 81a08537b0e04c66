"""Bad model files are rejected with an InputError that names the file, the key and what was
expected; loading a model file never executes anything."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from volcal.base.exceptions import InputError
from volcal.model.spec import bundled_models, load_model_file, resolve_model

GOOD_AXES = """
[[axis]]
name = "X"
kind = "linear"
direction = "+x"
branch = "tool"
travel = [0.0, 754.0]

[[axis]]
name = "Y"
kind = "linear"
direction = "+y"
branch = "tool"
travel = [0.0, 500.0]
"""


def write(tmp_path: Path, text: str, name: str = "bad.toml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def model(axes: str, header: str = 'name = "m"\n') -> str:
    return header + axes


def axis(**kw) -> str:
    """One [[axis]] table; values are TOML source text."""
    d = {"name": '"Z"', "kind": '"linear"', "direction": '"+z"', "branch": '"tool"',
         "travel": "[-550.0, 0.0]"}
    d.update(kw)
    return "\n[[axis]]\n" + "".join(f"{k} = {v}\n" for k, v in d.items() if v is not None)


def reject(tmp_path: Path, text: str, *patterns: str) -> InputError:
    """Load ``text`` as a file: it must raise InputError naming the file and matching every
    pattern (regular expressions, searched in the message)."""
    p = write(tmp_path, text)
    with pytest.raises(InputError) as info:
        load_model_file(p)
    msg = str(info.value)
    assert str(p) in msg, msg
    for pat in patterns:
        assert re.search(pat, msg), f"{pat!r} not in {msg!r}"
    return info.value


def test_a_good_file_loads(tmp_path):
    spec = load_model_file(write(tmp_path, model(GOOD_AXES + axis())))
    assert spec.axis_names == ["X", "Y", "Z"]
    assert spec.axis("Z").travel == (-550.0, 0.0)


def test_unknown_axis_kind(tmp_path):
    err = reject(tmp_path, model(GOOD_AXES + axis(kind='"prismatic"')),
                 r"axis Z", r"'kind'", r"prismatic", r'"linear" or "rotary"')
    assert err.column == "kind"


def test_duplicate_axis_name(tmp_path):
    reject(tmp_path, model(GOOD_AXES + axis(name='"Y"', direction='"+z"')),
           r"duplicate axis name", r"\['Y'\]", r"axis\.name")


def test_missing_travel(tmp_path):
    err = reject(tmp_path, model(GOOD_AXES + axis(travel=None)),
                 r"#3", r"'travel'", r"missing required key")
    assert err.column == "travel"


@pytest.mark.parametrize("key, value, pattern", [
    ("travel", '["0", "2*377"]', r"'travel'.*expected a number, got str '0'"),
    ("travel", '[0.0, "2*377"]', r"'travel'.*expected a number, got str '2\*377'"),
    ("reference", '"1+1"', r"'reference'.*expected a number, got str '1\+1'"),
    ("travel", "[0.0, inf]", r"'travel'.*expected a finite number, got inf"),
    ("reference", "nan", r"'reference'.*expected a finite number"),
    ("reference", "true", r"'reference'.*expected a number, got bool"),
    ("travel", "[-550.0, 0.0, 10.0]", r"'travel'.*expected \[min, max\]"),
    ("travel", '"-550..0"', r"'travel'.*expected \[min, max\]"),
    ("travel", "[0.0, -550.0]", r"'travel'.*expected min < max"),
    ("direction", '"z"', r"'direction'.*expected one of \['\+x'"),
    ("direction", '["+z"]', r"'direction'.*expected one of"),
    ("branch", '"spindle"', r"'branch'.*expected \"workpiece\" or \"tool\""),
    ("name", '"z"', r"'name'.*expected an axis name"),
    ("name", "3", r"'name'.*expected an axis name"),
    ("center", "[0.0, 0.0, 0.0]", r"'center'.*applies to rotary axes only"),
])
def test_bad_axis_values(tmp_path, key, value, pattern):
    reject(tmp_path, model(GOOD_AXES + axis(**{key: value})), r"\[\[axis\]\] #3", pattern)


def test_expression_for_rotary_centre(tmp_path):
    text = model(GOOD_AXES + axis() + axis(name='"C"', kind='"rotary"', direction='"+z"',
                                           travel="[-180.0, 180.0]",
                                           center='[0.0, "sqrt(2)", 0.0]'))
    reject(tmp_path, text, r"axis C", r"'center'", r"expected a number, got str 'sqrt\(2\)'")


def test_string_instead_of_table(tmp_path):
    reject(tmp_path, model('axis = "X"\n'), r"'axis'", r"\[\[axis\]\] tables")
    reject(tmp_path, model('axis = ["X", "Y"]\n'), r"'axis\[0\]'", r"expected a table")


def test_single_table_instead_of_array(tmp_path):
    text = model('[axis]\nname = "X"\nkind = "linear"\ndirection = "+x"\nbranch = "tool"\n'
                 'travel = [0.0, 1.0]\n')
    reject(tmp_path, text, r"'axis'", r"expected one or more \[\[axis\]\] tables")


def test_unknown_keys(tmp_path):
    reject(tmp_path, model(GOOD_AXES + axis(travle="[0.0, 1.0]")),
           r"#3", r"unknown key\(s\) \['travle'\]", r"allowed: \[.*'travel'")
    reject(tmp_path, model(GOOD_AXES, header='name = "m"\nunits = "inch"\n'),
           r"unknown top-level key\(s\) \['units'\]",
           r"allowed: \['axis', 'description', 'name', 'tool_errors'\]")


def test_missing_or_bad_model_name(tmp_path):
    reject(tmp_path, GOOD_AXES, r"'name'", r"missing required key")
    reject(tmp_path, model(GOOD_AXES, header="name = 5\n"), r"'name'", r"expected a model name")
    # the name becomes part of a cache file name: no path separators
    reject(tmp_path, model(GOOD_AXES, header='name = "../../etc/m"\n'), r"'name'",
           r"expected a model name")


@pytest.mark.parametrize("key, value, pattern", [
    ("errors", '["EXZ", "EQZ"]', r"'errors'.*unknown error name\(s\) \['EQZ'\].*'EXZ'"),
    ("errors", '"some"', r"'errors'.*expected \"all\", \"none\" or a list"),
    ("exclude", '["EAZ", "EXX"]', r"'exclude'.*unknown error name\(s\) \['EXX'\]"),
    ("exclude", '"EAZ"', r"'exclude'.*expected a list of error names"),
    ("exclude", "false", r"'exclude'.*expected a list of error names"),
    ("location", '["EC0Y"]', r"'location'.*unknown error name\(s\) \['EC0Y'\]"),
])
def test_unknown_error_names(tmp_path, key, value, pattern):
    reject(tmp_path, model(GOOD_AXES + axis(**{key: value})), r"axis Z", pattern)


def test_error_selection_works(tmp_path):
    from volcal.model.spec import error_symbols
    spec = load_model_file(write(tmp_path, model(GOOD_AXES + axis(
        errors='["EXZ", "EYZ", "EZZ"]', exclude='["EA0Z"]'))))
    names = [s.name for s in error_symbols(spec) if s.axis == "Z"]
    assert names == ["EXZ", "EYZ", "EZZ", "EB0Z"]


def test_workpiece_axis_after_tool_axis(tmp_path):
    reject(tmp_path, model(GOOD_AXES + axis(branch='"workpiece"')),
           r"'axis\.branch'", r"chain order", r"workpiece-branch axes.*before.*tool-branch")


def test_reference_outside_travel(tmp_path):
    err = reject(tmp_path, model(GOOD_AXES + axis(reference="10.0")),
                 r"axis Z", r"'reference'", r"reference 10\.0 outside travel \[-550\.0, 0\.0\]")
    assert err.column == "reference"


def test_two_linear_axes_in_one_direction(tmp_path):
    reject(tmp_path, model(GOOD_AXES + axis(direction='"-y"')), r"share a direction")


@pytest.mark.parametrize("text", [
    "this is not TOML\n",
    'name = "m"\n[[axis]\n',
    'name = "m"\nname = "n"\n',
])
def test_not_toml(tmp_path, text):
    reject(tmp_path, text, r"not valid TOML")


def test_binary_file(tmp_path):
    p = tmp_path / "bin.toml"
    p.write_bytes(b'name = "\xff\xfe"\n')
    with pytest.raises(InputError, match=r"bin\.toml.*not a UTF-8 text file"):
        load_model_file(p)


def test_missing_file_and_unknown_model(tmp_path):
    with pytest.raises(InputError, match=r"cannot read model file"):
        load_model_file(tmp_path / "nope.toml")
    with pytest.raises(InputError, match=r"no bundled model named 'nope'.*mcv754_wxyzt"):
        resolve_model("nope")


def test_loading_never_executes_code(tmp_path, monkeypatch):
    marker = tmp_path / "pwned"
    payload = f"__import__('pathlib').Path({str(marker)!r}).touch()"
    monkeypatch.chdir(tmp_path)
    texts = [
        # plain Python: not TOML
        f"import pathlib\npathlib.Path({str(marker)!r}).touch()\n",
        payload + "\n",
        # Python in string values where numbers, names or lists belong
        model(GOOD_AXES + axis(travel=f'["{payload}", 0.0]')),
        model(GOOD_AXES + axis(reference=repr(payload).replace("'", '"'))),
        model(GOOD_AXES + axis(errors=f'"{payload}"')),
        model(GOOD_AXES + axis(kind=f'"{payload}"')),
        model(GOOD_AXES, header=f'name = "{payload}"\n'),
    ]
    for k, text in enumerate(texts):
        p = write(tmp_path, text, f"evil{k}.toml")
        with pytest.raises(InputError, match=re.escape(str(p))):
            load_model_file(p)
    # a description may hold any text: it is kept as text, never run
    spec = load_model_file(write(tmp_path, model(GOOD_AXES, header=f'name = "m"\n'
                                                 f'description = "{payload}"\n'), "ok.toml"))
    assert spec.description == payload
    assert not marker.exists()


def test_bundled_models_are_valid():
    for name, path in bundled_models().items():
        spec = load_model_file(path)
        assert spec.name == name
