"""Kinematics: positions whose derivative is a velocity state, and the members of a pair that were not measured.

``kinematics={"x1": "x2"}`` declares that ``x1' = x2`` holds exactly (a position and its velocity):
that equation is fixed, not identified, and any member of the pair may be absent from the data. A third
name, ``"x1:x2:a1"``, names the column of an accelerometer that records ``x2'`` (:func:`kinematic_triples`).
For the equation-error stage the members that were not measured are reconstructed from those that were
(:func:`complete_states`): an unmeasured velocity by a smoothing derivative of its position
(:func:`estimate_velocity`), a position or velocity from a measured velocity or acceleration by integration
with its drift removed (:func:`integrate`). Both are biased and noisy where the record is; the output-error
refinement (:func:`symsbl.refine`) then fits only the measured columns, with the initial states as unknowns,
and removes that bias.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from .._base.errors import DataError, expected
from .._data.excitation import noise_std
from .._data.trajectory import Trajectory
from .weakform import WeakForm

__all__ = [
    "parse_kinematics",
    "kinematic_triples",
    "estimate_velocity",
    "velocity_noise",
    "latent_states",
    "complete_states",
    "sensor_states",
    "integrate",
    "band_edges",
    "completed_columns",
]


def _entries(spec) -> list:
    """The ``(position, velocity[, acceleration])`` entries a mapping or text declares, not yet checked against
    any states."""
    if spec is None or spec == "" or spec == {}:
        return []
    if isinstance(spec, str):
        out = []
        for part in filter(None, (p.strip() for p in spec.split(","))):
            names = [n.strip() for n in part.split(":")]
            if len(names) not in (2, 3) or not all(names):
                raise DataError(
                    expected(
                        "--kinematics",
                        "position:velocity pairs such as x1:x2,x3:x4, each with an "
                        "acceleration column as a third name if one is measured (x1:x2:a1)",
                        part,
                    )
                )
            out.append(tuple(names))
        return out
    if isinstance(spec, Mapping):
        out = []
        for x, v in spec.items():
            if isinstance(v, (tuple, list)) and len(v) == 2:
                out.append((x, v[0], v[1]))
            else:
                out.append((x, v))
        return out
    raise DataError(
        expected(
            "kinematics",
            "a mapping {position: velocity} (or {position: (velocity, acceleration)}) or text 'x1:x2' / 'x1:x2:a1'",
            type(spec).__name__,
            raw=True,
        )
    )


def _pairs(spec) -> list:
    """The ``(position, velocity)`` pairs a mapping or text declares, not yet checked against any states."""
    return [tuple(e[:2]) for e in _entries(spec)]


def parse_kinematics(spec, states: Sequence[str]) -> tuple[tuple[str, str], ...]:
    """``(position, velocity)`` pairs from a mapping ``{"x1": "x2"}`` or the text ``"x1:x2,x3:x4"``.

    Examples
    --------
    >>> parse_kinematics("y:v", ["y", "v", "z"])
    (('y', 'v'),)
    """
    pairs = _pairs(spec)
    used: set = set()
    for x, v in pairs:
        if x not in states or v not in states or x == v:
            raise DataError(
                expected("kinematics", f"position: velocity pairs of the states {list(states)}", f"{x}:{v}", raw=True)
            )
        if x in used or v in used:
            raise DataError(expected("kinematics", "each state in at most one pair", f"{x}:{v}", raw=True))
        used |= {x, v}
    return tuple(pairs)


def kinematic_triples(spec, states: Sequence[str]) -> tuple[tuple[str, str, str | None], ...]:
    """``(position, velocity, acceleration column or None)`` of every declared pair: the text
    ``"x1:x2:a1,x3:x4"`` or a mapping ``{"x1": ("x2", "a1"), "x3": "x4"}``. The acceleration column names a
    channel of the records that measures the velocity's derivative (an accelerometer), unlike any state.

    Examples
    --------
    >>> kinematic_triples("x:v:a", ["x", "v"])
    (('x', 'v', 'a'),)
    """
    pairs = parse_kinematics(spec, states)
    entries = _entries(spec)
    seen: set = set()
    out = []
    for (x, v), entry in zip(pairs, entries):
        a = entry[2] if len(entry) == 3 else None
        if a is not None and (a in states or a in seen or a == "t"):
            raise DataError(
                expected(
                    "kinematics",
                    "an acceleration column named unlike the states and the other accelerations",
                    f"{x}:{v}:{a}",
                    raw=True,
                )
            )
        if a is not None:
            seen.add(a)
        out.append((x, v, a))
    return tuple(out)


def sensor_states(columns: Sequence[str], spec) -> tuple[tuple[str, ...], dict[str, str]]:
    """The states of a model whose records hold the ``columns`` and the accelerations they measure ``{velocity:
    column}``: each declared pair in full, in the place of its first member among the columns (position,
    velocity or acceleration), the other columns as they are.

    Examples
    --------
    >>> sensor_states(["a", "z"], "x:v:a")
    (('x', 'v', 'z'), {'v': 'a'})
    >>> sensor_states(["y1", "y2"], "y1:v1")
    (('y1', 'v1', 'y2'), {})
    """
    entries = _entries(spec)
    member = {n: e for e in entries for n in e}
    out: list[str] = []
    for name in columns:
        for n in member[name][:2] if name in member else (name,):
            if n not in out:
                out.append(n)
    measured = set(columns)
    return tuple(out), {e[1]: e[2] for e in entries if len(e) == 3 and e[2] in measured}


def estimate_velocity(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The derivative of a sampled position by a smoothing (Savitzky-Golay, quintic) derivative filter.

    The half-window is at least a quarter of the period of the highest frequency that carries the velocity's
    signal (the bandwidth the weak form reads off the spectrum of the position's differences, above their
    white-noise floor), where the quintic filter's gain is within 0.02 % of the exact derivative's, and wider
    where that makes the estimate's mean squared error (the band it cuts plus the noise it passes) smaller.

    Parameters
    ----------
    t : ndarray, shape (n_samples,)
    x : ndarray, shape (n_samples,)

    Returns
    -------
    ndarray, shape (n_samples,)

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(4000) / 1000.0
    >>> x = np.sin(2 * np.pi * 3 * t) + 1e-4 * np.random.default_rng(0).standard_normal(t.size)
    >>> v = estimate_velocity(t, x)
    >>> bool(np.max(np.abs(v[50:-50] - 6 * np.pi * np.cos(6 * np.pi * t[50:-50]))) < 0.05 * 6 * np.pi)
    True
    """
    h, half = _half_window(t, x)
    if half < 3:
        return np.gradient(np.asarray(x, dtype=float), h)
    from scipy.signal import savgol_filter  # scipy.signal costs ~1 s to import: only when used

    return savgol_filter(np.asarray(x, dtype=float), 2 * half + 1, 5, deriv=1, delta=h, mode="interp")


