"""Noise told from excitation (:mod:`symsbl._data.excitation`) against the noise added, and the loop test between
periods against records with and without a loop.

A multisine to 30-40 % of the sampling rate puts excitation above a quarter of it, where the earlier estimate
(the periodogram's median above fs/4) read it as noise once it fills most of that band; a periodic multisine to
the Nyquist rate leaves no quiet band, and only the difference of periods tells its noise.
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from electronic_duffing import Oscillator, extrapolating, multisine, saturating, training
from scipy.signal import lfilter

import symsbl
from symsbl._data.excitation import aperiodic_part, noise_std, period, period_noise_std, quiet_band_std, relative_noise
from symsbl._data.residuals import MODEL_ERROR, residual_test
from symsbl._refine.diagnostics import noisy_inputs
from symsbl._refine.path import _noise_floor


def _median_of_fourths(x: np.ndarray) -> float:
    """The earlier estimate: the Hann periodogram's median above a quarter of the sampling rate."""
    w = np.hanning(x.size)
    power = np.abs(np.fft.rfft((x - x.mean()) * w)) ** 2
    return float(np.sqrt(np.median(power[power.size // 2 : -1]) / (np.log(2.0) * float(w @ w))))


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("share", [0.3, 0.4])
def test_quiet_bands_give_the_noise_of_a_multisine_to_a_third_of_the_rate(seed, share):
    """0.5 % noise on a multisine to 0.3 or 0.4 fs (one period of 8192 samples): within 10 %, where the fs/4 split
    reads the excitation between 0.25 and 0.4 fs (most of its bins) as noise (over 3 times the truth)."""
    rng = np.random.default_rng(seed)
    x = multisine(8192, share, rng) + 0.005 * rng.standard_normal(8192)
    assert quiet_band_std(x) == pytest.approx(0.005, rel=0.1)
    if share > 0.375:  # the excitation fills more than half of the upper half
        assert _median_of_fourths(x) > 3 * 0.005


def test_white_noise_alone_is_its_own_quiet_band():
    rng = np.random.default_rng(7)
    assert quiet_band_std(rng.standard_normal(60000)) == pytest.approx(1.0, rel=0.03)


@pytest.mark.parametrize("seed", range(5))
def test_periods_give_the_noise_of_a_multisine_that_fills_the_band(seed):
    """A periodic multisine to the Nyquist rate (4 periods of 2048) with 1 % noise: no band is quiet (the quiet
    bands read the excitation, 2.2 % per unit bandwidth here), the difference of periods gives the noise within
    10 %, and :func:`noise_std` takes the smaller."""
    rng = np.random.default_rng(seed)
    x = np.tile(multisine(2048, 0.5, rng), 4) + 0.01 * rng.standard_normal(4 * 2048)
    L = period(x)
    assert L == 2048
    assert period_noise_std(x, L) == pytest.approx(0.01, rel=0.1)
    assert quiet_band_std(x) > 2 * 0.01
    assert noise_std(x, L) == pytest.approx(period_noise_std(x, L))


def test_period_is_refused_where_the_record_does_not_repeat():
    """Filtered noise, a sine of 100.37 samples (it nearly repeats after 100: its leftover is a sine, not noise)
    and a record of less than two periods have no period."""
    rng = np.random.default_rng(3)
    assert period(lfilter([1.0], [1.0, -0.9], rng.standard_normal(4000))) is None
    t = np.arange(5000)
    assert period(np.sin(2 * np.pi * t / 100.37) + 1e-3 * rng.standard_normal(t.size)) is None
    one = multisine(3000, 0.3, rng)
    assert period(np.concatenate([one, one[:2000]])) is None
    assert period(np.column_stack([np.tile(one, 2), np.tile(one[::-1], 2)])) == 3000


def test_the_aperiodic_part_keeps_the_noise_and_drops_the_excitation():
    """Its variance is the noise's (the scaling for the average's share), over P - 1 periods."""
    rng = np.random.default_rng(4)
    noise = 0.1 * rng.standard_normal(8 * 512)
    x = np.tile(multisine(512, 0.3, rng), 8) + noise
    part = aperiodic_part(x, 512)
    assert part.shape == (7 * 512,)
    assert part.std() == pytest.approx(0.1, rel=0.05)


def _loop_record(seed: int, gain: float, periods: int = 8, n: int = 500):
    """A periodic 40-line multisine reference, a residual that is a lightly damped model error under it (a cubic
    of the response, 4 times the noise) plus white noise, and a measured input ``r - gain * noise_{t-4}``
    (``gain`` 0: open loop) with 0.2 % measurement noise."""
    rng = np.random.default_rng(seed)
    spectrum = np.zeros(n // 2 + 1, complex)
    spectrum[1:41] = np.exp(2j * np.pi * rng.uniform(size=40))
    ref = np.tile(np.fft.irfft(spectrum, n), periods)
    ref /= ref.std()
    w, r = 2 * np.pi * 0.03, np.exp(-0.04 * 2 * np.pi * 0.03)
    y = lfilter([1.0], [1.0, -2 * r * np.cos(w), r * r], ref)
    y /= y.std()
    noise = 0.05 * rng.standard_normal(ref.size)
    e = 0.2 * y + 0.1 * y**3 + noise
    u = ref - gain * np.concatenate([np.zeros(4), noise[:-4]]) + 0.002 * rng.standard_normal(ref.size)
    return e, u


@pytest.mark.slow
def test_the_loop_test_between_periods_holds_its_level_and_finds_a_loop():
    """Over 10 seeds of the record above: no alarm without the loop, every loop of gain 0.5 found, both from the
    parts of the residual and the input that do not repeat."""
    alarms = {0.0: 0, 0.5: 0}
    for gain in alarms:
        for seed in range(10):
            e, u = _loop_record(seed, gain)
            L = period(u)
            assert L == 500
            test = residual_test("y", e, {"u": u}, loop=(aperiodic_part(e, L), {"u": aperiodic_part(u, L)}))
            alarms[gain] += not test.open_loop
    assert alarms == {0.0: 0, 0.5: 10}


def _saturating_record(input_noise: float, seed: int = 0) -> symsbl.Trajectory:
    """An electronic-Duffing stand-in (``tests/electronic_duffing.py``): a hardening that saturates, outside a
    polynomial library, at 610 Hz, a periodic multisine to 0.35 fs (3 periods of 2048, the first dropped as
    transient), 0.5 % noise on x and v and ``input_noise`` on F (each relative to its spread)."""
    return training(Oscillator(saturating), seed, length=2048, periods=3, band=0.35, input_noise=input_noise)


@pytest.mark.parametrize(("input_noise", "flagged"), [(0.0005, False), (0.001, False), (0.005, True)])
def test_noise_on_a_measured_input_is_flagged_by_its_level_not_by_the_excitation_band(input_noise, flagged):
    """The stand-in above: 0.05 % and 0.1 % noise on the force (a fifth of the outputs' relative noise and below)
    raise no errors-in-variables doubt, 0.5 % (as much as the outputs') does, and the levels read are the noise
    added within 15 % (the earlier fs/4 split read 0.86 % on x, 1.5 % on v and 1.6 times the force's)."""
    record = _saturating_record(input_noise)
    reasons = noisy_inputs([record], ("x", "v"), ("F",))
    assert bool(reasons) is flagged, reasons
    L = period(record.inputs)
    assert L == 2048
    force = record.column("F")
    assert noise_std(force, L) / force.std() == pytest.approx(input_noise, rel=0.15)
    for name in ("x", "v"):
        y = record.column(name)
        assert noise_std(y, L) / y.std() == pytest.approx(0.005, rel=0.15)


def test_an_output_whose_noise_the_record_does_not_resolve_is_no_yardstick():
    """The stand-in with 0.5 % on the force is flagged against the outputs' noise; with the outputs low-passed to
    the excitation's band (their noise gone, as a filtered encoder's) there is nothing to compare it with, and
    no doubt is raised, where their unresolved level (1e-9 here, rounding) made any input noisy."""
    record = _saturating_record(0.005)
    L = period(record.inputs)
    clean = [np.tile(record.column(n)[:L], record.n_samples // L) for n in ("x", "v")]  # one period, repeated
    spectra = [np.fft.rfft(c) for c in clean]
    band = np.fft.rfftfreq(clean[0].size) <= 0.35 * 1.02
    filtered = np.column_stack([np.fft.irfft(np.where(band, f, 0.0), clean[0].size) for f in spectra])
    filtered += 1e-9 * filtered.std(axis=0) * np.random.default_rng(1).standard_normal(filtered.shape)  # rounding
    smooth = symsbl.Trajectory(record.t, filtered, record.inputs, ("x", "v"), ("F",))
    assert noisy_inputs([record], ("x", "v"), ("F",))
    levels = [noise_std(smooth.column(n), L) / smooth.column(n).std() for n in ("x", "v")]
    assert 0 < min(levels) and max(levels) < 1e-6
    assert noisy_inputs([smooth], ("x", "v"), ("F",)) == ()


def test_the_noise_floor_takes_an_unresolved_channel_at_the_others_level():
    """The model path's noise floor (a perfect model's cross-validated error, averaged over the channels) with x
    low-passed as above and v at its 0.5 % noise: v's level, where x's unresolved 1e-9 halved it before."""
    record = _saturating_record(0.0)
    L = period(record.inputs)
    x = np.tile(record.column("x")[:L], record.n_samples // L)
    x = np.fft.irfft(np.where(np.fft.rfftfreq(x.size) <= 0.35 * 1.02, np.fft.rfft(x), 0.0), x.size)
    x += 1e-9 * x.std() * np.random.default_rng(1).standard_normal(x.size)  # rounding
    Y = np.column_stack([x, record.column("v")])
    n = Y.shape[0]
    passes = SimpleNamespace(
        records=SimpleNamespace(n_total=n, Y=Y, starts=[0], lengths=[n]), valid=np.ones(Y.shape, bool), UN=record.inputs
    )
    assert np.isnan(relative_noise([x], [L]))
    floor = _noise_floor(passes)
    assert floor == relative_noise([record.column("v")], [L]) and floor == pytest.approx(0.005, rel=0.15)


def test_the_period_of_an_oversampled_multisine_is_its_own_not_a_neighbour():
    """Lines 2-30 Hz at 1 kHz: the autocorrelation at 999 samples is within 1 % of its peak at 1000."""
    t = np.arange(5000) / 1000.0
    rng = np.random.default_rng(5)
    u = sum(np.cos(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)) for f in range(2, 31))
    assert period(u) == 1000


@pytest.mark.slow
def test_a_law_outside_the_library_is_not_taken_for_a_disturbance_on_a_periodic_record():
    """The stand-in with a cubic-polynomial library (it holds neither the saturation nor x|x|), 0.05 % force
    noise: the innovations are not white (the model's error), but the noise between periods is (Ljung-Box of
    the measured outputs' non-repeating part), so no doubt is raised, no loop is read, the output error's model
    is reported, and the library is said not to hold the law (cross-validated error over 3 times the noise
    floor). Before, the whiteness doubt refitted on short segments and reported the equation error's model."""
    x, v, F = symsbl.symbols("x v F")
    record = _saturating_record(0.0005)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model = symsbl.identify(record, symsbl.polynomial([x, v], 3) + symsbl.inputs([F]), kinematics={"x": "v"})
    info = model.metadata["refine"]
    assert info["doubts"] == [] and model.metadata["estimator"]["used"] == "output-error"
    for t in info["residual"]:
        assert not t["white"] and t["noise_p"] >= 0.01 and t["open_loop"], t
    assert info["beyond_library"] and info["noise_floor"] == pytest.approx(0.005, rel=0.15)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_a_law_outside_the_library_is_not_taken_for_a_disturbance_under_a_random_force(seed):
    """The stand-in under a band-limited random force to 0.3 fs (not periodic: no noise between periods to tell),
    0.5 % noise on x and v, a cubic-polynomial library: the innovations are not white, but the model's own
    simulated trajectory predicts over :data:`MODEL_ERROR` of them out of sample (a random force the record lacks
    is independent of it: at most 0.009 over 10 process-noise records), so no doubt is raised and the output
    error's model is reported. Before, 10 seeds out of 10 were doubted, refitted on short segments and reported
    with the equation error's model."""
    x, v, F = symsbl.symbols("x v F")
    record = extrapolating(Oscillator(saturating), seed, n=8192, growth=(1.0, 1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", symsbl.RefineWarning)  # the residual depends on F: the law is missing
        model = symsbl.identify(record, symsbl.polynomial([x, v], 3) + symsbl.inputs([F]), kinematics={"x": "v"})
    info = model.metadata["refine"]
    assert info["doubts"] == [] and model.metadata["estimator"]["used"] == "output-error"
    assert info["short_segments"] is None and not info["closed_loop"]
    for t in info["residual"]:
        assert not t["white"] and t["trajectory"] > MODEL_ERROR, t


def test_noise_levels_tells_the_noise_from_a_multisine_to_a_third_of_the_rate():
    """The public estimate on a record whose state is a multisine to 0.35 fs with 0.5 % noise (one period of 8192
    samples) and whose input is the noiseless multisine: the state's within 10 % of the noise added, the input's
    below a thousandth of it; third differences read the state's excitation as noise (over 5 times the truth)."""
    from symsbl._data.trajectory import third_difference_std

    rng = np.random.default_rng(5)
    u = multisine(8192, 0.35, rng)
    x = u + 0.005 * rng.standard_normal(8192)
    record = symsbl.Trajectory(np.arange(8192) / 610.0, x[:, None], u[:, None], ("x",), ("F",))
    levels = symsbl.noise_levels(record)
    assert levels["x"] == pytest.approx(0.005, rel=0.1)
    assert levels["F"] < 5e-6
    assert third_difference_std(x) > 5 * 0.005


@pytest.mark.slow
def test_a_stage_that_runs_away_leaves_the_noise_precisions_as_they_were():
    """6144 samples of the stand-in under a random force, cubic library: the equation error's model (with a
    spurious ``+5 v^2 x``) runs away on the whole record once the continuation jumps to it. Its noise
    precisions, re-estimated from that non-finite residual, were NaN and went back with the fit to the last
    length that did not run away, which then could not be fitted either: a RefineWarning "expected a
    simulation that stays finite" and the equation error's model. Now the precisions stay as they were and
    the output error's model is reported with the cubic's support."""
    x, v, F = symsbl.symbols("x v F")
    record = extrapolating(Oscillator(saturating), 0, n=6144, growth=(1.0, 1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error", symsbl.RefineWarning)
        model = symsbl.identify(record, symsbl.polynomial([x, v], 3) + symsbl.inputs([F]), kinematics={"x": "v"})
    assert model.fit is symsbl.FitMethod.OUTPUT_ERROR and model.metadata["estimator"]["used"] == "output-error"
    assert sorted(model.equation("v").names) == sorted(["x", "v", "x**3", "F"])
