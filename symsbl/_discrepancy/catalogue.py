"""A catalogue of named physical effects for the discrepancy workflow.

Each :class:`Effect` is a physical mechanism that a mechanical model ``m x'' + ... = F`` may be
missing, written as the symbolic term(s) it adds to the *velocity* equation ``v' = ...`` of a
displacement/velocity pair ``(x, v)``, together with its admissibility rule (the sign its
coefficient must have for the effect to be physical) and, for effects with a shape parameter
(the gap of a clearance), a grid of values relative to the measured amplitude.

The terms are CasADi expressions built from the model's own symbols, so their names, their
columns in the regression and their place in the re-simulated model derive from one object.
Users add effects with :class:`Effect` directly, e.g.::

    Effect("van_der_pol", "amplitude-dependent negative damping", "damping",
           lambda x, v: x**2 * v)

Sign convention: in ``v' = (F - f(x, v)) / m`` a force ``f`` that dissipates energy or pulls
back towards rest enters ``v'`` with a coefficient of the sign *opposite* to that of the input's
coefficient ``1 / m``. ``sign=-1`` demands this; ``sign=0`` accepts either sign (a stiffness that
may harden or soften).

References
----------
K. Worden, G. R. Tomlinson, *Nonlinearity in Structural Dynamics*, IOP 2001, ch. 1-2 (the
catalogue of nonlinearities); R. Fuentes et al., J. Phys.: Conf. Ser. 1264 (2019) 012050
(the paper's quadratic damping ``k2 x2**2``).
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import casadi as ca

from .._base.errors import LibraryError, expected

__all__ = ["Effect", "Variant", "CATALOGUE", "catalogue", "get_effect"]


@dataclass(frozen=True)
class Variant:
    """One concrete candidate of an effect: its terms for given symbols and shape value.

    Attributes
    ----------
    effect : Effect
    exprs : tuple of casadi.SX
        Terms added to the velocity equation.
    shape : float or None
        Shape parameter (e.g. the clearance gap, in displacement units), None when the effect
        has none.
    """

    effect: Effect
    exprs: tuple
    shape: float | None = None

    @property
    def label(self) -> str:
        """The effect's name, with the shape value when there is one."""
        if self.shape is None:
            return self.effect.name
        return f"{self.effect.name}({self.effect.shape_name}={self.shape:.4g})"


@dataclass(frozen=True)
class Effect:
    """A named physical effect and the term(s) it adds to the velocity equation.

    Parameters
    ----------
    name : str
        Identifier, e.g. ``"coulomb_friction"`` (a Python-style name).
    description : str
        The effect in physical words, used in reports.
    family : str
        ``"friction"``, ``"damping"``, ``"stiffness"``, ``"clearance"`` or any other label;
        effects of one family are the ones most easily confused.
    terms : callable
        ``terms(x, v)`` (or ``terms(x, v, shape)`` when ``grid`` is given) returning one
        CasADi/scalar expression or a sequence of them, built from the displacement ``x`` and
        velocity ``v`` symbols.
    sign : {-1, 0}
        Admissibility: -1 when the effect must dissipate energy or restore (coefficient of sign
        opposite to the input's), 0 when either sign is physical.
    grid : tuple of float
        Shape values as fractions of the measured amplitude of ``grid_of``; empty for none.
        The best grid point is kept and pays ``log(len(grid))`` nats of evidence.
    grid_of : {"x", "v"}
        Which amplitude the grid is relative to.
    shape_name : str
        Name of the shape parameter in reports.
    coefficient : str
        Name of the physical coefficient (force per unit of the term) in reports, e.g. ``"Fc"``.

    Examples
    --------
    A user's effect: Stribeck-like friction that fades above 1 cm/s.

    >>> import casadi as ca
    >>> import symsbl
    >>> stribeck = symsbl.Effect("stribeck", "friction falling with speed", "friction",
    ...                          lambda x, v: ca.sign(v) * ca.exp(-(v / 0.01) ** 2), sign=-1, coefficient="Fs")
    >>> [e.name for e in symsbl.catalogue([stribeck])][-2:]
    ['clearance', 'stribeck']
    """

    name: str
    description: str
    family: str
    terms: Callable
    sign: int = 0
    grid: tuple = ()
    grid_of: str = "x"
    shape_name: str = "g"
    coefficient: str = "k"

    def variants(self, x: ca.SX, v: ca.SX, x_amplitude: float = 1.0, v_amplitude: float = 1.0) -> list[Variant]:
        """The candidates of this effect for symbols ``x``, ``v`` and the measured amplitudes.

        Raises
        ------
        LibraryError
            If ``terms`` does not return scalar expressions of ``x`` and ``v``.
        """
        if self.sign not in (-1, 0):
            raise LibraryError(expected(f"effect {self.name!r}: sign", "-1 or 0", self.sign))
        if self.grid_of not in ("x", "v"):
            raise LibraryError(expected(f"effect {self.name!r}: grid_of", "'x' or 'v'", self.grid_of))
        if not self.grid:
            return [Variant(self, self._exprs(self.terms(x, v)))]
        scale = x_amplitude if self.grid_of == "x" else v_amplitude
        return [Variant(self, self._exprs(self.terms(x, v, g * scale)), float(g * scale)) for g in self.grid]

    def _exprs(self, out) -> tuple:
        items = list(out) if isinstance(out, (list, tuple)) else [out]
        exprs = []
        for item in items:
            try:
                e = ca.SX(item)
            except (NotImplementedError, TypeError, RuntimeError):
                raise LibraryError(
                    expected(
                        f"effect {self.name!r}: terms",
                        "CasADi SX expressions of the displacement and velocity symbols",
                        type(item).__name__,
                        raw=True,
                    )
                ) from None
            if not e.is_scalar():
                raise LibraryError(
                    expected(f"effect {self.name!r}: terms", "scalar expressions", f"shape {e.shape}", raw=True)
                )
            exprs.append(e)
        if not exprs:
            raise LibraryError(expected(f"effect {self.name!r}: terms", "at least one expression", "none", raw=True))
        return tuple(exprs)