#: Half-windows :func:`estimate_velocity` weighs, from the velocity's band to :data:`MAX_HALF` in geometric steps.
HALF_WINDOWS = 24
#: scipy's quintic derivative coefficients lose the derivative to rounding from a half-window of 997 samples.
MAX_HALF = 800
#: Samples of the position the weighing reads at most.
ESTIMATE_SAMPLES = 2**17


def _half_window(t: np.ndarray, x: np.ndarray) -> tuple[float, int]:
    """The sample interval and the half-window of :func:`estimate_velocity` for the position ``x``: from the
    velocity's band (a quarter period of the frequency below which 99.9 % of the power of the position's
    differences lies) up, of :data:`HALF_WINDOWS` candidates, the one whose quintic derivative filter makes the
    least mean squared error: its bias (what it reads unlike the band's filter, less what their noises put in
    the difference: a wide window reads a fast motion's velocity low) plus the noise through its coefficients
    (a narrow one passes it), over the first :data:`ESTIMATE_SAMPLES`. The position's own quantile cut a
    servo axis's velocity band to 0.5 Hz (16 % off the benchmark's recipe; 0.12 % now); the band alone passed
    a chaotic oscillator's estimate three times the noise of the least error (5.4 % off, 1.4 % now)."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    h, n = float(t[1] - t[0]), x.size
    top = min(MAX_HALF, (n - 1) // 2)
    if top < 3 or n < 9:  # the differences' band needs 8 samples
        return h, min(top, 2)
    from scipy.signal import oaconvolve, savgol_coeffs  # scipy.signal costs ~1 s to import: only when used

    # at least the velocity's band, read off the position's differences (their power falls no faster than the
    # velocity's), the reference of least bias
    window = WeakForm().resolve(t[1:], np.diff(x)[:, None] / h).window
    if window is not None and window <= 4:  # no band above the differences' noise: the position's, then
        window = max(window, WeakForm().resolve(t, x[:, None]).window or 4)
    assert window is not None  # resolve() sets it
    first = min(max(3, int(round(0.5 * window))), top)
    piece = x[:ESTIMATE_SAMPLES]
    sigma = noise_std(piece)

    def filtered(half: int) -> tuple[np.ndarray, np.ndarray]:
        c = savgol_coeffs(2 * half + 1, 5, deriv=1, delta=h, use="dot")
        return c, oaconvolve(piece, c[::-1], mode="valid")

    c0, v0 = filtered(first)
    best, chosen = sigma**2 * float(c0 @ c0), first
    for half in np.unique(np.geomspace(first, top, HALF_WINDOWS).round().astype(int))[1:]:
        if 32 * half > piece.size:  # its ends, fitted by one polynomial each, would weigh more than 6 %
            break
        c, v = filtered(int(half))
        cut = half - first  # the reference's samples where this filter has its own
        d = v - v0[cut : cut + v.size]
        pad = np.pad(c0, cut)
        bias = max(float(np.mean(d**2)) - sigma**2 * float((c - pad) @ (c - pad)), 0.0)  # less the noise difference
        error = bias + sigma**2 * float(c @ c)
        if error < best:
            best, chosen = error, int(half)
    return h, chosen


def velocity_noise(t: np.ndarray, x: np.ndarray, v: np.ndarray) -> float:
    """The white-noise standard deviation of the velocity ``v`` that :func:`estimate_velocity` made of the
    position ``x``, over ``v``'s spread: the position's noise (:func:`symsbl._data.excitation.noise_std`) times
    the derivative filter's gain for white noise (the norm of its coefficients).

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(8000) / 1000.0
    >>> x = np.sin(2 * np.pi * 3 * t) + 1e-3 * np.random.default_rng(0).standard_normal(t.size)
    >>> v = estimate_velocity(t, x)
    >>> round(velocity_noise(t, x, v), 5)  # the noise of v less the clean position's derivative: 0.00047
    0.00045
    """
    h, half = _half_window(t, x)
    if half < 3:
        gain = math.sqrt(0.5) / h  # central differences
    else:
        from scipy.signal import savgol_coeffs

        gain = float(np.linalg.norm(savgol_coeffs(2 * half + 1, 5, deriv=1, delta=h)))
    spread = float(np.std(v))
    return noise_std(np.asarray(x, dtype=float)) * gain / spread if spread > 0 else math.inf


def latent_states(names: Sequence[str], measured: Sequence[str], pairs, accelerations=()) -> tuple[str, ...]:
    """The states of ``names`` that are not ``measured`` and belong to no position-velocity pair with a measured
    member (its position, its velocity, or the acceleration column of ``accelerations``, ``{velocity:
    column}``): latent, with a law of their own that no record holds (see :mod:`symsbl._latent`)."""
    observed = set(measured)
    acc = dict(accelerations)
    for x, v in pairs:
        if x in measured or v in measured or acc.get(v) in measured:
            observed |= {x, v}
    return tuple(n for n in names if n not in observed)


#: Order of the zero-phase high-pass filter that removes an integral's drift, and the ratio of the lowest
#: frequency the motion carries to its cut-off (the filter, run forwards and backwards, then passes that frequency
#: with a gain of ``1 / (1 + RATIO^-2 ORDER) = 1 - 1.5e-4``).
ORDER, RATIO = 4, 3.0
#: Share of a signal's power (weighted as its integral's) that may lie below the lowest frequency of its band.
LOW_SHARE = 1e-3
#: Periodogram bins at the bottom of a record's spectrum that never count as its band (three periods at least).
LOW_BINS = 3


def band_edges(t: np.ndarray, y: np.ndarray, integrations: int = 0) -> tuple[float, float]:
    """The lowest and highest frequency (Hz) of the band a sampled signal carries above its white-noise floor.

    The periodogram (Hann window, trend removed) is compared with its median over the upper half of the band
    (the noise floor, at least 1e-8 of the peak); bins 20 times above it carry signal. The lowest frequency is
    where the signal's power, weighted by ``omega^(-2 integrations)`` (the power of its ``integrations``-fold
    integral), passes :data:`LOW_SHARE` of its total from below; the highest is the highest signal bin.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(20000) / 1000.0
    >>> y = np.sin(2 * np.pi * 5 * t) + 0.3 * np.sin(2 * np.pi * 40 * t)
    >>> [round(f) for f in band_edges(t, y)]
    [5, 40]
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    n = y.size
    idx = np.arange(n)
    y = y - np.polyval(np.polyfit(idx, y, 1), idx)
    power = np.abs(np.fft.rfft(y * np.hanning(n))) ** 2
    f = np.fft.rfftfreq(n, float(t[1] - t[0]))
    # the noise floor, or (a noise-free signal) the window's leakage eight decades below the peak
    floor = max(float(np.median(power[power.size // 2 :])) if power.size > 8 else 0.0, 1e-8 * float(power.max()))
    # the first bins hold the window's leakage of a trend or a start from rest, not a band a record resolves
    signal = np.flatnonzero((power > 20.0 * floor) & (np.arange(f.size) >= LOW_BINS))
    if not signal.size:
        return float(f[1]) if f.size > 1 else 0.0, float(f[-1])
    weight = power[signal] / (2 * np.pi * f[signal]) ** (2 * integrations)
    share = np.cumsum(weight) / weight.sum()
    low = float(f[signal[int(np.searchsorted(share, LOW_SHARE))]])
    return low, float(f[signal[-1]])


def integrate(t: np.ndarray, y: np.ndarray, cutoff: float, times: int = 1) -> list[np.ndarray]:
    """The first ``times`` integrals of a sampled signal with their drift removed.

    The integrals are chained unfiltered (trapezoids, each with its polynomial trend removed: a sensor's bias
    integrates to a ramp, a parabola), and each is then high-passed once by a zero-phase Butterworth filter of
    order :data:`ORDER` at ``cutoff`` Hz, which removes the random walk its noise integrates to below the band
    of the motion (with whatever the true motion holds there: its mean, a static offset, which an output-error
    fit restores through the initial state). Filtering before integrating again would integrate the filter's
    edge transients into slow errors.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(10000) / 1000.0
    >>> w = 2 * np.pi * 5
    >>> a = -w ** 2 * np.sin(w * t) + 0.2      # a biased accelerometer
    >>> v, x = integrate(t, a, 5 / 3.0, times=2)
    >>> bool(np.max(np.abs(v - w * np.cos(w * t))[2000:-2000]) < 1e-3 * w)
    True
    >>> bool(np.max(np.abs(x - np.sin(w * t))[2000:-2000]) < 1e-2)
    True
    """
    from scipy.integrate import cumulative_trapezoid
    from scipy.signal import butter, sosfiltfilt  # scipy.signal costs ~1 s to import: only when used

    t = np.asarray(t, dtype=float)
    fs = 1.0 / float(t[1] - t[0])
    if not 0.0 < cutoff < 0.5 * fs:
        raise DataError(expected("cutoff", f"a frequency in (0, {0.5 * fs:g}) Hz", cutoff))
    sos = butter(ORDER, cutoff, btype="highpass", fs=fs, output="sos")
    pad = int(min(t.size - 1, math.ceil(3.0 * fs / cutoff)))
    tau = (t - t[0]) / max(float(t[-1] - t[0]), 1e-300)
    out, z = [], np.asarray(y, dtype=float)
    for k in range(1, times + 1):
        z = cumulative_trapezoid(z, t, initial=0.0)
        z = z - np.polyval(np.polyfit(tau, z, k), tau)  # the bias's trend and the unknown initial values
        # an even extension at the ends: an odd one reflects about the end value and makes a step there
        out.append(sosfiltfilt(sos, z - np.mean(z), padtype="even", padlen=pad))
    return out


def completed_columns(record: Trajectory, states: Sequence[str], triples) -> dict[str, np.ndarray]:
    """Every state of ``states`` that ``record`` holds or that its kinematic pairs (``(x, v, a)`` of
    :func:`kinematic_triples`) let be reconstructed: a velocity from its position (smoothing derivative) or from
    its acceleration (integration), a position from its velocity (integration). Latent states are left out."""
    have = set(record.state_names)
    out = {n: record.column(n) for n in states if n in have}
    for x, v, a in triples:
        if a is not None and a in have and (x not in out or v not in out):
            acc = record.column(a)
            first, second = integrate(record.t, acc, band_edges(record.t, acc, integrations=2)[0] / RATIO, times=2)
            out.setdefault(v, first)
            out.setdefault(x, second)
        if v not in out and x in out:
            out[v] = estimate_velocity(record.t, out[x])
        if x not in out and v in out:
            vel = out[v]
            out[x] = integrate(record.t, vel, band_edges(record.t, vel, integrations=1)[0] / RATIO)[0]
    return out


def complete_states(
    trajectories: Sequence[Trajectory], states: Sequence[str], pairs, accelerations=(), keep: Sequence[str] = ()
) -> tuple[list[Trajectory], tuple[str, ...]]:
    """The records with every state of ``states`` (then the columns ``keep``), the members of each kinematic pair
    that a record lacks reconstructed from those it holds (:func:`completed_columns`).

    Parameters
    ----------
    trajectories : sequence of Trajectory
    states : sequence of str
    pairs : sequence of (str, str)
        Position-velocity pairs.
    accelerations : mapping of str to str
        ``{velocity: column}``: the acceleration columns of the pairs that have one.
    keep : sequence of str
        Further columns of the records carried after the states (accelerations, algebraic outputs).

    Returns the completed records and the names of the states that were not measured.
    """
    measured = trajectories[0].state_names
    unmeasured = tuple(s for s in states if s not in measured)
    acc = dict(accelerations)
    triples = [(x, v, acc.get(v)) for x, v in pairs]
    in_pair = {n for x, v in pairs for n in (x, v)}
    for s in unmeasured:
        if s not in in_pair:
            raise DataError(
                expected(
                    f"state {s!r}",
                    "a column of the data, or a member of a declared kinematic pair (x:v)",
                    "neither",
                    f"add --kinematics {next(iter(measured), 'x')}:{s} if {s} is a velocity",
                    raw=True,
                )
            )
        x, v = next((x, v) for x, v in pairs if s in (x, v))
        if not ({x, v, acc.get(v)} & set(measured)):
            raise DataError(
                expected(
                    f"state {s!r}",
                    f"its pair's position {x!r}, velocity {v!r} or acceleration measured",
                    "no such column",
                    raw=True,
                )
            )
    if not unmeasured and not keep:
        return [tr.with_states(states) for tr in trajectories], ()
    out = []
    for tr in trajectories:
        columns = completed_columns(tr, states, triples)
        names = tuple(states) + tuple(keep)
        X = np.column_stack([columns[s] for s in states] + [tr.column(k) for k in keep])
        out.append(Trajectory(tr.t, X, tr.inputs, names, tr.input_names))
    return out, unmeasured
