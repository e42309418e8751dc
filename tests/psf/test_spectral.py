"""Sensor spectral response: default curves, channel weights, user CSV files."""
import numpy as np
import pytest

from dcdi_core.errors import InputRangeError
from dcdi_core.psf.spectral import (SpectralFileError, SpectralResponse, default_response, load_response,
                                    visible_wavelengths)

HEADER = "wavelength_nm,r,g,b\n"


def write(tmp_path, text, name="sensor.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def small_response():
    """B responds only below 600 nm, R only above 500 nm, G everywhere."""
    wl = np.array([400.0, 500.0, 600.0, 700.0])
    rgb = np.array([[0.0, 0.2, 1.0],
                    [0.0, 1.0, 0.5],
                    [1.0, 0.6, 0.0],
                    [0.5, 0.1, 0.0]])
    return SpectralResponse("small", "test", wl, rgb)


# -- default curves -------------------------------------------------------

def test_default_curves_load_and_cover_visible_band():
    r = default_response()
    assert "NEX-5N" in r.name and "Jiang" in r.source and "10.1109/WACV.2013.6475015" in r.source
    assert r.wavelength_nm[0] <= 400.0 and r.wavelength_nm[-1] >= 700.0
    assert np.all(np.diff(r.wavelength_nm) > 0)
    assert r.rgb.shape == (r.wavelength_nm.size, 3)
    assert np.all(r.rgb >= 0)
    np.testing.assert_array_equal(r.rgb.max(axis=0), 1.0)
    assert np.all(r.at(np.linspace(400, 700, 301)) > 0)        # every channel responds over the band


def test_default_peaks_in_channel_order():
    r = default_response()
    peak = r.wavelength_nm[np.argmax(r.rgb, axis=0)]
    b, g, rr = peak[2], peak[1], peak[0]
    assert b < g < rr
    assert (rr, g, b) == (590.0, 530.0, 450.0)                 # the tabulated NEX-5N peaks


def test_default_numbers_are_the_database_numbers():
    """Spot values of the Jiang et al. 2013 SONY NEX-5N block, before max-normalisation."""
    r = default_response()
    i = {w: k for k, w in enumerate(r.wavelength_nm)}
    assert r.rgb[i[590.0], 0] == 1.0 and r.rgb[i[530.0], 1] == 1.0 and r.rgb[i[450.0], 2] == 1.0
    assert r.rgb[i[400.0], 0] == pytest.approx(0.0073643 / 0.59492, rel=1e-15)
    assert r.rgb[i[720.0], 2] == pytest.approx(4.2452e-05 / 0.78336, rel=1e-15)
    assert r.rgb[i[550.0], 1] == pytest.approx(0.85895, rel=1e-15)
    assert r.wavelength_nm.size == 33 and np.all(np.diff(r.wavelength_nm) == 10.0)


def test_default_is_immutable():
    r = default_response()
    with pytest.raises(ValueError):
        r.rgb[0, 0] = 5.0
    assert default_response() is r


# -- sampling and weights -------------------------------------------------

def test_visible_wavelengths_are_band_midpoints():
    np.testing.assert_allclose(visible_wavelengths(3), [450.0, 550.0, 650.0])
    np.testing.assert_allclose(visible_wavelengths(1), [550.0])
    np.testing.assert_allclose(visible_wavelengths(2, 500.0, 600.0), [525.0, 575.0])
    assert visible_wavelengths(31).size == 31
    for bad in (0, -2, 2.5):
        with pytest.raises(InputRangeError):
            visible_wavelengths(bad)
    with pytest.raises(InputRangeError):
        visible_wavelengths(3, 700.0, 400.0)


@pytest.mark.parametrize("n", [3, 9, 31])
def test_channel_weights_sum_to_one(n):
    r = default_response()
    w = r.channel_weights(visible_wavelengths(n))
    assert w.shape == (n, 3)
    assert np.all(w >= 0)
    np.testing.assert_allclose(w.sum(axis=0), 1.0, rtol=0, atol=1e-12)
    wl = visible_wavelengths(n)
    # each channel's weight is centred where its response is: B < G < R
    centroid = (w * wl[:, None]).sum(axis=0)
    assert centroid[2] < centroid[1] < centroid[0]


def test_channel_weights_equal_spacing_is_proportional_to_response():
    r = default_response()
    wl = visible_wavelengths(9)
    s = r.at(wl)
    np.testing.assert_allclose(r.channel_weights(wl), s / s.sum(axis=0), rtol=1e-13)


def test_channel_weights_any_order_and_uneven_spacing():
    r = default_response()
    wl = np.array([450.0, 500.0, 520.0, 650.0])
    w = r.channel_weights(wl)
    perm = np.array([2, 0, 3, 1])
    np.testing.assert_allclose(r.channel_weights(wl[perm]), w[perm], rtol=1e-14)
    # cell widths 50 (end: reaches half a spacing out), 35, 75, 130 (end)
    width = np.array([50.0, 35.0, 75.0, 130.0])
    expect = r.at(wl) * width[:, None]
    np.testing.assert_allclose(w, expect / expect.sum(axis=0), rtol=1e-13)
    with pytest.raises(InputRangeError):
        r.channel_weights([500.0, 500.0, 600.0])
    with pytest.raises(InputRangeError):
        r.channel_weights([500.0, np.nan])


def test_single_wavelength_weights():
    r = default_response()
    np.testing.assert_array_equal(r.channel_weights([550.0]), [[1.0, 1.0, 1.0]])
    np.testing.assert_array_equal(r.channel_weights(550.0), [[1.0, 1.0, 1.0]])
    s = small_response()
    np.testing.assert_array_equal(s.channel_weights([550.0]), [[1.0, 1.0, 1.0]])
    with pytest.raises(InputRangeError, match=r"channel R.*450.*nm") as e:
        s.channel_weights([450.0])                         # R is 0 below 500 nm
    assert "small" in str(e.value)
    with pytest.raises(InputRangeError, match=r"channel B.*650.*nm"):
        s.channel_weights([650.0])                         # B is 0 above 600 nm
    with pytest.raises(InputRangeError, match=r"channel R.*380.*nm"):
        r.channel_weights([380.0])                         # outside the tabulated range: all zero


def test_at_is_linear_and_zero_outside():
    s = small_response()
    np.testing.assert_allclose(s.at(450.0), [0.0, 0.6, 0.75])
    np.testing.assert_array_equal(s.at([399.9, 700.1, 1000.0]), np.zeros((3, 3)))
    np.testing.assert_array_equal(s.at(400.0), [0.0, 0.2, 1.0])
    assert s.at(np.zeros((2, 5))).shape == (2, 5, 3)
    r = default_response()
    np.testing.assert_array_equal(r.at([300.0, 399.0, 721.0, 900.0]), 0.0)


def test_constructor_normalises_and_validates():
    s = SpectralResponse("x", "y", [500.0, 600.0], [[2.0, 0.0, 4.0], [1.0, 3.0, 0.0]])
    np.testing.assert_array_equal(s.rgb, [[1.0, 0.0, 1.0], [0.5, 1.0, 0.0]])
    with pytest.raises(InputRangeError):
        SpectralResponse("x", "y", [600.0, 500.0], [[1, 1, 1], [1, 1, 1]])
    with pytest.raises(InputRangeError):
        SpectralResponse("x", "y", [500.0, 600.0], [[1, 0, 1], [1, 0, 1]])
    with pytest.raises(InputRangeError):
        SpectralResponse("x", "y", [500.0, 600.0], [[1, -1, 1], [1, 1, 1]])


def test_content_hash_changes_with_numbers_only():
    s = small_response()
    h = s.content_hash()
    assert len(h) == 64 and h == small_response().content_hash()
    rgb = np.array(s.rgb)
    rgb[1, 1] = 0.9
    assert SpectralResponse("small", "test", s.wavelength_nm, rgb).content_hash() != h
    wl = np.array(s.wavelength_nm)
    wl[-1] = 701.0
    assert SpectralResponse("small", "test", wl, s.rgb).content_hash() != h
    assert SpectralResponse("other name", "other source", s.wavelength_nm, s.rgb).content_hash() == h
    assert default_response().content_hash() != h


# -- user CSV files -------------------------------------------------------

def test_csv_round_trip(tmp_path):
    text = ("# name: Test sensor\n# source: made up for a unit test\n# a comment\n\n"
            "Wavelength_nm, R, G, B\n"
            "450, 0.1, 0.2, 2.0\n# comment between rows\n"
            "550, 0.2, 1.0, 0.5\n"
            "650, 1.0, 0.1, 0.0\n")
    r = load_response(write(tmp_path, text))
    assert r.name == "Test sensor" and r.source == "made up for a unit test"
    np.testing.assert_array_equal(r.wavelength_nm, [450.0, 550.0, 650.0])
    np.testing.assert_allclose(r.rgb, [[0.1, 0.2, 1.0], [0.2, 1.0, 0.25], [1.0, 0.1, 0.0]])
    # write it back in the same format and read it again
    rows = "".join(f"{w!r},{a!r},{b!r},{c!r}\n" for w, (a, b, c) in zip(r.wavelength_nm, r.rgb))
    r2 = load_response(write(tmp_path, HEADER + rows, "again.csv"))
    assert r2.name == "again" and r2.source.endswith("again.csv")
    np.testing.assert_array_equal(r2.wavelength_nm, r.wavelength_nm)
    np.testing.assert_array_equal(r2.rgb, r.rgb)
    assert r2.content_hash() == r.content_hash()


def test_csv_columns_in_any_order(tmp_path):
    r = load_response(write(tmp_path, "b,g,r,wavelength_nm\n1,0.5,0.1,450\n0,1,1,650\n"))
    np.testing.assert_array_equal(r.rgb, [[0.1, 0.5, 1.0], [1.0, 1.0, 0.0]])


BAD_FILES = {
    "non_increasing": (HEADER + "450,1,1,1\n550,1,1,1\n550,1,1,1\n", 4, "550"),
    "decreasing": ("# c\n" + HEADER + "450,1,1,1\n440,1,1,1\n", 4, "440"),
    "negative": (HEADER + "450,1,1,1\n550,1,-0.5,1\n", 3, "-0.5"),
    "not_a_number": (HEADER + "450,1,1,1\n550,1,abc,1\n", 3, "abc"),
    "nan": (HEADER + "450,1,nan,1\n550,1,1,1\n", 2, "nan"),
    "missing_column_header": ("wavelength_nm,r,g\n450,1,1\n550,1,1\n", 1, "'b'"),
    "missing_column_row": (HEADER + "450,1,1,1\n550,1,1\n", 3, "550,1,1"),
    "all_zero_channel": ("# c\n\n" + HEADER + "450,1,0,1\n550,1,0,1\n", 3, "'g'"),
    "too_low": (HEADER + "250,1,1,1\n550,1,1,1\n", 2, "250"),
    "too_high": (HEADER + "450,1,1,1\n1200,1,1,1\n", 3, "1200"),
    "one_row": (HEADER + "450,1,1,1\n", 2, "at least 2"),
    "no_header": ("# only comments\n", 1, "header"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_csv_names_file_line_and_value(tmp_path, case):
    text, line, value = BAD_FILES[case]
    p = write(tmp_path, text, f"bad_{case}.csv")
    with pytest.raises(SpectralFileError) as e:
        load_response(p)
    msg = str(e.value)
    assert f"bad_{case}.csv" in msg
    assert f":{line}:" in msg and e.value.line_number == line
    assert value in msg
    assert isinstance(e.value, ValueError)
