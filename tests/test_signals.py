"""Forcing signals against closed forms, scipy and FFTs; numpy and CasADi faces agree."""

import casadi as ca
import numpy as np
import pytest
import scipy.signal
from helpers import exactly

from symsbl import Chirp, DataError, FreeDecay, Multisine, Sampled, Sine


def via_casadi(signal, t):
    ts = ca.SX.sym("t")
    f = ca.Function("u", [ts], [signal.expr(ts)])
    return np.array(f.map(t.size)(t[None, :])).T.squeeze()


def test_sine_exact():
    t = np.linspace(0, 1, 1001)
    s = Sine(amplitude=100, frequency=10, phase=0.3)
    np.testing.assert_allclose(s(t), 100 * np.sin(2 * np.pi * 10 * t + 0.3), rtol=0, atol=1e-12)
    np.testing.assert_allclose(via_casadi(s, t), s(t), rtol=0, atol=1e-12)
    assert Sine()(np.array([0.025]))[0] == pytest.approx(100.0)  # defaults: the paper's 100 N at 10 Hz


def test_multisine_rms_band_and_flat_spectrum():
    fs, period = 1024, 2.0
    s = Multisine(rms=50.0, f_min=5.0, f_max=150.0, seed=7, period=period)
    t = np.arange(int(fs * period)) / fs
    u = s(t)
    assert np.sqrt(np.mean(u**2)) == pytest.approx(50.0, rel=1e-12)
    spec = np.abs(np.fft.rfft(u)) / (t.size / 2)
    f = np.fft.rfftfreq(t.size, 1 / fs)
    band = (f >= 5.0) & (f <= 150.0)
    assert band.sum() == s.frequencies.size == 291
    np.testing.assert_allclose(spec[band], s.amplitude, rtol=1e-9)  # flat in the band
    assert spec[~band].max() < 1e-9 * s.amplitude  # nothing outside it
    np.testing.assert_allclose(via_casadi(s, t[:200]), u[:200], rtol=0, atol=1e-9)


def test_multisine_seeded_phases():
    a, b, c = Multisine(1, 1, 10, seed=1), Multisine(1, 1, 10, seed=1), Multisine(1, 1, 10, seed=2)
    np.testing.assert_array_equal(a.phases, b.phases)
    assert not np.array_equal(a.phases, c.phases)
    t = np.linspace(0, 3, 301)
    np.testing.assert_allclose(a(t), a(t + 1.0), atol=1e-12)  # periodic with period 1 s


def test_multisine_errors():
    with pytest.raises(
        DataError,
        match=exactly(
            "Multisine: expected a harmonic of 1/period = 1 Hz in the band, "
            "received [0.2, 0.5] Hz, which holds none; widen the band or lengthen "
            "the period"
        ),
    ):
        Multisine(1.0, 0.2, 0.5)
    with pytest.raises(
        DataError,
        match=exactly("Multisine: expected period > 0 and 0 <= f_min <= f_max, received period=1.0, f_min=10, f_max=5"),
    ):
        Multisine(1.0, 10, 5)


