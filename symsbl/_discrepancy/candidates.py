"""What the output-error discrepancy search tries: catalogue effects on every position-velocity pair
and between connected pairs, and library terms outside the catalogue.

A :class:`Candidate` is a set of terms added to one or two velocity equations, each with its own
coefficient. For a pair ``(x, v)`` an effect adds ``phi(x, v)`` to ``v'``. Between two connected pairs
``(x1, v1)`` and ``(x2, v2)`` (the velocity equation of one holds a state of the other) it adds
``phi(x1 - x2, v1 - v2)`` to both ``v1'`` and ``v2'``: a force of the link acts on both masses, with
coefficients ``-1/m1`` and ``+1/m2``, which the fit estimates separately. Library terms (products of
the pair's states up to degree three, absolute values, an offset) are the search beyond the catalogue.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from .._base.rule import multiplicity
from .._symbolic.symbols import casadi_to_sympy
from .catalogue import Effect

__all__ = ["Candidate", "Pair", "pairs_of", "catalogue_candidates", "library_candidates", "reshaped", "term_name"]


def term_name(expr) -> str:
    """A term's printed name (the key under which two terms are the same)."""
    return str(casadi_to_sympy([expr])[0])


@dataclass(frozen=True)
class Pair:
    """A position-velocity pair, or the relative motion of two (``x`` and ``v`` are then differences)."""

    x: str
    v: str
    velocities: tuple  # the velocity equations the candidate's terms join
    x_expr: object = field(repr=False, compare=False, default=None)
    v_expr: object = field(repr=False, compare=False, default=None)

    @property
    def where(self) -> str:
        if len(self.velocities) == 1:
            return f"{self.x}, {self.v}"
        return f"between ({self.x}) and ({self.v})"


@dataclass(frozen=True)
class Candidate:
    """Terms added to velocity equations, each with its own coefficient.

    Attributes
    ----------
    effect : Effect or None
        The catalogue effect (None: a library term outside the catalogue).
    label : str
        The effect's name with its shape value, or the library term.
    pair : Pair
    additions : tuple of (str, tuple of casadi.SX)
        Per velocity equation, the terms added.
    shape : float or None
    penalty : float
        Nats the gain pays for the choice among look-alikes (``log`` of the grid or library size).
    """

    effect: Effect | None
    label: str
    pair: Pair
    additions: tuple = field(repr=False)
    shape: float | None = None
    penalty: float = 0.0

    @property
    def name(self) -> str:
        return self.effect.name if self.effect is not None else self.label

    @property
    def terms(self) -> tuple:
        """The added terms' names, each once (an effect between two masses adds the same term to both)."""
        return tuple(dict.fromkeys(term_name(e) for _, exprs in self.additions for e in exprs))

    @property
    def key(self) -> tuple:
        """Effect and place: the variants of one grid share it."""
        return (self.name, self.pair.where)


def pairs_of(base: dict, symbols: dict, declared=()) -> list[Pair]:
    """The position-velocity pairs (declared, or read from base equations ``x: v``), then the relative motion
    of every two pairs whose velocity equations are coupled."""
    found = list(declared)
    if not found:
        for x, terms in base.items():
            names = [term_name(t) for t in terms]
            if len(names) == 1 and names[0] in symbols and names[0] != x:
                found.append((x, names[0]))
    out = [Pair(x, v, (v,), symbols[x], symbols[v]) for x, v in found]
    for i, (x1, v1) in enumerate(found):
        for x2, v2 in found[i + 1 :]:
            deps = [
                ca.depends_on(ca.vertcat(*base[a]), ca.vertcat(symbols[b1], symbols[b2]))
                for a, (b1, b2) in ((v1, (x2, v2)), (v2, (x1, v1)))
                if base.get(a)
            ]
            if any(deps):
                out.append(
                    Pair(f"{x1}-{x2}", f"{v1}-{v2}", (v1, v2), symbols[x1] - symbols[x2], symbols[v1] - symbols[v2])
                )
    return out


def _amplitude(expr, symbols: dict, records) -> float:
    f = ca.Function("a", [ca.vertcat(*symbols.values())], [expr])
    peak = 0.0
    for r in records:
        Z = np.column_stack([r.column(n) for n in symbols])
        peak = max(peak, float(np.max(np.abs(np.asarray(f.map(Z.shape[0])(Z.T))))))
    return peak if peak > 0 else 1.0


def catalogue_candidates(effects, pairs: list[Pair], symbols: dict, records) -> list[Candidate]:
    """Every variant of every effect on every pair."""
    out = []
    for pair in pairs:
        x_amp = _amplitude(pair.x_expr, symbols, records)
        v_amp = _amplitude(pair.v_expr, symbols, records)
        for effect in effects:
            variants = effect.variants(pair.x_expr, pair.v_expr, x_amp, v_amp)
            penalty = multiplicity(len(variants))
            for w in variants:
                label = w.label if len(pairs) == 1 else f"{w.label} [{pair.where}]"
                out.append(
                    Candidate(effect, label, pair, tuple((s, w.exprs) for s in pair.velocities), w.shape, penalty)
                )
    return out


def reshaped(c: Candidate, shape: float) -> Candidate:
    """``c`` with its shape parameter at ``shape`` (the same effect, place and penalty)."""
    effect = c.effect
    assert effect is not None  # only catalogue effects have a shape
    exprs = effect._exprs(effect.terms(c.pair.x_expr, c.pair.v_expr, shape))
    label = f"{effect.name}({effect.shape_name}={shape:.4g})"
    if c.label.endswith("]"):
        label += f" [{c.pair.where}]"
    return Candidate(effect, label, c.pair, tuple((s, exprs) for s in c.pair.velocities), float(shape), c.penalty)


def _library_terms(x, v) -> list:
    """Terms of one pair beyond the linear ones: products up to degree three, absolute values, an offset."""
    out = [
        ca.SX(1),
        x**2,
        x * v,
        v**2,
        x**3,
        x**2 * v,
        x * v**2,
        v**3,
        ca.fabs(x),
        ca.fabs(v),
        x * ca.fabs(x),
        v * ca.fabs(v),
        x * ca.fabs(v),
        v * ca.fabs(x),
        ca.sign(v),
        ca.sign(x),
    ]
    return out


def library_candidates(pairs: list[Pair], taken: set) -> list[Candidate]:
    """Library terms of each single pair not already among ``taken`` term names (catalogue or model)."""
    out = []
    for pair in (p for p in pairs if len(p.velocities) == 1):
        terms = [e for e in _library_terms(pair.x_expr, pair.v_expr) if term_name(e) not in taken]
        penalty = multiplicity(max(len(terms), 2))
        for e in terms:
            out.append(Candidate(None, term_name(e), pair, ((pair.v, (e,)),), None, penalty))
    return out
