"""Forcing signals: sine, random-phase multisine, chirp, free decay and sampled (measured) inputs.

Every signal has two faces:

* ``signal(t)`` evaluates it on a numpy time array (used to record the input on the output grid);
* ``signal.expr(t)`` builds it as a CasADi SX expression of the time symbol ``t``, so an integrator sees
  the exact input between samples instead of a zero-order hold.

Analytic signals (``is_analytic = True``) are exact functions of ``t``. :class:`Sampled` is a linear
interpolant of measured values; fixed-step integrators receive its values at the step nodes instead.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from .._base.errors import DataError, SimulationError, expected

__all__ = ["Signal", "Sine", "Multisine", "Chirp", "FreeDecay", "Sampled"]


class Signal(abc.ABC):
    """Base class of forcing signals with ``n_outputs`` channels.

    A signal is evaluated on numpy times (``signal(t)``) and built as a CasADi expression of the time
    symbol (``signal.expr(t)``), so integrators see it exactly between samples.

    Examples
    --------
    A user's signal, a ramp of 2 N/s:

    >>> import casadi as ca
    >>> import numpy as np
    >>> import symsbl
    >>> class Ramp(symsbl.Signal):
    ...     def __call__(self, t):
    ...         return 2.0 * np.asarray(t, dtype=float)
    ...     def expr(self, t):
    ...         return 2.0 * t
    >>> Ramp()(np.array([0.0, 0.5]))
    array([0., 1.])
    >>> t = ca.SX.sym("t")
    >>> float(ca.Function("f", [t], [Ramp().expr(t)])(3.0))
    6.0
    """

    n_outputs: int = 1
    is_analytic: bool = True

    @abc.abstractmethod
    def __call__(self, t) -> np.ndarray:
        """Evaluate on times ``t`` of shape ``(n,)``: returns ``(n,)`` (one output) or ``(n, n_outputs)``."""

    @abc.abstractmethod
    def expr(self, t: ca.SX) -> ca.SX:
        """The signal as an ``(n_outputs, 1)`` SX expression of the scalar time symbol ``t``."""

    def at_nodes(self, t: np.ndarray, n_nodes: int) -> np.ndarray:
        """The values at ``n_nodes`` equally spaced nodes of every interval of the grid ``t`` (both ends
        included), ``(len(t) - 1, n_nodes, n_outputs)``: what fixed-step RK4 integrates."""
        return self._at(_nodes(t, n_nodes))

    def _at(self, nodes: np.ndarray) -> np.ndarray:
        return np.asarray(self(nodes.ravel())).reshape(*nodes.shape, self.n_outputs)


def _nodes(t, n_nodes: int) -> np.ndarray:
    """``n_nodes`` equally spaced times in every interval of the grid ``t``, both ends included."""
    t = np.asarray(t, dtype=float)
    return t[:-1, None] + np.diff(t)[:, None] * np.arange(n_nodes) / (n_nodes - 1)


@dataclass(frozen=True)
class Sine(Signal):
    """``amplitude * sin(2 pi frequency t + phase)``; the paper's forcing is ``Sine(100, 10)`` (N, Hz).

    Examples
    --------
    >>> import numpy as np
    >>> import symsbl
    >>> symsbl.Sine(100.0, 10.0)(np.array([0.0, 0.025]))
    array([  0., 100.])
    """

    amplitude: float = 100.0
    frequency: float = 10.0
    phase: float = 0.0

    def __call__(self, t):
        return self.amplitude * np.sin(2 * np.pi * self.frequency * np.asarray(t, dtype=float) + self.phase)

    def expr(self, t):
        return self.amplitude * ca.sin(2 * np.pi * self.frequency * t + self.phase)


@dataclass(frozen=True)
class Multisine(Signal):
    """Random-phase multisine: equal-amplitude sines on the harmonics of ``1 / period`` in ``[f_min, f_max]``.

    ``u(t) = sum_k amp * sin(2 pi f_k t + phi_k)`` with ``f_k = k / period``, phases ``phi_k`` uniform in
    ``[0, 2 pi)`` from ``np.random.default_rng(seed)`` and ``amp = rms * sqrt(2 / K)``, so the RMS over one
    period is exactly ``rms`` and the spectrum is flat in the band and zero outside it. The signal is
    periodic with ``period``. Each integrator step evaluates all K sines: keep ``K`` moderate.

    Parameters
    ----------
    rms : float
        Root mean square over one period.
    f_min, f_max : float
        Band edges in Hz (inclusive); at least one harmonic must fall inside.
    seed : int
        Seed of the phases.
    period : float
        Period in seconds; the frequency resolution is ``1 / period``.

    Examples
    --------
    The RMS over one period is exactly ``rms``:

    >>> import numpy as np
    >>> import symsbl
    >>> u = symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1)
    >>> t = np.arange(4096) / 4096.0
    >>> round(float(np.sqrt(np.mean(u(t) ** 2))), 6)
    60.0
    """

    rms: float = 1.0
    f_min: float = 1.0
    f_max: float = 50.0
    seed: int = 0
    period: float = 1.0
    frequencies: np.ndarray = field(init=False, repr=False, compare=False)
    phases: np.ndarray = field(init=False, repr=False, compare=False)
    amplitude: float = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        if not (self.period > 0 and 0 <= self.f_min <= self.f_max):
            raise DataError(
                expected(
                    "Multisine",
                    "period > 0 and 0 <= f_min <= f_max",
                    f"period={self.period}, f_min={self.f_min}, f_max={self.f_max}",
                    raw=True,
                )
            )
        k = np.arange(np.ceil(self.f_min * self.period - 1e-9), np.floor(self.f_max * self.period + 1e-9) + 1)
        k = k[k > 0]
        if k.size == 0:
            raise DataError(
                expected(
                    "Multisine",
                    f"a harmonic of 1/period = {1 / self.period:g} Hz in the band",
                    f"[{self.f_min}, {self.f_max}] Hz, which holds none",
                    "widen the band or lengthen the period",
                    raw=True,
                )
            )
        phases = np.random.default_rng(self.seed).uniform(0.0, 2 * np.pi, k.size)
        object.__setattr__(self, "frequencies", k / self.period)
        object.__setattr__(self, "phases", phases)
        object.__setattr__(self, "amplitude", self.rms * np.sqrt(2.0 / k.size))

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        out = np.zeros_like(t)
        for f, ph in zip(self.frequencies, self.phases):  # a loop keeps memory at O(n), not O(n K)
            out += np.sin(2 * np.pi * f * t + ph)
        return self.amplitude * out

    def expr(self, t):
        return self.amplitude * ca.sum1(ca.sin(2 * np.pi * ca.DM(self.frequencies) * t + ca.DM(self.phases)))


_CHIRP_METHODS = ("linear", "exponential")


@dataclass(frozen=True)
class Chirp(Signal):
    """Swept sine ``amplitude * sin(phi(t))`` from ``f0`` at ``t = 0`` to ``f1`` at ``t = duration``.

    ``method="linear"``: instantaneous frequency ``f(t) = f0 + (f1 - f0) t / duration``,
    ``phi = 2 pi (f0 t + (f1 - f0) t**2 / (2 duration))``.
    ``method="exponential"``: ``f(t) = f0 (f1 / f0)**(t / duration)`` (f0, f1 > 0),
    ``phi = 2 pi f0 duration (r**(t / duration) - 1) / ln r`` with ``r = f1 / f0``.
    The same formula holds outside ``[0, duration]`` (the sweep continues).

    Examples
    --------
    A linear sweep from 1 Hz to 10 Hz over 2 s makes (1 + 10) / 2 * 2 = 11 cycles:

    >>> import numpy as np
    >>> import symsbl
    >>> chirp = symsbl.Chirp(amplitude=1.0, f0=1.0, f1=10.0, duration=2.0)
    >>> t = np.linspace(0.0005, 1.9995, 400001)         # the sweep without its two end points
    >>> int(np.sum(np.diff(np.sign(chirp(t))) != 0))    # 2 * 11 - 1 zero crossings inside
    21
    """

    amplitude: float = 1.0
    f0: float = 1.0
    f1: float = 100.0
    duration: float = 1.0
    method: str = "linear"

    def __post_init__(self):
        if self.method not in _CHIRP_METHODS:
            raise DataError(expected("Chirp.method", f"one of {list(_CHIRP_METHODS)}", self.method))
        if not self.duration > 0:
            raise DataError(expected("Chirp.duration", "a duration > 0 s", self.duration))
        if self.method == "exponential" and not (self.f0 > 0 and self.f1 > 0):
            raise DataError(
                expected("Chirp", "f0 > 0 and f1 > 0 for an exponential sweep", f"f0={self.f0}, f1={self.f1}", raw=True)
            )

    def frequency(self, t):
        """Instantaneous frequency ``phi'(t) / (2 pi)`` in Hz."""
        t = np.asarray(t, dtype=float)
        if self.method == "linear":
            return self.f0 + (self.f1 - self.f0) * t / self.duration
        return self.f0 * (self.f1 / self.f0) ** (t / self.duration)

    def _phase(self, t, exp, log):
        if self.method == "linear":
            return 2 * np.pi * (self.f0 * t + (self.f1 - self.f0) * t * t / (2 * self.duration))
        if self.f1 == self.f0:
            return 2 * np.pi * self.f0 * t
        lr = np.log(self.f1 / self.f0)
        return 2 * np.pi * self.f0 * self.duration * (exp(lr * t / self.duration) - 1) / lr

    def __call__(self, t):
        return self.amplitude * np.sin(self._phase(np.asarray(t, dtype=float), np.exp, np.log))

    def expr(self, t):
        return self.amplitude * ca.sin(self._phase(t, ca.exp, ca.log))