def _clearance(x, v, g):
    return ca.fmax(ca.fabs(x) - g, 0) * ca.sign(x)


#: The default catalogue, in report order.
CATALOGUE: tuple[Effect, ...] = (
    Effect(
        "coulomb_friction",
        "Coulomb (dry) friction: a force of constant size opposing the velocity",
        "friction",
        lambda x, v: ca.sign(v),
        sign=-1,
        coefficient="Fc",
    ),
    Effect(
        "quadratic_damping",
        "quadratic (turbulent/drag) damping, a force v|v| opposing the velocity",
        "damping",
        lambda x, v: v * ca.fabs(v),
        sign=-1,
        coefficient="c2",
    ),
    Effect(
        "velocity_squared",
        "a force proportional to v^2 (the paper's quadratic damping, even in v)",
        "damping",
        lambda x, v: v**2,
        sign=0,
        coefficient="k2",
    ),
    Effect(
        "cubic_damping",
        "cubic damping, a force v^3 opposing the velocity",
        "damping",
        lambda x, v: v**3,
        sign=-1,
        coefficient="c3",
    ),
    Effect(
        "cubic_stiffness",
        "cubic (Duffing) stiffness, a hardening or softening spring force x^3",
        "stiffness",
        lambda x, v: x**3,
        sign=0,
        coefficient="k3",
    ),
    Effect(
        "quadratic_stiffness",
        "quadratic stiffness, a symmetric spring force x|x|",
        "stiffness",
        lambda x, v: x * ca.fabs(x),
        sign=0,
        coefficient="kq",
    ),
    Effect(
        "clearance",
        "a clearance (backlash/contact): a spring that engages beyond a gap g",
        "clearance",
        _clearance,
        sign=-1,
        grid=tuple(round(0.1 * i, 1) for i in range(1, 10)),
        coefficient="kg",
    ),
)


def catalogue(extra: Sequence[Effect] = (), *, exclude: Sequence[str] = ()) -> tuple[Effect, ...]:
    """The default catalogue plus ``extra`` user effects, without the ``exclude`` names.

    Raises
    ------
    LibraryError
        On an unknown name in ``exclude``, a non-:class:`Effect` in ``extra`` or a repeated name.

    Examples
    --------
    >>> import symsbl
    >>> [e.name for e in symsbl.catalogue(exclude=["clearance"])]
    ['coulomb_friction', 'quadratic_damping', 'velocity_squared', 'cubic_damping', 'cubic_stiffness',
     'quadratic_stiffness']
    """
    for name in exclude:
        get_effect(name)
    out = [e for e in CATALOGUE if e.name not in set(exclude)]
    for e in extra:
        if not isinstance(e, Effect):
            raise LibraryError(expected("extra", "Effect instances", type(e).__name__, raw=True))
        out.append(e)
    names = [e.name for e in out]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise LibraryError(
            expected(
                "effects", "distinct effect names", f"{repeated} more than once", "rename the new effect", raw=True
            )
        )
    return tuple(out)


def get_effect(name: str, effects: Sequence[Effect] = CATALOGUE) -> Effect:
    """The effect called ``name``.

    Raises
    ------
    LibraryError
        If there is none; the message lists the valid names.
    """
    for e in effects:
        if e.name == name:
            return e
    close = difflib.get_close_matches(str(name), [e.name for e in effects], n=3)
    raise LibraryError(
        expected("effect", f"one of {[e.name for e in effects]}", name, f"did you mean {close[0]!r}?" if close else "")
    )
