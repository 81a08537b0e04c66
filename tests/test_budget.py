"""Uncertainty budgets (volcal.measurement.budget): numbers, sampling, budget files."""
from __future__ import annotations

import math

import numpy as np
import pytest

from volcal.base.exceptions import InputError
from volcal.measurement.budget import (
    PAPER001_DRIFT,
    Budget,
    DriftModel,
    Source,
    bundled_budgets,
    default_budget,
    load_budget,
)
from volcal.model.spec import resolve_model

N = 100_000
S3 = math.sqrt(3.0)


@pytest.fixture(scope="module")
def paper002() -> Budget:
    return load_budget("paper002")


# ---------------------------------------------------------------------------------------
# the bundled default against hand-computed values


def test_bundled_default_is_paper002(paper002):
    assert "paper002" in bundled_budgets()
    assert default_budget() == paper002
    assert [s.name for s in paper002.length_sources] == ["laser_length", "resolution",
                                                         "fixed_sphere", "reflector_form"]
    assert sorted(paper002.axis_sources) == ["X", "Y", "Z"]
    assert paper002.drift is None and not paper002.drift_sources


def test_length_sigma_hand_computed(paper002):
    # L = 1000 mm: U = 0.2 + 0.3 = 0.5 um at k = 2 -> 0.25 um, with 0.5, 0.1, 0.03 um
    # rectangular half-widths (u = a / sqrt 3), in quadrature
    u1000_um = math.sqrt(0.25 ** 2 + (0.5 / S3) ** 2 + (0.1 / S3) ** 2 + (0.03 / S3) ** 2)
    u0_um = math.sqrt(0.1 ** 2 + (0.5 / S3) ** 2 + (0.1 / S3) ** 2 + (0.03 / S3) ** 2)
    u3000_um = math.sqrt(0.55 ** 2 + (0.5 / S3) ** 2 + (0.1 / S3) ** 2 + (0.03 / S3) ** 2)
    got = paper002.length_sigma(np.array([1000.0, 0.0, 3000.0]))
    np.testing.assert_allclose(got, np.array([u1000_um, u0_um, u3000_um]) * 1e-3, rtol=1e-12)
    assert abs(u1000_um - 0.38661) < 1e-5
    # shape is kept; a negative (relative) length uses |L|
    assert paper002.length_sigma(np.full((2, 3), 1000.0)).shape == (2, 3)
    assert paper002.length_sigma(np.array([-1000.0]))[0] == pytest.approx(u1000_um * 1e-3)


def test_axis_repeatability(paper002):
    assert paper002.axis_repeatability("X") == ("rectangular", pytest.approx(0.8e-3))
    assert paper002.axis_repeatability("Y") == ("rectangular", pytest.approx(0.6e-3))
    assert paper002.axis_repeatability("Z") == ("rectangular", pytest.approx(0.3e-3))
    assert paper002.axis_repeatability("C") == ("none", 0.0)
    assert paper002.axis_sigma("X") == pytest.approx(0.8e-3 / S3)
    b = Budget("b", (Source("rc", 4.0, "arcsec", "normal", "axis:C", k=2.0),))
    dist, sigma = b.axis_repeatability("C")
    assert dist == "normal" and sigma == pytest.approx(2.0 * math.pi / 648000)  # rad


# ---------------------------------------------------------------------------------------
# sampling


def _frac_within_sigma(x: np.ndarray, sigma: float) -> float:
    return float(np.mean(np.abs(x) <= sigma))


def test_sampled_normal_source():
    s = Source("n", 3.0, "um", "normal", "length", k=2.0)  # u = 1.5 um
    x = s.sample(N, np.random.default_rng(11))
    sigma = 1.5e-3
    assert abs(x.mean()) < 5 * sigma / math.sqrt(N)
    assert x.std() == pytest.approx(sigma, rel=0.015)
    assert _frac_within_sigma(x, sigma) == pytest.approx(0.6827, abs=0.006)


def test_sampled_rectangular_source():
    s = Source("r", 0.5, "um", "rectangular", "length")  # a = 0.5 um
    x = s.sample(N, np.random.default_rng(12))
    a = 0.5e-3
    assert np.all(np.abs(x) <= a) and np.abs(x).max() > 0.999 * a
    assert abs(x.mean()) < 5 * (a / S3) / math.sqrt(N)
    assert x.std() == pytest.approx(a / S3, rel=0.015)
    assert _frac_within_sigma(x, a / S3) == pytest.approx(1 / S3, abs=0.006)


def test_sampled_length_errors_match_length_sigma(paper002):
    L = np.full(N, 1000.0)
    e = paper002.sample_length_errors(L, np.random.default_rng(13))
    sigma = paper002.length_sigma(np.array([1000.0]))[0]
    assert e.shape == (N,)
    assert abs(e.mean()) < 5 * sigma / math.sqrt(N)
    assert e.std() == pytest.approx(sigma, rel=0.015)


