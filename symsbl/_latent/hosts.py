"""The host of a latent state on a structure of several degrees of freedom, and what drives it.

On a chain of masses the hidden force between one mass and the ground (hysteresis, friction with
pre-sliding, in its support) enters the velocity equation of that mass, the *host*, with a law in the
host's velocity (a force between two masses, a law in their relative velocity, is not identified yet).
Every measured position is averaged over the same periods of the record (one cut for all) with its
band-limited derivatives, and each velocity equation is fitted by least squares on every position,
velocity and input:

    y_j'' = sum_i (k_ji y_i + c_ji y_i') + sum_l b_jl u_l + residual_j.

:func:`host_of`: a linear equation leaves a residual at its acceleration's noise (the spectral operator's
propagated noise); the host's leaves its hidden force's nonlinear part as well, so the host is the pair
whose residual exceeds its noise most. Measured: 3.5 and 0.91 times the noise on two masses with Dahl
friction on the first, 22 and 0.97 with a Bouc-Wen hysteresis on the first.

:func:`drives`: seen from the host, the rest of the structure is an input, and the host becomes the
single-degree-of-freedom problem of :mod:`.skeleton` and :mod:`.law` (``m y_h'' + c y_h' + k y_h + z = d``)
driven by

    d = sum_{j != h} (k_hj y_j + c_hj y_j') + sum_l b_hl u_l,

divided by the input's coefficient where the input acts on the host (the latent state then keeps the
input's units, as on one degree of freedom), else taken per unit mass. The host's own least-squares fit
books part of the hidden force on its neighbours' coupling; two drives are offered and the split keeps the
one whose hidden force a law explains best:

- *free*: the host's coupling as its least-squares fit gives it;
- *reciprocal*: a spring or damper between masses h and j pulls both (``K_hj = K_jh``), so the host's
  coupling to j is mass j's own (hidden-force-free) coupling to the host, ``(k_jh y_j + c_jh y_j')``, times
  one ratio ``m_j / m_h`` fitted with the host's skeleton: one unknown per neighbour instead of two.

Measured on the Dahl chain (the force on the second mass): the free drive's split left 0.013 of the hidden
force's derivative unexplained, the reciprocal 0.018, and the output error from the free start found the
law and every coefficient exactly. With a Bouc-Wen hysteresis on the driven first mass the free drive put
a damping of -30 on the neighbour's velocity (true +2) and its split left 0.41; the reciprocal 2.2 and
0.14, and the model from it predicted a fresh multisine within 0.4 % (``tests/test_latent.py``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .periodic import Periods

__all__ = ["Drive", "same_cut", "host_of", "drives", "DRIVEN"]

#: The input acts on the host when its part of the host's acceleration, ``|b| rms(u) / rms(y_h'')``, exceeds
#: this share; below it the fitted coefficient is the coupling's leakage (measured: 0.2 % on a mass the
#: input does not touch, 80 % on the one it drives).
DRIVEN = 0.05


@dataclasses.dataclass(frozen=True)
class Drive:
    """What drives a host besides its own skeleton.

    Attributes
    ----------
    host : (str, str)
        The host's position and velocity.
    pairs : tuple of (str, str)
        Every position-velocity pair of the structure.
    terms : tuple of (str, float)
        The drive ``d = sum kappa w``: each variable (an input, another position or velocity) and its
        coefficient.
    u : ndarray
        The drive on the record's (averaged) samples.
    driven : bool
        The input acts on the host: the drive is in the input's units.
    others : dict
        Per other velocity, its least-squares equation ``{velocity: ((variable, coefficient), ...)}``.
    kind : str
        ``"free"`` or ``"reciprocal"`` (see the module text).
    """

    host: tuple
    pairs: tuple
    terms: tuple
    u: np.ndarray
    driven: bool
    others: dict
    kind: str = "free"


def same_cut(periods: Periods, y: np.ndarray) -> Periods:
    """``periods`` with another measured signal ``y`` of the same record in place of its output: the same start,
    period and dropped periods, so that every position of a structure is averaged over the same samples."""
    P, L = periods.Y.shape
    Y = np.asarray(y, dtype=float)[periods.start : periods.start + P * L].reshape(P, L)
    return dataclasses.replace(periods, Y=Y)


def _lstsq(A: np.ndarray, b: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Least squares of ``b`` on the columns of ``A`` over the rows ``keep``, the columns scaled to unit norm."""
    scale = np.maximum(np.linalg.norm(A[keep], axis=0), 1e-300)
    coef, *_ = np.linalg.lstsq(A[keep] / scale, b[keep], rcond=None)
    return coef / scale


