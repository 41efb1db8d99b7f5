"""One compiled pass over the records: the simulation, its sensitivities, the outputs, the Gauss-Newton blocks.

One SX step function carries the state ``x`` and its sensitivities ``S = dx/d[theta, x0]`` (the exact
derivative of the discrete RK4 map, propagated through the step's Jacobian), resets them to the segment's
initial state (and ``S`` to ``[0, I]``) where a segment starts, and returns at every sample the model's
outputs ``h(x, u, theta)`` (the measured channels: a state, or any expression of the states, inputs and
coefficients) with their Jacobian ``dh/d[theta, x0] = dh/dx S + [dh/dtheta, 0]``. ``mapaccum`` repeats it
over chunks of samples; one MX wrapper is JIT-compiled into a C loop (:func:`symsbl._base.jit.jit_wrap`) and
called through ``Function.buffer()``.

The residuals and Jacobian rows of a chunk then go through the noise model's whitening filter (per
channel; identity for white noise) and the noise precisions, and the blocks ``J^T W J``, ``J^T W r`` and the
squared residuals are summed per segment with matrix products, each chunk's pieces of a segment at once:
one pass gives every block of the normal equations at any segment length.

A large structure (a step whose C source would exceed :data:`STAGED_SOURCE`) takes :func:`staged_step`
instead: the same derivative of the RK4 map, carried through the stages as matrix products of the
right-hand side's sparse Jacobians with ``S`` (an MX graph whose source grows with the model, not with
states times coefficients).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .._base.blas import one_blas_thread
from .._base.errors import SimulationError
from .._base.jit import MAX_AUTO_SOURCE, jit_lookup, jit_wrap
from .problem import Parameterisation, Records

__all__ = ["Passes", "Segments", "Blocks"]

#: Samples per compiled call (at most: see :func:`chunk_size`).
CHUNK = 4096
#: Carried values times samples of one call of the sensitivity pass at most. CasADi builds the ``mapaccum`` of a
#: call in a time that grows faster than the size of what it returns (measured on a 4844-value carried state, a
#: 4-state chain with 89 candidate coefficients: 9.1 s for 4096 samples, 0.5 s for 128, 0.04 s for 64).
MAP_VALUES = 2**18

#: ``jit="auto"`` compiles the passes for records of at least this many samples (or when the same
#: structure is fitted again). A fit takes 15-40 passes; on CasADi's virtual machine a pass costs 2-35 us a
#: sample (a Duffing oscillator to a 3-state Bouc-Wen model with its candidates), compiling 0.5-4 s: the
#: break-even is a few thousand samples (a 3 s Bouc-Wen record at 4096 Hz: 13 s uncompiled, 5.6 s with
#: compiling).
JIT_MIN_SAMPLES = 2**12


def chunk_size(n_carried: int) -> int:
    """Samples per call of a pass carrying ``n_carried`` values: :data:`CHUNK`, halved down to 64 until the call
    returns at most :data:`MAP_VALUES` values."""
    chunk = CHUNK
    while chunk > 64 and n_carried * chunk > MAP_VALUES:
        chunk //= 2
    return chunk


def _rk4(param: Parameterisation, x, theta, ud, dt, substeps: int):
    """RK4 over one sample interval in ``substeps`` steps; ``ud`` holds the inputs at the stage nodes."""
    nu = len(param.model.inputs)
    h = dt / substeps

    def u_at(node: int):
        return ud[node * nu : (node + 1) * nu] if nu else ca.SX(0, 1)

    xi = x
    for j in range(substeps):
        k1 = param.rhs(xi, u_at(2 * j), theta)
        k2 = param.rhs(xi + h / 2 * k1, u_at(2 * j + 1), theta)
        k3 = param.rhs(xi + h / 2 * k2, u_at(2 * j + 1), theta)
        k4 = param.rhs(xi + h * k3, u_at(2 * j + 2), theta)
        xi = xi + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return xi


def _symbols(param: Parameterisation, substeps: int):
    nx, nu, npar = len(param.model.states), len(param.model.inputs), param.n_free
    return dict(
        x=ca.SX.sym("x", nx),
        theta=ca.SX.sym("theta", npar),
        ud=ca.SX.sym("ud", nu * (2 * substeps + 1)),
        dt=ca.SX.sym("dt"),
        reset=ca.SX.sym("reset"),
        x_start=ca.SX.sym("x_start", nx),
        un=ca.SX.sym("un", nu),
    )


def sensitivity_step(
    param: Parameterisation, observe, n_outputs: int, substeps: int, columns=None
) -> tuple[ca.Function, dict]:
    """The step ``(z, ud, dt, theta, reset, x_start, un) -> (z_next, h, Jh)`` with ``z = [x, vec(S)]``.

    ``observe(x, u, theta)`` gives the ``n_outputs`` outputs (an SX column) at the state ``x`` and the input
    ``u`` of the sample; ``Jh`` is their Jacobian in ``[theta[columns], x0]``, column-major ``(n_outputs * ns,)``
    (``columns``: the coefficients differentiated, default all; ``theta`` is given whole)."""
    nx, ny = len(param.model.states), n_outputs
    cols = _columns(param, columns)
    npar = param.n_free if cols is None else len(cols)
    ns = npar + nx
    v = _symbols(param, substeps)
    S = ca.SX.sym("S", nx, ns)
    x_next = _rk4(param, v["x"], v["theta"], v["ud"], v["dt"], substeps)
    # S_next = dx_next/dx S + [dx_next/dtheta, 0]: the step's Jacobian (CasADi takes it in reverse mode, nx sweeps)
    # times S costs 2-10x fewer operations than pushing all ns directions through the step in forward mode
    # (measured: 325 against 596 for a Duffing oscillator, 11887 against 125406 for a 4-state chain with 89
    # candidate coefficients).
    jac = ca.jacobian(x_next, ca.vertcat(v["x"], _differentiated(v["theta"], cols)))
    S_next = jac[:, :nx] @ S + ca.horzcat(jac[:, nx:], ca.SX.zeros(nx, nx))
    z = ca.vertcat(v["x"], ca.vec(S))
    f = _reset_and_observe(z, v, v, x_next, S_next, observe, ny, {"cse": True}, cols)
    return f, dict(nx=nx, ns=ns, ny=ny, nz=nx + nx * ns, npar=npar)


def _columns(param: Parameterisation, columns) -> list[int] | None:
    """The coefficients a step differentiates: ``columns`` (indices into ``theta``), None for all."""
    if columns is None or list(columns) == list(range(param.n_free)):
        return None
    return [int(c) for c in columns]


def _differentiated(theta, cols: list[int] | None):
    """The part of the symbol ``theta`` a step differentiates (the symbol itself for all)."""
    return theta if cols is None else theta[cols]


def _reset_and_observe(
    z, args: dict, v: dict, x_next, S_next, observe, ny: int, opts: dict, cols: list[int] | None
) -> ca.Function:
    """The step ``(z, ud, dt, theta, reset, x_start, un) -> (z_next, h, Jh)`` of a step's ``x_next`` and
    ``S_next`` (SX or MX, in the symbols ``args``): reset where a segment starts, then observed. ``v``: the SX
    symbols of :func:`_symbols`, in which the outputs and their Jacobians are written; ``cols``: the coefficients
    ``S_next`` differentiates."""
    nx = x_next.shape[0]
    npar = S_next.shape[1] - nx
    kind = type(z)
    reset = args["reset"] > 0.5
    x1 = ca.if_else(reset, args["x_start"], x_next)
    S1 = ca.if_else(reset, kind(ca.horzcat(ca.DM.zeros(nx, npar), ca.DM.eye(nx))), S_next)
    xs = ca.SX.sym("xs", nx)
    h = observe(xs, v["un"], v["theta"])
    output = ca.Function(
        "output", [xs, v["un"], v["theta"]], [h, ca.jacobian(h, xs), ca.jacobian(h, _differentiated(v["theta"], cols))]
    )
    h1, hx, ht = output(x1, args["un"], args["theta"])
    Jh = ca.mtimes(hx, S1) + ca.horzcat(ht, kind.zeros(ny, nx))
    names = ["z", "ud", "dt", "theta", "reset", "x_start", "un"]
    return ca.Function(
        "sensitivity_step",
        [z, *(args[n] for n in names[1:])],
        [ca.vertcat(x1, ca.vec(S1)), h1, ca.vec(Jh)],
        names,
        ["z_next", "h", "Jh"],
        opts,
    )


def staged_step(
    param: Parameterisation, observe, n_outputs: int, substeps: int, columns=None
) -> tuple[ca.Function, dict]:
    """:func:`sensitivity_step` with ``S`` carried through the RK4 stages: ``K = f_x(x_i) S_i + [f_theta(x_i), 0]``
    at each stage state ``x_i`` (whose ``S_i`` the stage's update gives), ``S_next = S + h/6 (K1 + 2 K2 + 2 K3 +
    K4)`` per substep: the exact derivative of the same discrete map. The Jacobians are small SX functions
    called from an MX graph, whose products and sums CasADi writes as loops. ``columns``: see
    :func:`sensitivity_step`.

    The stages carry ``S`` transposed, ``K^T = S_i^T f_x^T + [f_theta, 0]^T``: CasADi's product of a dense
    matrix by a sparse one runs down the dense one's long columns (a coefficient each), where ``f_x S`` runs
    down ``f_x``'s few nonzeros per column (measured on a ten-mass chain's 187 sensitivities: 1.7-2.2 s a
    pass against 3.9 s, the same blocks)."""
    nx, ny = len(param.model.states), n_outputs
    cols = _columns(param, columns)
    npar = param.n_free if cols is None else len(cols)
    ns, nu = npar + nx, len(param.model.inputs)
    v = _symbols(param, substeps)
    xs, us = ca.SX.sym("xs", nx), ca.SX.sym("us", nu)
    f = param.rhs(xs, us, v["theta"])
    local = ca.Function(
        "rhs_jac",
        [xs, us, v["theta"]],
        [f, ca.jacobian(f, xs).T, ca.jacobian(f, _differentiated(v["theta"], cols)).T],
    )
    m = {k: ca.MX.sym(k, sym.shape[0]) for k, sym in v.items()}
    z = ca.MX.sym("z", nx + nx * ns)
    x, S = z[:nx], ca.reshape(z[nx:], nx, ns).T  # S transposed from here on
    h, pad = m["dt"] / substeps, ca.MX.zeros(nx, nx)

    def stage(xi, Si, node: int):
        k, fx_t, ft_t = local(xi, m["ud"][node * nu : (node + 1) * nu] if nu else ca.MX(0, 1), m["theta"])
        return k, ca.mtimes(Si, fx_t) + ca.vertcat(ft_t, pad)

    for j in range(substeps):
        k1, K1 = stage(x, S, 2 * j)
        k2, K2 = stage(x + h / 2 * k1, S + h / 2 * K1, 2 * j + 1)
        k3, K3 = stage(x + h / 2 * k2, S + h / 2 * K2, 2 * j + 1)
        k4, K4 = stage(x + h * k3, S + h * K3, 2 * j + 2)
        x, S = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), S + h / 6 * (K1 + 2 * K2 + 2 * K3 + K4)
    step = _reset_and_observe(z, m, v, x, S.T, observe, ny, {}, cols)
    return step, dict(nx=nx, ns=ns, ny=ny, nz=nx + nx * ns, npar=npar)


def state_step(param: Parameterisation, substeps: int) -> ca.Function:
    """The step ``(x, ud, dt, theta, reset, x_start) -> x_next`` of the simulation alone."""
    v = _symbols(param, substeps)
    x_next = _rk4(param, v["x"], v["theta"], v["ud"], v["dt"], substeps)
    out = ca.if_else(v["reset"] > 0.5, v["x_start"], x_next)
    return ca.Function(
        "state_step",
        [v["x"], v["ud"], v["dt"], v["theta"], v["reset"], v["x_start"]],
        [out],
        ["x", "ud", "dt", "theta", "reset", "x_start"],
        ["x_next"],
        {"cse": True},
    )


def _chunk(
    step: ca.Function, jit, n_samples: int, chunk: int = CHUNK, max_source: int = MAX_AUTO_SOURCE
) -> tuple[ca.Function, bool]:
    """``chunk`` steps of ``step`` (its first input and output carried, the other outputs returned at every
    step), ``theta`` (input 3) given once; compiled under ``jit="auto"`` up to ``max_source`` bytes of C. Returns
    the function and whether it is compiled."""
    key = (hashlib.sha1(step.serialize().encode()).hexdigest(), "oe_chunk", chunk)
    cached = jit_lookup(key) if jit is not False else _VM_CHUNKS.get(key)
    if cached is not None:
        return cached, jit is not False
    acc = step.mapaccum("steps", chunk)
    args = [
        ca.MX.sym(step.name_in(i), step.sparsity_in(i))
        if i in (0, 3)
        else ca.MX.sym(step.name_in(i), step.size1_in(i), chunk)
        for i in range(step.n_in())
    ]
    call = [args[0], args[1], args[2], ca.repmat(args[3], 1, chunk), *args[4:]]
    res = acc(*call)
    outs = list(res) if isinstance(res, (list, tuple)) else [res]
    wrapper = ca.Function(f"{step.name()}_chunk", args, outs, step.name_in(), step.name_out())
    if jit is False:  # building the map of a large step takes seconds: kept for the structure's next records
        _VM_CHUNKS[key] = wrapper
        while len(_VM_CHUNKS) > 16:
            _VM_CHUNKS.pop(next(iter(_VM_CHUNKS)))
        return wrapper, False
    lazy = jit == "auto" and n_samples < JIT_MIN_SAMPLES
    return jit_wrap(wrapper, "oe_chunk", jit, SimulationError, key=key, only_cached=lazy, max_source=max_source)


#: Largest C source of a fit's passes compiled under ``jit="auto"`` (bytes). A fit calls them thousands of times:
#: a 5-degree-of-freedom chain's 640 kB pass compiled in 17 s and its refinement took 52 s of CPU, against 227 s
#: on CasADi's virtual machine under the general bound (:data:`symsbl._base.jit.MAX_AUTO_SOURCE`); its selection's
#: pass with every candidate (74 coefficients, 1005 kB, before the selection's neighbourhoods) ran on the virtual
#: machine under a bound of 1 MB, 87 s of CPU for the identification against 49 s compiled. A model file's
#: structure, fitted once by ``validate``, keeps the general bound.
FIT_SOURCE = 2_000_000

#: Largest C source of a fit's pass written from :func:`sensitivity_step` (bytes, estimated as
#: :data:`SOURCE_PER_INSTRUCTION` per instruction of its step); a larger structure takes :func:`staged_step`.
#: A ten-mass chain's pass (20 states, 167 coefficients) was 6.5 MB: gcc needed 59 s and 4.3 GB at -O1, on the
#: virtual machine a pass took 12 s; its staged pass, 134 kB of C, compiled in 0.6 s and took 4.0 s.
STAGED_SOURCE = FIT_SOURCE
#: Bytes of C per instruction of a step as CasADi writes it (measured 22.8 and 23.6 on chains of 5 and 10 masses).
SOURCE_PER_INSTRUCTION = 24


def _step(param: Parameterisation, records: Records, columns, staged: bool | None) -> tuple[ca.Function, dict, bool]:
    """The step of a fit's passes, its layout and whether it is :func:`staged_step` (``staged`` None: when
    :func:`sensitivity_step`'s would exceed :data:`STAGED_SOURCE`)."""
    parts = (param, param.observe(records.outputs), records.n_outputs, records.substeps, columns)
    step = None
    if staged is None:
        step, layout = sensitivity_step(*parts)
        staged = step.n_instructions() * SOURCE_PER_INSTRUCTION > STAGED_SOURCE
    if staged:
        step, layout = staged_step(*parts)
    elif step is None:
        step, layout = sensitivity_step(*parts)
    return step, layout, bool(staged)