@pytest.mark.parametrize("method, scipy_method", [("linear", "linear"), ("exponential", "logarithmic")])
def test_chirp_matches_scipy(method, scipy_method):
    t = np.linspace(0, 2, 20001)
    c = Chirp(amplitude=3.0, f0=2.0, f1=40.0, duration=2.0, method=method)
    ref = 3.0 * scipy.signal.chirp(t, f0=2.0, t1=2.0, f1=40.0, method=scipy_method, phi=-90)
    np.testing.assert_allclose(c(t), ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(via_casadi(c, t[::50]), c(t[::50]), rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", ["linear", "exponential"])
def test_chirp_instantaneous_frequency(method):
    """Zero crossings are half a period apart: 1 / (2 * gap) is the frequency at the gap's midpoint."""
    fs = 200_000
    t = np.arange(2 * fs + 1) / fs
    c = Chirp(amplitude=1.0, f0=5.0, f1=200.0, duration=2.0, method=method)
    u = c(t)
    i = np.flatnonzero(np.sign(u[:-1]) * np.sign(u[1:]) < 0)
    crossings = t[i] - u[i] * (t[i + 1] - t[i]) / (u[i + 1] - u[i])
    f_est = 1.0 / (2 * np.diff(crossings))
    np.testing.assert_allclose(f_est, c.frequency(0.5 * (crossings[1:] + crossings[:-1])), rtol=1e-3)
    assert c.frequency(0.0) == pytest.approx(5.0) and c.frequency(2.0) == pytest.approx(200.0)


def test_chirp_errors():
    with pytest.raises(
        DataError, match=exactly("Chirp.method: expected one of ['linear', 'exponential'], received 'log'")
    ):
        Chirp(method="log")
    with pytest.raises(
        DataError,
        match=exactly("Chirp: expected f0 > 0 and f1 > 0 for an exponential sweep, received f0=0.0, f1=100.0"),
    ):
        Chirp(f0=0.0, method="exponential")
    with pytest.raises(DataError, match=exactly("Chirp.duration: expected a duration > 0 s, received 0.0")):
        Chirp(duration=0.0)


def test_free_decay_is_zero():
    t = np.linspace(0, 1, 11)
    np.testing.assert_array_equal(FreeDecay()(t), np.zeros(11))
    assert FreeDecay(2)(t).shape == (11, 2)
    assert ca.DM(FreeDecay(2).expr(ca.SX.sym("t"))).shape == (2, 1)


def test_sampled_linear_interpolation():
    rng = np.random.default_rng(0)
    tg = np.arange(20) * 0.1
    v = rng.standard_normal((20, 2))
    s = Sampled(tg, v)
    tq = np.sort(rng.uniform(0, 1.9, 57))
    expected = np.column_stack([np.interp(tq, tg, v[:, 0]), np.interp(tq, tg, v[:, 1])])
    np.testing.assert_allclose(s(tq), expected, rtol=0, atol=1e-14)
    np.testing.assert_allclose(via_casadi(s, tq), expected, rtol=0, atol=1e-12)
    assert s.n_outputs == 2 and not s.is_analytic
    one = Sampled(tg, v[:, 0])
    assert one.n_outputs == 1 and one(tq).shape == (57,)


def test_sampled_errors():
    with pytest.raises(
        DataError,
        match=exactly("Sampled values: expected shape (3,) or (3, n_outputs) to match t, received shape (2,)"),
    ):
        Sampled([0, 1, 2], [1, 2])
    with pytest.raises(
        DataError, match=exactly("Sampled t: expected strictly increasing times, received t = 1.0 at row 2")
    ):
        Sampled([0, 1, 1], [1, 2, 3])
    with pytest.raises(
        DataError,
        match=exactly("Sampled: expected finite t and values, received NaN/inf samples; remove or repair them"),
    ):
        Sampled([0, 1, 2], [1, np.nan, 3])
    with pytest.raises(
        DataError, match=exactly("Sampled t: expected a 1-D array of at least 2 samples, received shape (1,)")
    ):
        Sampled([0], [1])


def test_a_held_input_keeps_each_sample_until_the_next_and_each_interval_its_own_value():
    import numpy as np

    import symsbl

    held = symsbl.Sampled([0.0, 1.0, 2.0], [1.0, 5.0, 3.0], kind="hold")
    assert np.array_equal(held(np.array([0.0, 0.5, 0.999, 1.0, 1.5, 2.0, 3.0])), [1, 1, 1, 5, 5, 3, 3])
    nodes = held.at_nodes(np.array([0.0, 1.0, 2.0]), 3)  # left end, middle, right end of each interval
    assert nodes.shape == (2, 3, 1) and np.array_equal(nodes[:, :, 0], [[1, 1, 1], [5, 5, 5]])
    linear = symsbl.Sampled([0.0, 1.0, 2.0], [1.0, 5.0, 3.0])
    assert np.array_equal(linear.at_nodes(np.array([0.0, 1.0, 2.0]), 3)[:, :, 0], [[1, 3, 5], [5, 4, 3]])