@dataclass(frozen=True)
class FreeDecay(Signal):
    """Zero input on every channel: the response from the initial condition alone.

    Examples
    --------
    >>> import numpy as np
    >>> import symsbl
    >>> symsbl.FreeDecay()(np.array([0.0, 1.0]))
    array([0., 0.])
    """

    n_outputs: int = 1

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        return np.zeros(t.shape) if self.n_outputs == 1 else np.zeros(t.shape + (self.n_outputs,))

    def expr(self, t):
        return ca.SX.zeros(self.n_outputs, 1)


class Sampled(Signal):
    """A measured input: values on a time grid, interpolated in between.

    Parameters
    ----------
    t : array_like, shape (n_samples,)
        Strictly increasing sample times.
    values : array_like, shape (n_samples,) or (n_samples, n_outputs)
    kind : {"linear", "cubic", "periodic", "hold"}
        How the input runs between samples: held linear (the default, what a zero-phase data
        logger implies least), a not-a-knot cubic spline (error O(h^4) instead of O(h^2): use it
        for inputs sampled a few times above their bandwidth), band-limited periodic
        interpolation through the spectrum, exact for a periodic input sampled over whole periods
        (the samples must hold whole periods; the value one period after the first is not repeated),
        or a zero-order hold: each sample's value until the next sample, as a digital
        controller's output steps (fixed-step RK4 holds it over each whole step; adaptive
        integrators cannot take it).

    Notes
    -----
    ``expr`` is a CasADi ``interpolant`` of ``t`` (for adaptive integrators; linear, or a B-spline
    for the other kinds); fixed-step RK4 instead receives the values at its stage nodes from
    ``__call__`` (see :func:`symsbl.simulate`). Outside ``[t[0], t[-1]]`` the linear and cubic
    kinds hold the end values; :func:`~symsbl.simulate` refuses grids that leave the sampled span.

    Examples
    --------
    >>> import numpy as np
    >>> import symsbl
    >>> force = symsbl.Sampled([0.0, 1.0, 2.0], [0.0, 10.0, 0.0])
    >>> force(np.array([0.5, 1.5]))
    array([5., 5.])

    A cubic spline follows a smooth input between its samples:

    >>> t = np.linspace(0.0, 1.0, 21)
    >>> smooth = symsbl.Sampled(t, np.sin(2 * np.pi * t), kind="cubic")
    >>> bool(abs(smooth(np.array([0.125]))[0] - np.sin(np.pi / 4)) < 1e-3)
    True
    """

    is_analytic = False
    KINDS = ("linear", "cubic", "periodic", "hold")

    def __init__(self, t, values, kind: str = "linear"):
        if kind not in self.KINDS:
            raise DataError(expected("kind", f"one of {list(self.KINDS)}", kind))
        self.kind = kind
        t = np.array(t, dtype=float)
        values = np.array(values, dtype=float)
        if t.ndim != 1 or t.size < 2:
            raise DataError(expected("Sampled t", "a 1-D array of at least 2 samples", f"shape {t.shape}", raw=True))
        if values.ndim not in (1, 2) or values.shape[0] != t.size:
            raise DataError(
                expected(
                    "Sampled values",
                    f"shape ({t.size},) or ({t.size}, n_outputs) to match t",
                    f"shape {values.shape}",
                    raw=True,
                )
            )
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(values))):
            raise DataError(
                expected("Sampled", "finite t and values", "NaN/inf samples", "remove or repair them", raw=True)
            )
        if np.any(np.diff(t) <= 0):
            i = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
            raise DataError(
                expected("Sampled t", "strictly increasing times", f"t = {float(t[i])!r} at row {i}", raw=True)
            )
        t.setflags(write=False)
        values.setflags(write=False)
        self.t, self.values = t, values
        self.n_outputs = 1 if values.ndim == 1 else values.shape[1]
        self._interp = None
        self._spline = None

    def __repr__(self):
        return (
            f"Sampled(n_samples={self.t.size}, n_outputs={self.n_outputs}, span=[{self.t[0]}, {self.t[-1]}], "
            f"kind={self.kind!r})"
        )

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        if self.kind == "cubic":
            return self._cubic()(np.clip(t, self.t[0], self.t[-1]))
        if self.kind == "periodic":
            return self._periodic(t)
        if self.kind == "hold":
            return self.values[np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, self.t.size - 1)]
        if self.values.ndim == 1:
            return np.interp(t, self.t, self.values)
        return np.column_stack([np.interp(t, self.t, v) for v in self.values.T])

    def _cubic(self):
        if self._spline is None:
            from scipy.interpolate import CubicSpline

            self._spline = CubicSpline(self.t, self.values, axis=0)
        return self._spline

    def _periodic(self, t: np.ndarray) -> np.ndarray:
        """Band-limited interpolation of samples that hold whole periods of a periodic signal.

        Times on a few fractional offsets of the sample grid (the stages of a fixed-step
        integrator) cost one inverse FFT per offset; other times fall back to the trigonometric
        sum, in blocks.
        """
        n = self.t.size
        dt = (self.t[-1] - self.t[0]) / (n - 1)
        values = self.values if self.values.ndim == 2 else self.values[:, None]
        spectrum = np.fft.rfft(values, axis=0)
        s = (np.ravel(t) - self.t[0]) / dt
        base = np.floor(s + 1e-9)
        frac = np.round(s - base, 9)
        offsets = np.unique(frac)
        out = np.empty((s.size, values.shape[1]))
        if offsets.size <= 130:  # the 2 S + 1 stage nodes of up to 64 RK4 substeps
            k = np.arange(spectrum.shape[0])
            for q in offsets:
                shift = np.exp(2j * np.pi * k * q / n)
                if n % 2 == 0:
                    shift[-1] = np.cos(np.pi * q)  # the Nyquist bin stays real
                shifted = np.fft.irfft(spectrum * shift[:, None], n=n, axis=0)
                rows = frac == q
                out[rows] = shifted[base[rows].astype(np.int64) % n]
        else:
            for start in range(0, s.size, 256):
                part = s[start : start + 256]
                k = np.arange(spectrum.shape[0])
                weight = np.full(k.size, 2.0)
                weight[0] = 1.0
                if n % 2 == 0:
                    weight[-1] = 1.0
                phase = np.exp(2j * np.pi * np.outer(part, k) / n) * weight
                out[start : start + part.size] = (phase @ spectrum).real / n
        return out.reshape(np.shape(t) + self.values.shape[1:])

    def at_nodes(self, t: np.ndarray, n_nodes: int) -> np.ndarray:
        """As :meth:`Signal.at_nodes`; a held input keeps each interval's own value at its right end (the
        step there belongs to the next interval)."""
        nodes = _nodes(t, n_nodes)
        if self.kind == "hold":
            nodes[:, -1] = nodes[:, 0]
        return self._at(nodes)

    def expr(self, t):
        if self.kind == "hold":
            raise SimulationError(
                expected(
                    "Sampled(kind='hold')",
                    "a fixed-step integrator",
                    "an adaptive one",
                    "simulate with method='rk4' (or 'auto')",
                    raw=True,
                )
            )
        if self._interp is None:
            data = np.ascontiguousarray(self.values).ravel()  # sample-major, as interpolant expects
            method = "linear" if self.kind == "linear" else "bspline"
            self._interp = ca.interpolant("u_sampled", method, [self.t], data)
        return self._interp(t)