@dataclass
class Kernels:
    """The chunk functions of one structure's passes, which passes of a sub-structure may run (see
    :mod:`symsbl._refine.reuse`): the pass with sensitivities, and the plain simulation built when first asked for.
    They hold no record: the samples are their inputs."""

    param: Parameterisation
    outputs: tuple
    substeps: int
    layout: dict
    chunk: int
    sens: ca.Function
    compiled: bool
    jit: object
    n_samples: int
    max_source: int
    state: ca.Function | None = None

    def state_pass(self) -> ca.Function:
        """The plain simulation's chunk function (compiled as the pass's ``jit`` says)."""
        if self.state is None:
            step = state_step(self.param, self.substeps)
            self.state, _ = _chunk(step, self.jit, self.n_samples, max_source=self.max_source)
        return self.state


#: Uncompiled chunk functions of the structures used last, by the key of their step.
_VM_CHUNKS: dict = {}


@dataclass(frozen=True)
class Segments:
    """Where the segments of a fit start, and how a pass sums them: in pieces, a segment cut at chunk starts.

    Attributes
    ----------
    starts : ndarray of int, shape (n_segments,)
        First row of each segment.
    piece_starts : ndarray of int, shape (n_pieces,)
        First row of every piece (the segments' starts and the chunks' starts, merged).
    piece_segment : ndarray of int, shape (n_pieces,)
        The segment of each piece.
    chunk_pieces : ndarray of int, shape (n_chunks + 1,)
        The first piece of every chunk (and the number of pieces, last).
    ends : ndarray of int, shape (n_segments,)
        Last row of each segment.
    since : ndarray of int, shape (n_rows,)
        Samples since the start of the row's segment (0 at a segment's first sample).
    record_of_segment : ndarray of int, shape (n_segments,)
        The record each segment belongs to.
    """

    starts: np.ndarray
    piece_starts: np.ndarray
    piece_segment: np.ndarray
    chunk_pieces: np.ndarray
    ends: np.ndarray
    since: np.ndarray
    record_of_segment: np.ndarray

    def __len__(self) -> int:
        return len(self.starts)