def test_per_metre_part_grows_with_length():
    s = Source("l", 0.0, "um", "rectangular", "length", per_metre=1.0)  # a = L/1000 um
    x = s.sample(None, np.random.default_rng(14), L_mm=np.array([0.0, 2000.0] * (N // 2)))
    assert np.all(x[::2] == 0.0)
    assert np.abs(x[1::2]).max() <= 2e-3
    assert x[1::2].std() == pytest.approx(2e-3 / S3, rel=0.02)


def test_sampled_axis_errors(paper002):
    x = paper002.sample_axis_errors(["X", "Y", "Z", "C"], N, np.random.default_rng(15))
    assert x.shape == (N, 4)
    np.testing.assert_allclose(x[:, :3].std(axis=0), np.array([0.8, 0.6, 0.3]) * 1e-3 / S3,
                               rtol=0.015)
    assert np.all(np.abs(x[:, :3]) <= np.array([0.8, 0.6, 0.3]) * 1e-3)
    assert np.all(x[:, 3] == 0.0)
    # a rotary axis in arcsec comes out in rad
    b = Budget("b", (Source("rc", 2.0, "arcsec", "rectangular", "axis:C"),))
    c = b.sample_axis_errors(["C"], N, np.random.default_rng(16))[:, 0]
    assert np.abs(c).max() <= 2.0 * math.pi / 648000
    assert c.std() == pytest.approx(2.0 * math.pi / 648000 / S3, rel=0.015)


def test_sampling_is_seeded(paper002):
    L = np.linspace(100, 2000, 50)
    a = paper002.sample_length_errors(L, np.random.default_rng(5))
    b = paper002.sample_length_errors(L, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(paper002.sample_length_errors(L, 5), a)  # integer seed
    with pytest.raises(TypeError):
        paper002.sample_length_errors(L, None)


# ---------------------------------------------------------------------------------------
# drift


def test_paper001_drift_model():
    # amplitudes read in metres: 8.939e-6 m = 8.939e-3 mm
    assert max(PAPER001_DRIFT.amplitude_mm) == pytest.approx(8.939e-3)
    t = np.array([0.0, 0.25])
    fixed = DriftModel(PAPER001_DRIFT.amplitude_mm, PAPER001_DRIFT.omega_rad_s,
                       PAPER001_DRIFT.phase_rad, random_phase=False)
    A = np.array(PAPER001_DRIFT.amplitude_mm)
    w = np.array(PAPER001_DRIFT.omega_rad_s)
    ph = np.array(PAPER001_DRIFT.phase_rad)
    expected = [np.sum(A * np.sin(w * tk + ph)) for tk in t]
    np.testing.assert_allclose(fixed.sample(t, np.random.default_rng(0)), expected)
    sigma = math.sqrt(np.sum(A ** 2) / 2)
    assert PAPER001_DRIFT.sigma_mm == pytest.approx(sigma)
    # one random-phase realisation over many random times has the process' std
    times = np.random.default_rng(1).uniform(0, 1e4, N)
    f = default_budget().with_drift(PAPER001_DRIFT).sample_drift(times, np.random.default_rng(2))
    assert f.std() == pytest.approx(sigma, rel=0.03)
    assert np.abs(f).max() <= A.sum()


def test_drift_rate_source_and_no_drift(paper002):
    np.testing.assert_array_equal(paper002.sample_drift(np.arange(5.0), 0), np.zeros(5))
    b = Budget("b", (Source("thermal", 1.0, "um/min", "rectangular", "drift"),))
    t = np.array([10.0, 70.0, 130.0])
    d = b.sample_drift(t, np.random.default_rng(3))
    assert d[0] == 0.0
    rate = d[1] / 60.0
    assert abs(rate) <= 1e-3 / 60.0
    assert d[2] == pytest.approx(rate * 120.0)
    with pytest.raises(ValueError, match="finite time stamps"):
        b.sample_drift(np.array([0.0, np.nan]), 0)


# ---------------------------------------------------------------------------------------
# budget files

GOOD = """
name = "mine"
description = "test budget"

[[source]]
name = "length"
applies_to = "length"
distribution = "normal"
magnitude = 1
per_metre = 2
unit = "um"
k = 2

[[source]]
name = "rep_C"
applies_to = "axis:C"
distribution = "rectangular"
magnitude = 5
unit = "urad"

[drift]
unit = "nm"
random_phase = false
terms = [{ amplitude = 100, omega_rad_s = 2.0, phase_rad = 0.5 }]
"""


def test_user_budget_file(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text(GOOD)
    b = load_budget(path)
    assert b.name == "mine" and b.origin == str(path)
    assert b.length_sigma(np.array([500.0]))[0] == pytest.approx((1 + 2 * 0.5) / 2 * 1e-3)
    assert b.axis_repeatability("C") == ("rectangular", pytest.approx(5e-6))
    assert b.drift.amplitude_mm == pytest.approx((1e-4,)) and not b.drift.random_phase
    assert b.sample_drift(np.array([1.0]), 0)[0] == pytest.approx(1e-4 * math.sin(2.5))
    assert load_budget(str(path)) == b
    b.check_axes(resolve_model("head_bc"))  # C is rotary: urad fits


def test_drift_preset(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text(GOOD.split("[drift]")[0] + '[drift]\npreset = "paper001"\n')
    assert load_budget(path).drift == PAPER001_DRIFT


BAD = [
    ("name = [", None, "not valid TOML"),
    ('description = "x"\n[[source]]\nname="a"', "name", "missing required key"),
    ('name = "b"\ncolour = 1\n[[source]]', "colour", "unknown top-level key"),
    ('name = "b"', "source", "expected one or more [[source]] tables"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\ndistribution = "normal"\n'
     'unit = "um"\nk = 2', "magnitude", "missing required key"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\ndistribution = "normal"\n'
     'magnitude = "0.2"\nunit = "um"\nk = 2', "magnitude", "expected a number, got str"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\ndistribution = "normal"\n'
     'magnitude = -1\nunit = "um"\nk = 2', "magnitude", "expected a magnitude >= 0"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\ndistribution = "uniform"\n'
     'magnitude = 1\nunit = "um"', "distribution", 'expected "normal" or "rectangular"'),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\ndistribution = "normal"\n'
     'magnitude = 1\nunit = "um"', "k", "needs its coverage factor k"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\n'
     'distribution = "rectangular"\nmagnitude = 1\nunit = "um"\nk = 2', "k",
     "k applies to normal sources only"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\n'
     'distribution = "rectangular"\nmagnitude = 1\nunit = "arcsec"', "unit",
     "expected a length unit"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "axis:X"\n'
     'distribution = "rectangular"\nmagnitude = 1\nunit = "um"\nper_metre = 1', "per_metre",
     "per_metre applies to length sources only"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "axis:x"\n'
     'distribution = "rectangular"\nmagnitude = 1\nunit = "um"', "applies_to",
     'expected "length", "drift" or "axis:<NAME>"'),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\n'
     'distribution = "rectangular"\nmagnitud = 1\nunit = "um"', "magnitud",
     "did you mean 'magnitude'"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "axis:X"\ndistribution = "rectangular"\n'
     'magnitude = 1\nunit = "um"\n[[source]]\nname = "a"\napplies_to = "axis:Y"\n'
     'distribution = "rectangular"\nmagnitude = 1\nunit = "um"', "source.name",
     "duplicate source name"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "axis:X"\ndistribution = "rectangular"\n'
     'magnitude = 1\nunit = "um"\n[[source]]\nname = "c"\napplies_to = "axis:X"\n'
     'distribution = "rectangular"\nmagnitude = 1\nunit = "um"', "source.applies_to",
     "more than one source for axis"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\ndistribution = "rectangular"\n'
     'magnitude = 1\nunit = "um"\n[drift]\npreset = "paper999"', "drift.preset",
     "unknown drift preset"),
    ('name = "b"\n[[source]]\nname = "a"\napplies_to = "length"\ndistribution = "rectangular"\n'
     'magnitude = 1\nunit = "um"\n[drift]\nunit = "s"\nterms = [{amplitude = 1, '
     'omega_rad_s = 1}]', "drift.unit", "expected the amplitude unit"),
]


@pytest.mark.parametrize("text, key, fragment", BAD)
def test_bad_budget_files_rejected(tmp_path, text, key, fragment):
    path = tmp_path / "bad_budget.toml"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        load_budget(path)
    msg = str(info.value)
    assert "bad_budget.toml" in msg
    assert fragment in msg
    if key is not None:
        assert info.value.column == key and f"'{key}'" in msg


def test_unknown_budget_name_lists_bundled():
    with pytest.raises(InputError, match=r"no bundled budget named 'paper999'.*paper002"):
        load_budget("paper999")


def test_check_axes_against_model(tmp_path, paper002):
    paper002.check_axes(resolve_model("mcv754_wxyzt"))
    b = Budget("b", (Source("rc", 1.0, "um", "rectangular", "axis:C"),))
    with pytest.raises(InputError, match="axis C is rotary"):
        b.check_axes(resolve_model("head_bc"))
    with pytest.raises(InputError, match="does not have"):
        b.check_axes(resolve_model("mcv754_wxyzt"))


def test_source_validation_in_python():
    with pytest.raises(InputError, match="coverage factor"):
        Source("n", 1.0, "um", "normal", "length")
    with pytest.raises(InputError, match="drift-rate unit"):
        Source("d", 1.0, "um", "rectangular", "drift")
