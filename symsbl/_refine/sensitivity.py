"""One compiled pass over the records: the simulation, its sensitivities and the Gauss-Newton blocks.

One SX step function carries the state ``x``, its sensitivities ``S = dx/d[theta, x0]`` (the exact
derivative of the discrete RK4 map, propagated through the step's Jacobian) and running sums of the
Gauss-Newton blocks ``J^T W J`` (upper triangle), ``J^T W r`` and the weighted squared residual of every
measured channel. It resets the state to the segment's initial state (and ``S`` to ``[0, I]``) where a
segment starts. ``mapaccum`` repeats it over chunks of samples; one MX wrapper is JIT-compiled into
a C loop (:func:`symsbl._base.jit.jit_wrap`) and called through ``Function.buffer()``. The
accumulators restart every chunk (bounded round-off) and per-segment totals are gathered where
each piece of a segment ends: one pass gives every block of the normal equations at any segment
length, with no Python loop over segments or samples.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .._base.errors import SimulationError
from .._base.jit import jit_lookup, jit_wrap
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
        return ud[node * nu:(node + 1) * nu] if nu else ca.SX(0, 1)

    xi = x
    for j in range(substeps):
        k1 = param.rhs(xi, u_at(2 * j), theta)
        k2 = param.rhs(xi + h / 2 * k1, u_at(2 * j + 1), theta)
        k3 = param.rhs(xi + h / 2 * k2, u_at(2 * j + 1), theta)
        k4 = param.rhs(xi + h * k3, u_at(2 * j + 2), theta)
        xi = xi + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return xi


def _symbols(param: Parameterisation, substeps: int, n_measured: int):
    nx, nu, npar = len(param.model.states), len(param.model.inputs), param.n_free
    return dict(x=ca.SX.sym("x", nx), theta=ca.SX.sym("theta", npar), ud=ca.SX.sym("ud", nu * (2 * substeps + 1)),
                dt=ca.SX.sym("dt"), reset=ca.SX.sym("reset"), x_start=ca.SX.sym("x_start", nx),
                y=ca.SX.sym("y", n_measured), sw=ca.SX.sym("sw", n_measured))


def sensitivity_step(param: Parameterisation, measured, substeps: int) -> tuple[ca.Function, dict]:
    """The step ``(z, ud, dt, theta, reset, x_start, y, sw) -> z_next`` with ``z = [x, vec(S), sums]``."""
    nx, npar, ny = len(param.model.states), param.n_free, len(measured)
    ns = npar + nx
    ntri = ns * (ns + 1) // 2
    nsum = ntri + ns + ny
    v = _symbols(param, substeps, ny)
    S = ca.SX.sym("S", nx, ns)
    sums = ca.SX.sym("sums", nsum)
    x_next = _rk4(param, v["x"], v["theta"], v["ud"], v["dt"], substeps)
    # S_next = dx_next/dx S + [dx_next/dtheta, 0]: the step's Jacobian (CasADi takes it in reverse mode, nx sweeps)
    # times S costs 2-10x fewer operations than pushing all ns directions through the step in forward mode
    # (measured: 325 against 596 for a Duffing oscillator, 11887 against 125406 for a 4-state chain with 89
    # candidate coefficients).
    jac = ca.jacobian(x_next, ca.vertcat(v["x"], v["theta"]))
    S_next = jac[:, :nx] @ S + ca.horzcat(jac[:, nx:], ca.SX.zeros(nx, nx))
    reset = v["reset"] > 0.5
    x1 = ca.if_else(reset, v["x_start"], x_next)
    S1 = ca.if_else(reset, ca.SX(ca.horzcat(ca.DM.zeros(nx, npar), ca.DM.eye(nx))), S_next)
    previous = ca.if_else(reset, ca.SX.zeros(nsum), sums)
    r = v["sw"] * (v["y"] - x1[list(measured)])
    J = ca.diag(v["sw"]) @ S1[list(measured), :]
    JtJ = J.T @ J
    iu, ju = np.triu_indices(ns)
    tri = ca.vertcat(*[JtJ[int(a), int(b)] for a, b in zip(iu, ju)])
    z = ca.vertcat(v["x"], ca.vec(S), sums)
    z_next = ca.vertcat(x1, ca.vec(S1), previous + ca.vertcat(tri, J.T @ r, r * r))
    names = ["z", "ud", "dt", "theta", "reset", "x_start", "y", "sw"]
    f = ca.Function("sensitivity_step", [z, v["ud"], v["dt"], v["theta"], v["reset"], v["x_start"], v["y"], v["sw"]],
                    [z_next], names, ["z_next"], {"cse": True})
    return f, dict(nx=nx, ns=ns, ny=ny, ntri=ntri, nsum=nsum, nz=nx + nx * ns + nsum, npar=npar)


def state_step(param: Parameterisation, substeps: int) -> ca.Function:
    """The step ``(x, ud, dt, theta, reset, x_start) -> x_next`` of the simulation alone."""
    v = _symbols(param, substeps, 0)
    x_next = _rk4(param, v["x"], v["theta"], v["ud"], v["dt"], substeps)
    out = ca.if_else(v["reset"] > 0.5, v["x_start"], x_next)
    return ca.Function("state_step", [v["x"], v["ud"], v["dt"], v["theta"], v["reset"], v["x_start"]], [out],
                       ["x", "ud", "dt", "theta", "reset", "x_start"], ["x_next"], {"cse": True})


def _chunk(step: ca.Function, jit, n_samples: int, chunk: int = CHUNK) -> ca.Function:
    """``chunk`` steps of ``step`` (its first input carried), ``theta`` (input 3) given once."""
    key = (hashlib.sha1(step.serialize().encode()).hexdigest(), "oe_chunk", chunk)
    cached = jit_lookup(key) if jit is not False else _VM_CHUNKS.get(key)
    if cached is not None:
        return cached
    acc = step.mapaccum("steps", chunk)
    args = [ca.MX.sym(step.name_in(i), step.sparsity_in(i)) if i in (0, 3)
            else ca.MX.sym(step.name_in(i), step.size1_in(i), chunk) for i in range(step.n_in())]
    call = [args[0], args[1], args[2], ca.repmat(args[3], 1, chunk), *args[4:]]
    wrapper = ca.Function(f"{step.name()}_chunk", args, [acc(*call)], step.name_in(), step.name_out())
    if jit is False:  # building the map of a large step takes seconds: kept for the structure's next records
        _VM_CHUNKS[key] = wrapper
        while len(_VM_CHUNKS) > 16:
            _VM_CHUNKS.pop(next(iter(_VM_CHUNKS)))
        return wrapper
    lazy = jit == "auto" and n_samples < JIT_MIN_SAMPLES
    fn, _ = jit_wrap(wrapper, "oe_chunk", jit, SimulationError, key=key, only_cached=lazy)
    return fn


#: Uncompiled chunk functions of the structures used last, by the key of their step.
_VM_CHUNKS: dict = {}


@dataclass(frozen=True)
class Segments:
    """Where the segments of a fit start, and the bookkeeping of the pieces a pass sums them in.

    A segment is cut into pieces at every chunk start; the pass returns the running sums at each piece's
    last sample, and the sums of a segment are those of its pieces.

    Attributes
    ----------
    starts : ndarray of int, shape (n_segments,)
        First row of each segment.
    piece_ends : ndarray of int
        Last row of every piece.
    piece_first : ndarray of int, shape (n_segments,)
        Each segment's first piece.
    chunk_pieces : ndarray of int
        The first piece of every chunk (and the number of pieces, last).
    segment_end_pieces : ndarray of int, shape (n_segments,)
        Each segment's last piece.
    record_of_segment : ndarray of int, shape (n_segments,)
        The record each segment belongs to.
    """

    starts: np.ndarray
    piece_ends: np.ndarray
    piece_first: np.ndarray
    chunk_pieces: np.ndarray
    segment_end_pieces: np.ndarray
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
    """

    H: np.ndarray
    g: np.ndarray
    rr: np.ndarray
    end_S: np.ndarray

    @property
    def cost(self) -> float:
        """Half the weighted sum of squared residuals."""
        return float(0.5 * self.rr.sum())

    def where(self, mask: np.ndarray, other: Blocks) -> Blocks:
        """The blocks of ``other`` for the segments in ``mask``, these elsewhere."""
        pick = lambda a, b: np.where(mask.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)  # noqa: E731
        return Blocks(pick(self.H, other.H), pick(self.g, other.g), pick(self.rr, other.rr),
                      pick(self.end_S, other.end_S))