@dataclass(frozen=True)
class Blocks:
    """The Gauss-Newton blocks of one pass, per segment.

    Attributes
    ----------
    H : ndarray, shape (n_segments, ns, ns)
        ``J^T W J`` (coefficients first, then the segment's initial state; ``ns = n_free + n_states``).
    g : ndarray, shape (n_segments, ns)
        ``J^T W r``.
    rr : ndarray, shape (n_segments, n_measured)
        The weighted squared residuals of each channel.
    end_S : ndarray, shape (n_segments, ns, n_states)
        The sensitivities (transposed) at each segment's last sample.
    n_kept : ndarray, shape (n_segments, n_measured)
        The samples each segment contributes per channel (measured, and with their noise model's lags).
    residual : ndarray, shape (n_total, n_measured), optional
        The raw residual ``y - h`` of every sample (unweighted, not whitened; not carried by :meth:`where`).
    """

    H: np.ndarray
    g: np.ndarray
    rr: np.ndarray
    end_S: np.ndarray
    n_kept: np.ndarray
    residual: np.ndarray | None = None

    @property
    def cost(self) -> float:
        """Half the weighted sum of squared residuals."""
        return float(0.5 * self.rr.sum())

    def where(self, mask: np.ndarray, other: Blocks) -> Blocks:
        """The blocks of ``other`` for the segments in ``mask``, these elsewhere."""

        def pick(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return np.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)

        return Blocks(
            pick(self.H, other.H),
            pick(self.g, other.g),
            pick(self.rr, other.rr),
            pick(self.end_S, other.end_S),
            pick(self.n_kept, other.n_kept),
        )


