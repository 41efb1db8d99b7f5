"""Compiled passes shared by structures: a sub-structure runs on the passes of a structure that holds it.

One refinement fits several structures: the model with its candidates, the structure its selection
settles on, the union of the equation error's and output error's structures on the model path (on a
shortening of the records), the one the path chooses. Each compiled its own passes (0.3-3 s of C
compiler a structure, gcc's time growing with its sensitivities: 56 % of the CPU of a five-mass chain's
identification). A structure whose terms all belong to one compiled before (with the same RK4 steps and
measured channels; the records are the passes' inputs, not their code) is fitted by that structure's
compiled functions with its other coefficients at zero: the same discrete map, so the same states,
outputs and sensitivities (to rounding), at the cost of the sensitivities the larger structure carries.

:func:`shared_passes` opens the scope in which structures share: one refinement, in its own thread. What
one call compiled does not host the next call's structures, so which structures share depends on the call
alone (and, under ``jit="auto"`` on short records, on which passes the compilation cache already holds);
:func:`passes_of` is where an engine gets its passes.
"""

from __future__ import annotations

import contextlib
import contextvars

import numpy as np
import sympy as sp

from .._base.jit import MAX_AUTO_SOURCE
from .problem import Parameterisation, Records
from .sensitivity import Kernels, Passes

__all__ = ["shared_passes", "passes_of", "HOST_SHARE", "HOSTS_KEPT"]

#: A structure runs on a host's passes when its sensitivities (coefficients and states) are at least this share of
#: the host's: a pass costs about in proportion to the sensitivities it carries, a compilation 0.3-3 s, and a
#: structure compiled in an earlier run loads in milliseconds (so a warm cache pays the host's surplus for nothing).
#: Chains of 3 and 5 masses share at 0.6 as at 0.3; the demo's model paths (6-10 of 14-25 sensitivities) at 0.3
#: only, for 10 compilations of 0.3-0.5 s.
HOST_SHARE = 0.6
#: Functions whose value and derivative are finite wherever their arguments are: a host's term outside the
#: structure is multiplied by zero, and ``0 * inf`` (``1/x``, ``sqrt(x)``'s slope at 0, ``log``) is NaN.
BOUNDED = (sp.sin, sp.cos, sp.tanh, sp.atan, sp.Abs, sp.sign, sp.exp)
#: Compiled structures kept within one scope (the newest).
HOSTS_KEPT = 6

#: The compiled structures of the scope open in this context (None: outside a scope, nothing is shared).
_HOSTS: contextvars.ContextVar[list[Kernels] | None] = contextvars.ContextVar("symsbl_hosts", default=None)


@contextlib.contextmanager
def shared_passes():
    """The scope in which compiled passes serve the sub-structures fitted after them (nested scopes: the outer
    one's)."""
    if _HOSTS.get() is not None:
        yield
        return
    token = _HOSTS.set([])
    try:
        yield
    finally:
        _HOSTS.reset(token)


def passes_of(param: Parameterisation, records: Records, jit="auto", max_source: int = MAX_AUTO_SOURCE) -> Passes:
    """The passes of ``param`` on ``records``: run by a compiled host's functions where one holds the structure,
    else compiled for it (and kept as a host, inside a :func:`shared_passes` scope)."""
    hosts = _HOSTS.get()
    if hosts is None or jit is False:
        return Passes(param, records, jit=jit, max_source=max_source)
    found = [(host, embed) for host in hosts if (embed := _embedding(param, records, host)) is not None]
    if found:
        host, embed = min(found, key=lambda pair: pair[0].param.n_free)
        return Passes(param, records, jit=jit, host=(host, embed), max_source=max_source)
    own = Passes(param, records, jit=jit, max_source=max_source)
    if own.compiled and not own.staged:
        hosts.append(own.kernels)  # the compiled functions, not the records
        del hosts[:-HOSTS_KEPT]
    return own


def _embedding(param: Parameterisation, records: Records, host: Kernels) -> np.ndarray | None:
    """Where each of ``param``'s free coefficients sits in ``host``'s, when ``host``'s compiled passes compute
    ``param``'s right-hand side and outputs with its other coefficients at zero (else None)."""
    nx = len(param.model.states)
    if param.n_free + nx < HOST_SHARE * (host.param.n_free + nx):
        return None
    if records.substeps != host.substeps or records.outputs != host.outputs:
        return None
    mine, theirs = param.model, host.param.model
    if (
        mine.state_names != theirs.state_names
        or mine.input_names != theirs.input_names
        or [(eq.lhs, eq.fixed) for eq in mine.equations] != [(eq.lhs, eq.fixed) for eq in theirs.equations]
    ):
        return None
    slots = _slots(host.param)
    embed: list[int] = []
    fixed_seen = 0
    for i, j, free in param.terms:
        term = mine.equations[i].terms[j]
        slot = slots.get((i, term.name, str(term.expr)))
        if slot is None or slot[0] != free or (not free and slot[2] != term.coef):
            return None
        if free:
            embed.append(slot[1])
        else:
            fixed_seen += 1
    if fixed_seen != sum(not free for _, _, free in host.param.terms):  # a fixed term of the host's only: not zero
        return None
    used = set(embed)
    if len(used) != len(embed):  # a term twice: one coefficient of the host's for two of this structure's
        return None
    extra = [t for k, t in enumerate(_free_terms(host.param)) if k not in used]
    return np.array(embed, dtype=int) if all(_bounded(t.sympy) for t in extra) else None


def _free_terms(param: Parameterisation) -> list:
    """The terms of ``param``'s free coefficients, in their order."""
    return [param.model.equations[i].terms[j] for i, j, free in param.terms if free]


def _bounded(expr: sp.Expr) -> bool:
    """Whether a term's value and its derivatives are finite wherever its variables are: polynomials in them and
    in :data:`BOUNDED` functions of them (``tan`` is not: a pole within a runaway trial would poison the pass)."""
    powers = all(p.exp.is_Integer and p.exp >= 0 for p in expr.atoms(sp.Pow))
    return powers and all(isinstance(f, BOUNDED) for f in expr.atoms(sp.Function))


def _slots(param: Parameterisation) -> dict:
    """``(equation, name, expression) -> (free, index of the free coefficient or -1, fixed coefficient)``."""
    out, k = {}, 0
    for i, j, free in param.terms:
        term = param.model.equations[i].terms[j]
        out[(i, term.name, str(term.expr))] = (free, k if free else -1, None if free else term.coef)
        k += int(free)
    return out