class Passes:
    """The records of a fit in the layout of the compiled passes, and the passes themselves.

    A pass is a function of the coefficients, the segments' initial states, the segmentation and the noise
    precisions, all given to it; the arrays this object keeps besides the records are scratch space the
    compiled calls read."""

    def __init__(self, param: Parameterisation, records: Records, jit="auto"):
        self.param, self.records = param, records
        step, self.layout = sensitivity_step(param, records.measured, records.substeps)
        self.chunk = chunk_size(self.layout["nz"])  # divides CHUNK, the padding and the plain simulation's calls
        self._sens = _chunk(step, jit, records.n_total, self.chunk)
        self._sens_buffer = self._sens.buffer()  # creating a buffer costs milliseconds for a large step
        self._state = None  # compiled when a plain simulation is asked for
        self.jit = jit
        n, C = records.n_total, CHUNK
        self.n_pad = -(-n // C) * C
        pad = self.n_pad - n
        self.UD = np.vstack([records.UD, np.zeros((pad, records.UD.shape[1]))])
        self.DT = np.concatenate([records.DT, np.zeros(pad)])
        finite = np.isfinite(records.Y)
        self.Y = np.vstack([np.where(finite, records.Y, 0.0), np.zeros((pad, records.Y.shape[1]))])
        self.valid = np.vstack([finite, np.zeros((pad, records.Y.shape[1]), bool)])
        self._reset = np.zeros(self.n_pad)
        self._x_start = np.zeros((self.n_pad, self.layout["nx"]))
        self._sw = np.zeros((self.n_pad, records.Y.shape[1]))
        self.n_obs = self.valid.sum(axis=0)

    # -- segments ------------------------------------------------------------------------------
    def segment_starts(self, length: int) -> np.ndarray:
        """Each record cut into ``round(n / length) >= 1`` segments of ``length`` samples (the last one longer)."""
        starts = []
        for s, n in zip(self.records.starts, self.records.lengths):
            k = max(1, int(round(n / length)))
            starts.extend(int(s) + length * np.arange(k))
        return np.array(starts, dtype=np.int64)

    def segments(self, starts: np.ndarray) -> Segments:
        """The segmentation starting at rows ``starts`` (sorted, the first row of every record among them)."""
        n, C = self.records.n_total, self.chunk
        starts = np.asarray(starts, dtype=np.int64)
        cuts = np.union1d(starts, np.arange(0, n, C))
        ends = np.append(cuts[1:], n) - 1
        segment_of_piece = np.searchsorted(starts, ends, side="right") - 1
        return Segments(starts=starts, piece_ends=ends,
                        piece_first=np.searchsorted(segment_of_piece, np.arange(len(starts))),
                        chunk_pieces=np.searchsorted(ends, np.arange(0, self.n_pad + 1, C)),
                        segment_end_pieces=np.searchsorted(ends, np.append(starts[1:], n) - 1),
                        record_of_segment=np.searchsorted(self.records.starts, starts, side="right") - 1)

    def _load(self, seg: Segments, X0: np.ndarray, w: np.ndarray | None = None) -> None:
        """Fill the scratch arrays the compiled calls read: reset flags, initial states, weights."""
        self._reset[:] = 0.0
        self._reset[seg.starts] = 1.0
        self._x_start[seg.starts] = X0
        if w is not None:
            self._sw[:] = np.sqrt(np.asarray(w, dtype=float))[None, :] * self.valid

    # -- passes --------------------------------------------------------------------------------
    def sensitivities(self, theta: np.ndarray, X0: np.ndarray, seg: Segments, w: np.ndarray) -> Blocks:
        """The Gauss-Newton blocks of every segment of ``seg`` at coefficients ``theta``, initial states ``X0``
        ``(n_segments, n_states)`` and noise precisions ``w`` ``(n_measured,)``."""
        lay, C = self.layout, self.chunk
        nx, ns, ntri = lay["nx"], lay["ns"], lay["ntri"]
        self._load(seg, X0, w)
        theta = np.ascontiguousarray(theta, dtype=float)
        buf, call = self._sens_buffer
        z0 = np.zeros(lay["nz"])
        zout = np.empty((C, lay["nz"]))
        pieces = np.empty((len(seg.piece_ends), lay["nz"]))
        buf.set_arg(3, memoryview(theta))
        buf.set_res(0, memoryview(zout))
        for c, a in enumerate(range(0, self.n_pad, C)):
            z0[nx + nx * ns:] = 0.0  # the sums restart every chunk
            buf.set_arg(0, memoryview(z0))
            for i, arr in ((1, self.UD), (2, self.DT), (4, self._reset), (5, self._x_start), (6, self.Y),
                           (7, self._sw)):
                buf.set_arg(i, memoryview(arr[a:a + C]))
            call()
            p0, p1 = seg.chunk_pieces[c], seg.chunk_pieces[c + 1]
            if p1 > p0:
                pieces[p0:p1] = zout[seg.piece_ends[p0:p1] - a]
            z0[:] = zout[-1]
        sums = np.add.reduceat(pieces[:, nx + nx * ns:], seg.piece_first, axis=0)
        K = len(seg)
        H = np.empty((K, ns, ns))
        iu, ju = np.triu_indices(ns)
        H[:, iu, ju] = sums[:, :ntri]
        H[:, ju, iu] = sums[:, :ntri]
        end_S = pieces[seg.segment_end_pieces, nx:nx + nx * ns].reshape(K, ns, nx)
        return Blocks(H, sums[:, ntri:ntri + ns], sums[:, ntri + ns:], end_S)

    def simulate(self, theta: np.ndarray, X0: np.ndarray, seg: Segments) -> np.ndarray:
        """The simulated states of every sample ``(n_total, nx)`` from the segments' initial states."""
        nx, C = self.layout["nx"], CHUNK
        self._load(seg, X0)
        theta = np.ascontiguousarray(theta, dtype=float)
        out = np.empty((self.n_pad, nx))
        if self._state is None:
            self._state = _chunk(state_step(self.param, self.records.substeps), self.jit, self.records.n_total)
        buf, call = self._state.buffer()
        x0 = np.zeros(nx)
        buf.set_arg(3, memoryview(theta))
        for a in range(0, self.n_pad, C):
            buf.set_arg(0, memoryview(x0))
            for i, arr in ((1, self.UD), (2, self.DT), (4, self._reset), (5, self._x_start)):
                buf.set_arg(i, memoryview(arr[a:a + C]))
            buf.set_res(0, memoryview(out[a:a + C]))
            call()
            x0 = out[a + C - 1].copy()
        return out[:self.records.n_total]
