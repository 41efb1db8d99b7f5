"""SUNDIALS CVODES (BDF, error-controlled) through ``ca.integrator``, for continuous right-hand sides.

Analytic inputs enter as expressions of the time symbol (``dae["t"] + t_offset``), sampled inputs as a
linear ``ca.interpolant`` of time, so the solver sees the input between samples exactly. Long grids are
integrated in segments of :data:`CVODES_SEGMENT` samples (the state carried across, ``t_offset`` the
segment's start), so that a long run can report its progress.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .._base.casadi import interrupts_kept
from .._base.errors import SimulationError, expected
from .._base.progress import Progress

__all__ = ["run_cvodes", "CVODES_SEGMENT"]


#: CVODES integrates long grids in segments of this many sample intervals (the state carried
#: across), so that a long run reports its progress; each segment restarts the solver, which
#: costs a few small steps (measured on Duffing at 32768 Hz: +1 % run time, changes below rtol).
CVODES_SEGMENT = 2**16


def run_cvodes(system, t, signals, x0, *, rtol, atol, substeps, chunk_size, jit, options):
    """Integrate with CVODES; return ``(states (n, nx) with NaN after a failure, failure time or None, reason)``."""
    x = ca.vertcat(*system.states)
    ts, offset = ca.SX.sym("t"), ca.SX.sym("t_offset")
    u = ca.vertcat(*[s.expr(ts + offset) for s in signals]) if signals else ca.SX(0, 1)
    ode = system.rhs_function()(x, u)
    opts = {"reltol": rtol, "abstol": atol, "disable_internal_warnings": True}
    opts.update(options or {})
    dae = {"x": x, "p": offset, "t": ts, "ode": ode}
    out = np.full((t.size, system.n_states), np.nan)
    out[0] = x0
    # The integrator of the previous segment is reused when its relative output grid is this
    # segment's: a uniform grid builds one (two with a shorter last segment), a measured grid
    # with jitter one per segment.
    solver = None
    tol = 1e-9 * float(np.min(np.diff(t)))
    with Progress(f"simulate {system.name} (cvodes)", total=t.size - 1, unit="steps") as bar:
        for a in range(0, t.size - 1, CVODES_SEGMENT):
            b = min(a + CVODES_SEGMENT, t.size - 1)
            grid = t[a + 1 : b + 1] - t[a]
            if solver is None or solver[0].size != grid.size or not np.allclose(solver[0], grid, rtol=0, atol=tol):
                try:
                    F = ca.integrator("simulate", "cvodes", dae, 0.0, grid, opts)
                except RuntimeError as err:
                    raise SimulationError(
                        expected(
                            "method",
                            "a cvodes integrator that can be built",
                            str(err).strip().splitlines()[-1][:120],
                            "try method='rk4'",
                            raw=True,
                        )
                    ) from None
                solver = (grid, *F.buffer(), F.index_in("p"))
            _, buf, trigger, i_p = solver
            start, shift = np.array(out[a]), np.array([t[a]])
            buf.set_arg(0, memoryview(start))
            buf.set_arg(i_p, memoryview(shift))
            buf.set_res(0, memoryview(out[a + 1 : b + 1]))
            try:
                with interrupts_kept():  # a Ctrl-C inside CVODES comes back as CV_RHSFUNC_FAIL otherwise
                    trigger()
            except RuntimeError as err:
                reason = str(err).strip().splitlines()[-1].split(": ", 1)[-1]
                done = np.flatnonzero(np.all(np.isfinite(out), axis=1))
                t_last = t[done[-1]] if done.size else t[0]
                t_fail = buf.stats().get("tcur", np.nan)  # where CVODES stopped (segment time), if it says
                t_fail = float(t_fail) + t[a] if np.isfinite(t_fail) else -np.inf
                return out, (t_fail if t_fail > t_last else float(t_last)), f"cvodes failed: {reason}"
            bar.update(b - a)
    return out, None, ""
