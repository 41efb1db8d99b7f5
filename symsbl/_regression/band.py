"""The band of the regression rows when a record measures a derivative (an accelerometer on a velocity).

A position and a velocity integrated from an acceleration are wrong below the band the acceleration carries:
the sensor's noise integrates to errors whose power grows as ``omega^-4`` towards low frequencies, and the
slow, quasi-static part of the motion barely shows in an acceleration. In the rows ``a = D(x, v, u) xi`` of the
equation error, those errors enter every column of a position or a velocity, and a spring's force error of a
few per cent hides a dashpot of 0.5 % of critical damping. A linear filter applied to every column of ``D`` and
``Y`` alike keeps the identity ``H a = H D xi`` for any ``xi``, so the rows are high-passed at the lower edge of
the measured accelerations' own band, where they hold their signal; the output error then fits the whole band
(measured: a chain of three masses recorded by accelerometers at 0.5 % noise, 1-30 Hz: the equation error
kept no dashpot and put spurious springs between masses, and the output error then failed; rows high-passed at
2.75 Hz: the dashpots and the coupling's cubic reaction found, the model exact).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np

from .._derivatives.kinematics import band_edges

__all__ = ["lower_edge", "high_passed", "ORDER", "MAX_SHARE"]

#: Order of the (causal) Butterworth high-pass on the rows.
ORDER = 4
#: A cut-off at or above this share of the rows' rate is not applied: the band reaches the rows' Nyquist.
MAX_SHARE = 0.4


def lower_edge(t: np.ndarray, columns: Iterable[np.ndarray]) -> float:
    """The lowest of the columns' lower band edges (Hz; see :func:`~symsbl._derivatives.kinematics.band_edges`),
    or 0.0 for none."""
    return min((band_edges(t, c)[0] for c in columns), default=0.0)


def high_passed(pairs: Iterator, cutoff: float, rate: float) -> Iterator:
    """``(D, Y)`` slabs of consecutive rows (at ``rate`` rows a second) high-passed at ``cutoff`` Hz, column by
    column with one filter state carried from slab to slab; the slabs as they are when ``cutoff`` is 0 or at
    least :data:`MAX_SHARE` of ``rate``. The filter starts in the steady state of the first row, and a column
    constant so far is zero: a constant term is removed whole (a constant force and a shifted start give the
    same accelerations), not left as rounding noise that a regression would scale up."""
    if not 0.0 < cutoff < MAX_SHARE * rate:
        yield from pairs
        return
    from scipy.signal import butter, sosfilt, sosfilt_zi  # scipy.signal costs ~1 s to import: only when used

    sos = butter(ORDER, cutoff, btype="highpass", fs=rate, output="sos")
    steady = sosfilt_zi(sos)[:, :, None]
    states: list = []
    first: list = []
    flat: list = []
    for pair in pairs:
        if not states:
            first = [a[0].copy() for a in pair]
            states = [steady * a[:1] for a in pair]
            flat = [np.ones(a.shape[1], dtype=bool) for a in pair]
        out = []
        for k, a in enumerate(pair):
            flat[k] &= np.all(a == first[k], axis=0)
            filtered, states[k] = sosfilt(sos, a, axis=0, zi=states[k])
            filtered[:, flat[k]] = 0.0
            out.append(filtered)
        yield out[0], out[1]
