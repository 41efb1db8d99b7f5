"""The Dask map-reduce gives the single-process statistics and model, on a local cluster."""

import sys

import numpy as np
import pytest
from helpers import exactly

from symsbl import (
    DataError,
    PointDifference,
    SavitzkyGolay,
    WeakForm,
    identify_stream,
    paper,
    stream_stats,
    symbols,
)

dask = pytest.importorskip("dask", reason="Dask is optional: pip install symsbl[dask]")
distributed = pytest.importorskip("dask.distributed", reason="dask.distributed is optional: pip install symsbl[dask]")
da = pytest.importorskip("dask.array", reason="dask.array is optional: pip install symsbl[dask]")

from symsbl import dask_stats, from_delayed, identify_dask  # noqa: E402

LIB = paper(symbols("x1 x2"), symbols("F"), degree=3)
NAMES = dict(states=("x1", "x2"), inputs=("F",))


@pytest.fixture(scope="module")
def record(duffing_short):
    return duffing_short


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        with distributed.Client(cluster) as c:
            yield c


def _array(traj, chunks=1000):
    return da.from_array(np.column_stack([traj.t, traj.states, traj.inputs]), chunks=(chunks, 4))


def _assert_same(a, b):
    assert a.stats.n_samples == b.stats.n_samples
    for name in ("gram", "dty", "yty", "y_sum"):
        x, y = getattr(a.stats, name), getattr(b.stats, name)
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-13 * np.max(np.abs(y)), err_msg=name)


@pytest.mark.parametrize(
    "strategy",
    [WeakForm(window=29), WeakForm(window=30, overlap=2), PointDifference(), SavitzkyGolay(window=9, polyorder=3)],
    ids=repr,
)
def test_cluster_statistics_equal_the_single_process_ones(client, record, strategy):
    ref = stream_stats(record, LIB, derivative=strategy)
    got = dask_stats(_array(record), LIB, derivative=strategy, block_samples=700, **NAMES)
    _assert_same(got, ref)
    assert got.derivative == ref.derivative


def test_cluster_model_equals_the_single_process_model(client, record):
    ref = identify_stream(record, LIB)
    got = identify_dask(_array(record, 1500), LIB, **NAMES)
    assert str(got) == str(ref)
    for a, b in zip(got.equations, ref.equations):
        np.testing.assert_allclose(a.coefs, b.coefs, rtol=1e-10)


def test_cluster_identification_takes_identifys_options(client, record):
    """A RefineOptions, a selection rule and kinematics act as in the single-process front end."""
    from symsbl import RefineOptions, SelectionRule

    asked = dict(
        refine=RefineOptions(noise="white"), selection=SelectionRule(model_choice="evidence"), kinematics="x1:x2"
    )
    ref = identify_stream(record, LIB, **asked)
    got = identify_dask(_array(record, 1500), LIB, **NAMES, **asked)
    assert got.equation("x1").fixed and str(got) == str(ref)
    assert got.metadata["refine"]["noise"]["x1"]["model"] == "white"


def test_delayed_chunks_and_several_records(client, record):
    pieces = [dask.delayed(record.slice)(a, min(a + 1300, record.n_samples)) for a in range(0, record.n_samples, 1300)]
    other = record.slice(0, 2000)
    strategy = WeakForm(window=31)
    ref = stream_stats([record, other], LIB, derivative=strategy)
    lengths = [min(1300, record.n_samples - a) for a in range(0, record.n_samples, 1300)]
    for given in (None, lengths):
        records = [from_delayed(pieces, n_columns=4, lengths=given), _array(other)]
        _assert_same(dask_stats(records, LIB, derivative=strategy, block_samples=900, **NAMES), ref)


def test_threaded_scheduler_without_a_cluster(record):
    ref = stream_stats(record, LIB, derivative="central")
    got = dask_stats(_array(record), LIB, derivative="central", block_samples=1000, scheduler="threads", **NAMES)
    _assert_same(got, ref)


def test_bad_records_are_named(record):
    with pytest.raises(
        DataError,
        match=r"records\[0\]: expected a dask.array.Array of shape \(n_samples, 4\) .* "
        r"received ndarray",
    ):
        dask_stats(np.zeros((10, 4)), LIB, **NAMES)
    with pytest.raises(
        DataError,
        match=exactly(
            "records[0]: expected a dask.array.Array of shape (n_samples, 4) with "
            "columns ['t', 'x1', 'x2', 'F'], received Delayed; turn a list of "
            "delayed chunks into one with symsbl.from_delayed"
        ),
    ):
        dask_stats([dask.delayed(np.zeros)((10, 4))], LIB, **NAMES)
    with pytest.raises(DataError, match=r"records\[0\]: expected shape \(n_samples, 4\) .* received shape \(4097, 3\)"):
        dask_stats(_array(record)[:, :3], LIB, **NAMES)
    with pytest.raises(DataError, match=exactly("lengths: expected one length per chunk (1), received 2")):
        from_delayed([dask.delayed(np.zeros)((10, 4))], n_columns=4, lengths=[5, 5])


def test_missing_dask_says_how_to_install(monkeypatch, record):
    monkeypatch.setitem(sys.modules, "dask", None)
    with pytest.raises(
        ImportError,
        match=exactly(
            "identify_dask: expected Dask to be installed, received ImportError; "
            "install it with pip install 'dask[distributed]' (or pip install "
            "'.[dask]' from a clone of symsbl)"
        ),
    ):
        dask_stats(None, LIB, **NAMES)