def _share(part: np.ndarray, whole: np.ndarray, keep: np.ndarray) -> float:
    return float(np.std(part[keep]) / max(float(np.std(whole[keep])), 1e-300))


def _columns(spectra: dict, pairs, inputs: dict):
    names = [n for pair in pairs for n in pair] + list(inputs)
    values = [x for y, _ in pairs for x in (spectra[y].y, spectra[y].v)] + list(inputs.values())
    return names, dict(zip(names, values)), np.column_stack(values)


def host_of(spectra: dict, pairs, inputs: dict) -> tuple[tuple, dict]:
    """The host pair, and per position the RMS of its velocity equation's least-squares residual over the
    propagated noise of its acceleration."""
    _, _, A = _columns(spectra, pairs, inputs)
    misfit = {}
    for y, _ in pairs:
        s, keep = spectra[y], spectra[y].valid
        residual = s.a - A @ _lstsq(A, s.a, keep)
        misfit[y] = float(np.sqrt(np.mean(residual[keep] ** 2)) / max(s.sd(s.iw**2), 1e-300))
    return next(p for p in pairs if p[0] == max(misfit, key=misfit.__getitem__)), misfit


def drives(spectra: dict, pairs, inputs: dict, host) -> list[Drive]:
    """The host's drives, free and reciprocal (see the module text).

    Parameters
    ----------
    spectra : dict
        Per position, its :class:`Spectra` over one cut of the record.
    pairs : sequence of (str, str)
        The position-velocity pairs, every position measured.
    inputs : dict
        Per input, its samples on the same (averaged) grid.
    host : (str, str)
        The host pair.
    """
    names, col, A = _columns(spectra, pairs, inputs)
    rows = {v: _lstsq(A, spectra[y].a, spectra[y].valid) for y, v in pairs}
    y, v = host
    keep, acc = spectra[y].valid, spectra[y].a
    others = {w: tuple(zip(names, (float(c) for c in rows[w]))) for _, w in pairs if w != v}
    free = [(n, float(c)) for n, c in zip(names, rows[v]) if n not in (y, v)]
    coupled = []  # each neighbour (y_j, v_j, k_jh, c_jh) whose equation the host pulls beyond DRIVEN
    for yj, vj in pairs:
        k, g = (float(rows[vj][names.index(n)]) for n in (y, v))
        if vj != v and _share(k * col[y] + g * col[v], spectra[yj].a, keep) > DRIVEN:
            coupled.append((yj, vj, k, g))
    pulls = [k * col[yj] + g * col[vj] for yj, vj, k, g in coupled]
    coef = _lstsq(np.column_stack([col[y], col[v], *pulls, *inputs.values()]), acc, keep)[2:]
    reciprocal = [(n, float(r * w)) for (yj, vj, k, g), r in zip(coupled, coef) for n, w in ((yj, k), (vj, g))]
    reciprocal += [(i, float(b)) for i, b in zip(inputs, coef[len(coupled) :])]
    first = next(iter(inputs))
    return [
        _normalised(kind, host, pairs, terms, col, acc, keep, first, others)
        for kind, terms in (("free", free), ("reciprocal", reciprocal))
    ]


def _normalised(kind, host, pairs, terms, col, acc, keep, first: str, others) -> Drive:
    """The drive of ``terms``, divided by the first input's coefficient where that input acts on the host."""
    gain = dict(terms).get(first, 0.0)
    driven = _share(gain * col[first], acc, keep) > DRIVEN
    norm = gain if driven else 1.0
    terms = tuple((n, c / norm) for n, c in terms)
    u = sum(c * col[n] for n, c in terms)
    return Drive(tuple(host), tuple(pairs), terms, np.asarray(u, dtype=float), bool(driven), others, kind)
