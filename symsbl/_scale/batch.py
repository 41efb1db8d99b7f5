"""Fit many independent records (a batch of experiments) in one call.

Each record is identified on its own, exactly as :func:`symsbl.identify` (or
:func:`symsbl.identify_stream` for a chunked record) would, and the records are spread
over ``n_jobs`` threads that share one compiled dictionary. The dictionary evaluation, numpy's
reductions and BLAS release the GIL; the RVM's sequential updates and the support search are
Python code that holds it. Threads therefore help when building the statistics dominates
(long records, large libraries) and little when the fit does (short records: about 90 % of a
1 s Duffing fit at degree 3). ``bench/bench_scale.py`` measures the ratio against a loop.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

from .._base.checks import integer
from .._base.errors import DataError, expected
from .._identify import identify
from .._model import IdentifiedModel
from .._symbolic.library import Library
from .records import ChunkedRecord
from .stream import identify_stream

__all__ = ["identify_many"]


def _one(data, library: Library, kwargs: dict) -> IdentifiedModel:
    chunked = isinstance(data, ChunkedRecord) or (
        isinstance(data, (list, tuple)) and bool(data) and any(isinstance(d, ChunkedRecord) for d in data)
    )
    return (identify_stream if chunked else identify)(data, library, **kwargs)


def identify_many(datasets: Sequence, library: Library, *, n_jobs: int = 1, **kwargs) -> list[IdentifiedModel]:
    """Identify one model per dataset, ``n_jobs`` datasets at a time.

    Parameters
    ----------
    datasets : sequence
        Each entry is what :func:`symsbl.identify` accepts (a Trajectory or a list of
        Trajectories, identified together) or a :class:`~symsbl.ChunkedRecord` or list
        of records (identified with :func:`symsbl.identify_stream`).
    library : Library
        Candidate terms, shared by every fit (compiled once).
    n_jobs : int, default 1
        Worker threads; 1 fits the datasets one after the other in the calling thread. On a
        2-core machine a batch of 4 s Duffing records ran 0.66x as fast on 2 threads as in a
        loop (the fits are GIL-bound), so raise it only for statistics-heavy fits.
    **kwargs
        Passed to every fit (``derivative``, ``rvm``, ``chunk_size``, ``jit``, ...).

    Returns
    -------
    list of IdentifiedModel
        In the order of ``datasets``; the first error raised by any fit is re-raised.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> other = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(80.0, 12.0))
    >>> models = symsbl.identify_many([train, other.with_noise(0.004, seed=1)], library)
    >>> [m.equation("x2").names for m in models]
    [['x1', 'x2', 'x1**3', 'F'], ['x1', 'x2', 'x1**3', 'F']]
    """
    datasets = list(datasets)
    if not datasets:
        raise DataError(expected("datasets", "a non-empty sequence of records", "an empty one", raw=True))
    n_jobs = integer("n_jobs", n_jobs, low=1, error=DataError)
    workers = min(int(n_jobs), len(datasets))
    if workers == 1:
        return [_one(d, library, kwargs) for d in datasets]
    with ThreadPoolExecutor(workers) as pool:
        return [f.result() for f in [pool.submit(_one, d, library, kwargs) for d in datasets]]
