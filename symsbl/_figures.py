"""Shared pieces of symsbl's figures: the matplotlib handle, the colours, labels and time windows."""

from __future__ import annotations

import numpy as np

from ._base.errors import MissingExtraError, expected
from ._base.format import pretty
from ._data.trajectory import Trajectory

__all__ = [
    "new_figure",
    "term_label",
    "forcing_window",
    "MEASURED",
    "MODEL",
    "BAND",
    "PRIOR",
    "POSTERIOR",
    "BEFORE",
    "AFTER",
    "MATPLOTLIB_MISSING",
    "require_matplotlib",
]

#: Colours of the measured data, the model and its band (colour-blind safe pair).
MEASURED = "0.2"
MODEL = "#d55e00"
BAND = "#e69f00"
PRIOR = "#0072b2"
POSTERIOR = "#009e73"


def new_figure(**kwargs):
    """A new :class:`matplotlib.figure.Figure`, or an ImportError that says how to install it."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise MissingExtraError(MATPLOTLIB_MISSING) from exc
    return Figure(**kwargs)


def term_label(name: str) -> str:
    """Readable label of a term name: ``"x1**2*Abs(x2)"`` -> ``"x1^2 |x2|"``."""
    return pretty(name)


#: The colours of the model before and after a discrepancy step.
BEFORE = "#0072b2"
AFTER = MODEL

#: The one-line error when matplotlib is missing, with an install hint that works from a clone and from an index.
MATPLOTLIB_MISSING = expected(
    "figures",
    "matplotlib to be installed",
    "ImportError",
    "pip install matplotlib (or pip install '.[plot]' from a clone of symsbl, pip install 'symsbl[plot]' "
    "from an index)",
    raw=True,
)


def require_matplotlib() -> None:
    """Raise :class:`~symsbl.MissingExtraError` now, before any work, if matplotlib is missing."""
    new_figure()


def forcing_window(data: Trajectory, cycles: float = 1.0, *, threshold: float = 0.1) -> tuple[float, float]:
    """The last ``cycles`` periods of the slowest significant component of the forcing.

    The spectrum of the first input (of the first state if there is none) is computed; the
    lowest frequency whose amplitude exceeds ``threshold`` times the peak sets the period. For
    the paper's 10 Hz sine this is one 0.1 s cycle; for a 2-30 Hz multisine, 0.5 s.

    Parameters
    ----------
    data : Trajectory
    cycles : float
        Number of periods to show.
    threshold : float
        Fraction of the spectral peak above which a frequency counts as significant.

    Returns
    -------
    (t_start, t_stop) : tuple of float
        Seconds, within ``data.t``.
    """
    signal = data.inputs[:, 0] if data.inputs.shape[1] else data.states[:, 0]
    spectrum = np.abs(np.fft.rfft(signal - signal.mean()))
    freqs = np.fft.rfftfreq(signal.size, data.dt)
    t0, t1 = float(data.t[0]), float(data.t[-1])
    if spectrum.size < 2 or spectrum[1:].max() <= 0:
        return t0, t1
    significant = np.flatnonzero(spectrum[1:] >= threshold * spectrum[1:].max()) + 1
    span = cycles / freqs[significant[0]]
    return max(t0, t1 - span), t1