class Passes:
    """The records of a fit in the layout of the compiled passes, and the passes themselves.

    A pass is a function of the coefficients, the segments' initial states, the segmentation, the noise
    precisions and the noise model, all given to it; the arrays this object keeps besides the records are
    scratch space the compiled calls read."""

    chunk: int  # samples a compiled call steps through
    compiled: bool  # whether the passes run compiled C (else CasADi's virtual machine)

    def __init__(
        self,
        param: Parameterisation,
        records: Records,
        jit="auto",
        max_source: int = MAX_AUTO_SOURCE,
        columns=None,
        staged: bool | None = None,
        host: tuple[Kernels, np.ndarray] | None = None,
    ):
        """``columns``: the coefficients whose sensitivities the pass carries (indices into ``theta``, default all;
        the blocks of the others are zero); ``staged``: whether the step is :func:`staged_step` (default: when
        :func:`sensitivity_step`'s would exceed :data:`STAGED_SOURCE`); ``host``: the :class:`Kernels` of a structure
        holding this one, which run it with the other coefficients at zero, and where each of ``param``'s free
        coefficients sits among that structure's (see :mod:`symsbl._refine.reuse`)."""
        assert host is None or columns is None  # a hosted structure keeps its own coefficients' sensitivities
        self.param, self.records = param, records
        self.columns = _columns(param, columns)
        self._embed = None if host is None else host[1]
        if host is not None:
            self.kernels, self.staged = host[0], False
        else:
            step, layout, self.staged = _step(param, records, self.columns, staged)
            # divides CHUNK, the padding and the plain simulation's calls
            chunk = chunk_size(layout["nz"] + layout["ny"] * (1 + layout["ns"]))
            sens, compiled = _chunk(step, jit, records.n_total, chunk, max_source)
            kept = (records.outputs, records.substeps, layout, chunk, sens, compiled, jit, records.n_total)
            self.kernels = Kernels(param, *kept, max_source)
        self.layout, self.chunk, self.compiled = self.kernels.layout, self.kernels.chunk, self.kernels.compiled
        self._sens = self.kernels.sens
        n_host = self.kernels.param.n_free  # a hosted structure keeps its coefficients' and the states' sensitivities
        self._pick = None if host is None else np.concatenate([host[1], n_host + np.arange(self.layout["nx"])])
        lay = self.layout
        self.max_source = max_source
        self._sens_buffer = self._sens.buffer()  # creating a buffer costs milliseconds for a large step
        self.jit = jit
        n, C = records.n_total, CHUNK
        self.n_pad = -(-n // C) * C
        pad = self.n_pad - n
        self.UD = np.vstack([records.UD, np.zeros((pad, records.UD.shape[1]))])
        self.DT = np.concatenate([records.DT, np.zeros(pad)])
        self.UN = np.vstack([records.UN, np.zeros((pad, records.UN.shape[1]))])
        finite = np.isfinite(records.Y)
        self.Y = np.vstack([np.where(finite, records.Y, 0.0), np.zeros((pad, records.Y.shape[1]))])
        self.valid = np.vstack([finite, np.zeros((pad, records.Y.shape[1]), bool)])
        self._reset = np.zeros(self.n_pad)
        self._x_start = np.zeros((self.n_pad, lay["nx"]))
        self.n_obs = self.valid.sum(axis=0)
        self.row_record = np.concatenate([records.row_record, np.full(pad, len(records.lengths) - 1)])
        self._output_map: ca.Function | None = None  # compiled when simulated outputs are asked for
        # consecutive valid samples ending at each row, per channel (a whitening filter needs its lags valid)
        self.valid_runs = _runs(self.valid)

    # -- segments ------------------------------------------------------------------------------
    def segment_starts(self, length: int) -> np.ndarray:
        """Each record cut into ``round(n / length) >= 1`` segments of ``length`` samples (the last one longer)."""
        starts: list[int] = []
        for s, n in zip(self.records.starts, self.records.lengths):
            k = max(1, int(round(n / length)))
            starts.extend(int(s) + length * np.arange(k))
        return np.array(starts, dtype=np.int64)

    def segments(self, starts: np.ndarray) -> Segments:
        """The segmentation starting at rows ``starts`` (sorted, the first row of every record among them)."""
        n, C = self.records.n_total, self.chunk
        starts = np.asarray(starts, dtype=np.int64)
        pieces = np.union1d(starts, np.arange(0, n, C))
        ends = np.append(starts[1:], n) - 1
        rows = np.arange(n)
        since = rows - starts[np.searchsorted(starts, rows, side="right") - 1]
        return Segments(
            starts=starts,
            piece_starts=pieces,
            piece_segment=np.searchsorted(starts, pieces, side="right") - 1,
            chunk_pieces=np.searchsorted(pieces, np.arange(0, self.n_pad + 1, C)),
            ends=ends,
            since=since,
            record_of_segment=np.searchsorted(self.records.starts, starts, side="right") - 1,
        )

    def _load(self, seg: Segments, X0: np.ndarray) -> None:
        """Fill the scratch arrays the compiled calls read: reset flags and initial states."""
        self._reset[:] = 0.0
        self._reset[seg.starts] = 1.0
        self._x_start[seg.starts] = X0

    # -- passes --------------------------------------------------------------------------------
    def sensitivities(
        self,
        theta: np.ndarray,
        X0: np.ndarray,
        seg: Segments,
        w: np.ndarray,
        ar: np.ndarray | None = None,
        stop=None,
        rows: tuple[int, int] | None = None,
    ) -> Blocks:
        """The Gauss-Newton blocks of every segment of ``seg``.

        Parameters
        ----------
        theta : ndarray, shape (n_free,)
        X0 : ndarray, shape (n_segments, n_states)
            The segments' initial states.
        seg : Segments
        w : ndarray, shape (n_records, n_outputs) or (n_outputs,)
            Noise precisions of the channels in each record (of their innovations, with a noise model); one row
            serves every record.
        ar : ndarray, shape (n_outputs, p), optional
            Autoregressive noise model of each channel: the residual ``r`` is whitened to
            ``e_t = r_t + sum_i ar[c, i-1] r_{t-i}`` and so is each Jacobian row; the first ``p`` samples of a
            segment (and samples whose lags are not all measured) are left out (the conditional likelihood).
            None or ``p = 0``: white noise.
        stop : callable, optional
            ``stop(cost)`` of the cost summed so far (half the weighted squared residuals, which only grow from
            chunk to chunk): when true, the pass ends there and its blocks carry an infinite cost (a trial step
            already refused, whatever the rest of the record holds).
        rows : (int, int), optional
            Only the rows ``[lo, hi)`` are simulated and counted, ``lo`` a segment's start (a window of a long
            record: the chunks that hold it). The blocks and end sensitivities of the segments outside it are
            zero, the residual NaN outside it.
        """
        lay, C = self.layout, self.chunk
        nx, ny = lay["nx"], lay["ny"]
        theta, keep = self._hosted(theta)
        ns = lay["ns"] if keep is None else len(keep)
        ar = np.zeros((ny, 0)) if ar is None else np.asarray(ar, dtype=float).reshape(ny, -1)
        self._load(seg, X0)
        sw = np.sqrt(self.per_record(w))
        buf, call = self._sens_buffer
        z0 = np.zeros(lay["nz"])
        zout = np.empty((C, lay["nz"]))
        hout = np.empty((C, ny))
        jout = np.empty((C, ny * lay["ns"]))
        K = len(seg)
        H = np.zeros((K, ns, ns))
        g = np.zeros((K, ns))
        rr = np.zeros((K, ny))
        kept = np.zeros((K, ny))
        residual = np.empty((self.records.n_total, ny)) if rows is None else np.full((self.records.n_total, ny), np.nan)
        assert rows is None or np.any(seg.starts == rows[0])  # the window starts where a segment does
        end_S = np.zeros((K, ns, nx))
        buf.set_arg(3, _view(theta))  # type: ignore[call-arg]
        buf.set_res(0, _view(zout))  # type: ignore[call-arg]
        buf.set_res(1, _view(hout))  # type: ignore[call-arg]
        buf.set_res(2, _view(jout))  # type: ignore[call-arg]
        with one_blas_thread():
            done = self._chunks(
                buf, call, seg, ar, sw, z0, (zout, hout, jout), (H, g, rr, end_S, kept), residual, stop, rows, keep
            )
        if not done:
            rr[:] = np.inf
        return self._whole(Blocks(H, g, rr, end_S, kept, residual))

    def _hosted(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The coefficients the compiled passes take (a host's: ``theta`` where this structure has them, zero
        elsewhere) and the sensitivities this structure keeps of theirs (None: all)."""
        theta = np.asarray(theta, dtype=float)
        if self._embed is None:
            return np.ascontiguousarray(theta), None
        full = np.zeros(self.kernels.param.n_free)
        full[self._embed] = theta
        return full, self._pick

    def _whole(self, blocks: Blocks) -> Blocks:
        """``blocks`` of this pass's columns in the layout of every coefficient (zero where it carries none)."""
        if self.columns is None:
            return blocks
        npar, nx = self.param.n_free, self.layout["nx"]
        idx = np.concatenate([self.columns, npar + np.arange(nx)])
        K, ns = len(blocks.H), npar + nx
        H, g, end_S = np.zeros((K, ns, ns)), np.zeros((K, ns)), np.zeros((K, ns, nx))
        H[:, idx[:, None], idx[None, :]] = blocks.H
        g[:, idx] = blocks.g
        end_S[:, idx] = blocks.end_S
        return Blocks(H, g, blocks.rr, end_S, blocks.n_kept, blocks.residual)

    @np.errstate(over="ignore", invalid="ignore")  # a simulation that runs away gives non-finite blocks, refused later
    def _chunks(self, buf, call, seg: Segments, ar, sw, z0, outs, sums, residual, stop=None, rows=None, pick=None):
        """The compiled calls of one pass, chunk by chunk, each chunk's rows whitened and summed into the blocks;
        False when ``stop`` ended the pass early. ``rows``: see :meth:`sensitivities`; ``pick``: the sensitivities
        summed, indices among the step's (None: every one)."""
        lay, C = self.layout, self.chunk
        nx, ny, every = lay["nx"], lay["ny"], lay["ns"]
        ns = every if pick is None else len(pick)
        zout, hout, jout = outs
        H, g, rr, end_S, kept = sums
        order = ar.shape[1]
        lag_r = np.zeros((order, ny))
        lag_j = np.zeros((order, ny, ns))
        lo, hi = (0, self.n_pad) if rows is None else (int(rows[0]), int(rows[1]))
        for a in range(lo - lo % C, min(hi, self.n_pad), C):
            c = a // C
            buf.set_arg(0, _view(z0))
            for i, arr in ((1, self.UD), (2, self.DT), (4, self._reset), (5, self._x_start), (6, self.UN)):
                buf.set_arg(i, _view(arr[a : a + C]))
            call()
            z0[:] = zout[-1]
            n = min(C, self.records.n_total - a)
            if n <= 0:
                break
            R = self.Y[a : a + n] - hout[:n]  # (n, ny)
            J = jout[:n].reshape(n, every, ny)
            J = (J if pick is None else J[:, pick]).transpose(0, 2, 1)  # (n, ny, ns)
            keep = self.valid[a : a + n]
            if rows is not None:  # the rows before the window were simulated from no state: they do not count
                at = np.arange(a, a + n)
                inside = (at >= lo) & (at < hi)
                keep = keep & inside[:, None]
                R, J = np.where(inside[:, None], R, 0.0), np.where(inside[:, None, None], J, 0.0)
            residual[a : a + n] = np.where(keep, R, np.nan)
            E, EJ = R, J
            if order:
                R_ext = np.concatenate([lag_r, R])
                J_ext = np.concatenate([lag_j, J])
                E = R.copy()
                EJ = J.copy()
                for i in range(1, order + 1):
                    E += ar[:, i - 1] * R_ext[order - i : order - i + n]
                    EJ += ar[:, i - 1][None, :, None] * J_ext[order - i : order - i + n]
                keep = keep & (seg.since[a : a + n, None] >= order) & (self.valid_runs[a : a + n] > order)
                lag_r, lag_j = R_ext[-order:], J_ext[-order:]
            weight = sw[self.row_record[a : a + n]] * keep  # (n, ny)
            E = E * weight
            EJ = EJ * weight[:, :, None]
            p0, p1 = seg.chunk_pieces[c], seg.chunk_pieces[c + 1]
            _accumulate(H, g, rr, seg.piece_starts[p0:p1] - a, seg.piece_segment[p0:p1], n, E, EJ)
            np.add.at(kept, seg.piece_segment[p0:p1], np.add.reduceat(keep, seg.piece_starts[p0:p1] - a, axis=0))
            last = seg.ends[(seg.ends >= max(a, lo)) & (seg.ends < min(a + n, hi))]
            if last.size:
                ends = zout[last - a, nx:].reshape(-1, every, nx)
                end_S[np.searchsorted(seg.ends, last)] = ends if pick is None else ends[:, pick]
            if stop is not None and stop(0.5 * rr.sum()):
                return False
        return True

    def per_record(self, w) -> np.ndarray:
        """Noise precisions as ``(n_records, n_outputs)``: a row given once serves every record."""
        w = np.asarray(w, dtype=float)
        n_records = len(self.records.lengths)
        return np.broadcast_to(w, (n_records, self.layout["ny"])) if w.ndim == 1 else w.reshape(n_records, -1)

    def segment_rows(self, values: np.ndarray, seg: Segments) -> np.ndarray:
        """Per-segment values ``(n_segments, ...)`` summed per record ``(n_records, ...)``."""
        out = np.zeros((len(self.records.lengths),) + values.shape[1:])
        np.add.at(out, seg.record_of_segment, values)
        return out

    def outputs(self, theta: np.ndarray, X0: np.ndarray, seg: Segments) -> np.ndarray:
        """The simulated channels of every sample ``(n_total, n_outputs)`` (what ``Y`` measures) from the segments'
        initial states."""
        return self.observed(self.simulate(theta, X0, seg), theta)

    def observed(self, X: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """The channels ``Y`` measures ``(n_total, n_outputs)`` of the simulated states ``X`` ``(n_total, nx)``."""
        index = self.records.state_index
        if index is not None:
            return X[:, list(index)]
        n = self.records.n_total
        if self._output_map is None:
            lay = self.layout
            x, u = ca.SX.sym("x", lay["nx"]), ca.SX.sym("u", self.UN.shape[1])
            th = ca.SX.sym("theta", self.param.n_free)
            h = ca.Function("outputs", [x, u, th], [self.param.observe(self.records.outputs)(x, u, th)])
            self._output_map = h.map(CHUNK)
        out = np.empty((self.n_pad, self.layout["ny"]))
        theta = np.repeat(np.asarray(theta, dtype=float)[:, None], CHUNK, axis=1)
        Xp = np.vstack([X, np.zeros((self.n_pad - n, X.shape[1]))])
        with np.errstate(all="ignore"):
            for a in range(0, self.n_pad, CHUNK):
                out[a : a + CHUNK] = np.asarray(
                    self._output_map(Xp[a : a + CHUNK].T, self.UN[a : a + CHUNK].T, theta)
                ).T
        return out[:n]

    def simulate(self, theta: np.ndarray, X0: np.ndarray, seg: Segments) -> np.ndarray:
        """The simulated states of every sample ``(n_total, nx)`` from the segments' initial states."""
        nx, C = self.layout["nx"], CHUNK
        self._load(seg, X0)
        theta, _ = self._hosted(theta)
        out = np.empty((self.n_pad, nx))
        buf, call = self.kernels.state_pass().buffer()
        x0 = np.zeros(nx)
        buf.set_arg(3, _view(theta))  # type: ignore[call-arg]
        for a in range(0, self.n_pad, C):
            buf.set_arg(0, _view(x0))  # type: ignore[call-arg]
            for i, arr in ((1, self.UD), (2, self.DT), (4, self._reset), (5, self._x_start)):
                buf.set_arg(i, _view(arr[a : a + C]))  # type: ignore[call-arg]
            buf.set_res(0, _view(out[a : a + C]))  # type: ignore[call-arg]
            call()
            x0 = out[a + C - 1].copy()
        return out[: self.records.n_total]


def _view(a: np.ndarray) -> memoryview:
    """``a``'s memory, which a CasADi ``FunctionBuffer`` reads or writes in place (CasADi's stubs list the C++
    ``size`` argument of ``set_arg``/``set_res`` that the Python binding takes from this buffer)."""
    return memoryview(a)  # type: ignore[arg-type]  # numpy's stubs give ndarray no __buffer__ before Python 3.12


def _runs(valid: np.ndarray) -> np.ndarray:
    """Per channel, the number of consecutive valid samples ending at each row (0 where invalid)."""
    out = np.zeros(valid.shape, dtype=np.int64)
    for c in range(valid.shape[1]):
        v = valid[:, c].astype(np.int64)
        total = np.cumsum(v)
        last_reset = np.maximum.accumulate(np.where(v == 0, total, 0))
        out[:, c] = total - last_reset
    return out


#: Rows times (coefficients squared) of one block product at most (memory of the padded pieces: 2^22 doubles).
_PRODUCT = 2**22


def _accumulate(H, g, rr, piece_starts, piece_segment, n: int, E: np.ndarray, EJ: np.ndarray) -> None:
    """Add one chunk's whitened, weighted residuals ``E`` ``(n, ny)`` and Jacobian rows ``EJ`` ``(n, ny, ns)`` to
    the blocks of the segments its pieces belong to (pieces start at the chunk offsets ``piece_starts``)."""
    ny, ns = EJ.shape[1], EJ.shape[2]
    lengths = np.diff(np.append(piece_starts, n))
    rr_chunk = np.add.reduceat(E * E, piece_starts, axis=0)
    np.add.at(rr, piece_segment, rr_chunk)
    if len(piece_starts) == 1 or lengths.max() * len(piece_starts) * ns * ns * ny > _PRODUCT:
        for p0, length, k in zip(piece_starts, lengths, piece_segment):
            A: np.ndarray = EJ[p0 : p0 + length].reshape(-1, ns)
            H[k] += A.T @ A
            g[k] += A.T @ E[p0 : p0 + length].reshape(-1)
        return
    # many short pieces: pad them to one length and multiply them in one batched product
    L = int(lengths.max())
    piece = np.repeat(np.arange(len(piece_starts)), lengths)
    offset = np.arange(n) - np.repeat(piece_starts, lengths)
    A = np.zeros((len(piece_starts), L, ny, ns))
    A[piece, offset] = EJ
    b: np.ndarray = np.zeros((len(piece_starts), L, ny))
    b[piece, offset] = E
    A = A.reshape(len(piece_starts), L * ny, ns)
    b = b.reshape(len(piece_starts), L * ny)
    At = A.transpose(0, 2, 1)
    np.add.at(H, piece_segment, At @ A)
    np.add.at(g, piece_segment, (At @ b[:, :, None])[:, :, 0])
