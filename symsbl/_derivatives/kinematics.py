"""Kinematics: positions whose derivative is a velocity state, and velocities that were never measured.

``kinematics={"x1": "x2"}`` declares that ``x1' = x2`` holds exactly (a position and its velocity):
that equation is fixed, not identified, and ``x2`` may be absent from the data, as in every
laser-vibrometer test that records displacement only. For the equation-error stage an unmeasured
velocity is estimated from its position by a smoothing derivative (:func:`estimate_velocity`), which
is biased and noisy where the record is; the output-error refinement (:func:`symsbl.refine`) then
fits only the measured columns, with the unmeasured initial states as unknowns, and removes that bias.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from .._base.errors import DataError, expected
from .._data.trajectory import Trajectory
from .weakform import WeakForm

__all__ = ["parse_kinematics", "estimate_velocity", "latent_states", "complete_states", "with_velocities"]


def _pairs(spec) -> list:
    """The ``(position, velocity)`` pairs a mapping or text declares, not yet checked against any states."""
    if spec is None or spec == "" or spec == {}:
        return []
    if isinstance(spec, str):
        pairs = []
        for part in filter(None, (p.strip() for p in spec.split(","))):
            x, sep, v = part.partition(":")
            if not sep:
                raise DataError(expected("--kinematics", "position:velocity pairs such as x1:x2,x3:x4", part))
            pairs.append((x.strip(), v.strip()))
        return pairs
    if isinstance(spec, Mapping):
        return list(spec.items())
    raise DataError(expected("kinematics", "a mapping {position: velocity} or text 'x1:x2'",
                             type(spec).__name__, raw=True))


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
            raise DataError(expected("kinematics", f"position: velocity pairs of the states {list(states)}",
                                     f"{x}:{v}", raw=True))
        if x in used or v in used:
            raise DataError(expected("kinematics", "each state in at most one pair", f"{x}:{v}", raw=True))
        used |= {x, v}
    return tuple(pairs)


def with_velocities(names: Sequence[str], spec) -> tuple[str, ...]:
    """``names`` with the velocity of each declared pair that they lack placed after its position: the states of
    a model whose records hold only the positions.

    Examples
    --------
    >>> with_velocities(["y1", "y2", "z"], "y1:v1,y2:v2")
    ('y1', 'v1', 'y2', 'v2', 'z')
    """
    extra = {x: v for x, v in _pairs(spec) if x in names and v not in names}
    return tuple(n for name in names for n in ((name, extra[name]) if name in extra else (name,)))


def estimate_velocity(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The derivative of a sampled position by a smoothing (Savitzky-Golay, quintic) derivative filter.

    The half-window is a quarter of the period of the highest frequency that carries the position's
    signal (the bandwidth the weak form reads off the spectrum, above the white-noise floor), where
    the quintic filter's gain is within 0.02 % of the exact derivative's; the noise above that band is
    attenuated.

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
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    h = float(t[1] - t[0])
    window = WeakForm().resolve(t, x[:, None]).window  # about 0.5 / f_hi in samples
    assert window is not None  # resolve() sets it
    half = int(max(3, round(0.5 * window)))
    half = min(half, (len(x) - 1) // 2)
    if half < 3:
        return np.gradient(x, h)
    from scipy.signal import savgol_filter  # scipy.signal costs ~1 s to import: only when used

    return savgol_filter(x, 2 * half + 1, 5, deriv=1, delta=h, mode="interp")


def latent_states(names: Sequence[str], measured: Sequence[str], pairs) -> tuple[str, ...]:
    """The states of ``names`` that are neither ``measured`` nor the velocity of a position-velocity pair:
    latent, with a law of their own that no record holds (see :mod:`symsbl._latent`)."""
    velocities = {v for _, v in pairs}
    return tuple(n for n in names if n not in measured and n not in velocities)


def complete_states(trajectories: Sequence[Trajectory], states: Sequence[str],
                    pairs: Sequence[tuple[str, str]]) -> tuple[list[Trajectory], tuple[str, ...]]:
    """The records with every state of ``states``, unmeasured velocities estimated from their positions.

    Returns the completed records and the names of the states that were not measured.
    """
    measured = trajectories[0].state_names
    unmeasured = tuple(s for s in states if s not in measured)
    velocity_of = {v: x for x, v in pairs}
    for s in unmeasured:
        if s not in velocity_of:
            raise DataError(expected(
                f"state {s!r}", "a column of the data, or the velocity of a declared kinematic pair (x:v)",
                "neither", f"add --kinematics {next(iter(measured), 'x')}:{s} if {s} is a velocity", raw=True))
        if velocity_of[s] not in measured:
            raise DataError(expected(f"state {s!r}", f"its position {velocity_of[s]!r} measured", "no such column",
                                     raw=True))
    if not unmeasured:
        return [tr.with_states(states) for tr in trajectories], ()
    out = []
    for tr in trajectories:
        columns = {n: tr.column(n) for n in measured}
        for s in unmeasured:
            columns[s] = estimate_velocity(tr.t, columns[velocity_of[s]])
        out.append(Trajectory(tr.t, np.column_stack([columns[s] for s in states]), tr.inputs, tuple(states),
                              tr.input_names))
    return out, unmeasured
