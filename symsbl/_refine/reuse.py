"""Compiled passes shared by structures: a sub-structure runs on the passes of a structure that holds it.

One refinement fits several structures: the model with its candidates, the structure its selection
settles on, the union of the equation error's and output error's structures on the model path (on a
shortening of the records), the one the path chooses. Each compiled its own passes (0.3-3 s of C
compiler a structure, gcc's time growing with its sensitivities: 56 % of the CPU of a five-mass chain's
identification). A structure whose terms all belong to one compiled before (with the same RK4 steps and
measured channels; the records are the passes' inputs, not their code) is fitted by that structure's
compiled functions with its other coefficients at zero: the same discrete map, so the same states,
outputs and sensitivities (to rounding), at the cost of the sensitivities the larger structure carries.

:func:`shared_passes` opens the scope in which structures share (one refinement: what is compiled in
one call, or thread, is not kept for the next, so a call's result does not depend on what ran before it);
:func:`passes_of` is where an engine gets its passes.
"""

from __future__ import annotations

import contextlib
import contextvars

import numpy as np

from .._base.jit import MAX_AUTO_SOURCE
from .problem import Parameterisation, Records
from .sensitivity import Passes

__all__ = ["shared_passes", "passes_of", "HOST_SHARE", "HOSTS_KEPT"]

#: A structure runs on a host's passes when its sensitivities (coefficients and states) are at least this share of
#: the host's: a pass costs about in proportion to the sensitivities it carries, a compilation 0.3-3 s. The demo's
#: model paths (6-10 of 14-25 sensitivities) share at 0.3 and not at 0.6; chains of 3 and 5 masses share alike.
HOST_SHARE = 0.3
#: Compiled structures kept within one scope (the newest).
HOSTS_KEPT = 6

#: The compiled structures of the scope open in this context (None: outside a scope, nothing is shared).
_HOSTS: contextvars.ContextVar[list[Passes] | None] = contextvars.ContextVar("symsbl_hosts", default=None)


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
        hosts.append(own)
        del hosts[:-HOSTS_KEPT]
    return own


def _embedding(param: Parameterisation, records: Records, host: Passes) -> np.ndarray | None:
    """Where each of ``param``'s free coefficients sits in ``host``'s, when ``host``'s compiled passes compute
    ``param``'s right-hand side and outputs with its other coefficients at zero (else None)."""
    nx, theirs_records = len(param.model.states), host.records
    if param.n_free + nx < HOST_SHARE * (host.param.n_free + nx):
        return None
    if records.substeps != theirs_records.substeps or records.outputs != theirs_records.outputs:
        return None
    mine, theirs = param.model, host.param.model
    if (
        mine.state_names != theirs.state_names
        or mine.input_names != theirs.input_names
        or [(eq.lhs, eq.fixed) for eq in mine.equations] != [(eq.lhs, eq.fixed) for eq in theirs.equations]
    ):
        return None
    slots = _slots(host.param)
    embed, fixed_seen = [], 0
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
    return np.array(embed, dtype=int)


def _slots(param: Parameterisation) -> dict:
    """``(equation, name, expression) -> (free, index of the free coefficient or -1, fixed coefficient)``."""
    out, k = {}, 0
    for i, j, free in param.terms:
        term = param.model.equations[i].terms[j]
        out[(i, term.name, str(term.expr))] = (free, k if free else -1, None if free else term.coef)
        k += int(free)
    return out
