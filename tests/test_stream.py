"""Streaming statistics equal the in-memory ones across chunk boundaries, for every strategy."""

import numpy as np
import pytest
from helpers import exactly

from symsbl import (
    CentralDifference,
    DataError,
    LibraryError,
    PointDifference,
    SavitzkyGolay,
    Sine,
    Trajectory,
    WeakForm,
    chunked,
    identify,
    identify_stream,
    open_npz,
    paper,
    regression_stats,
    simulate,
    stream_stats,
    symbols,
    systems,
    time_grid,
)

LIB = paper(symbols("x1 x2"), symbols("F"), degree=3)
STRATEGIES = [
    WeakForm(window=37),
    WeakForm(window=4, power=2),
    WeakForm(window=24, overlap=2),
    WeakForm(window=12, overlap=3),
    PointDifference(),
    CentralDifference(),
    SavitzkyGolay(window=9, polyorder=3),
]


@pytest.fixture(scope="module")
def record(duffing_short):
    return duffing_short


def _pieces(traj, sizes):
    """Consecutive slices of ``traj`` with the given lengths, cycling through them."""
    out, a, k = [], 0, 0
    while a < traj.n_samples:
        b = a + sizes[k % len(sizes)]
        b = traj.n_samples if traj.n_samples - b < 2 else b  # a Trajectory has at least 2 samples
        out.append(traj.slice(a, b))
        a, k = b, k + 1
    return out


def _as_array(traj):
    return np.column_stack([traj.t, traj.states, traj.inputs])


def _assert_same(a, b, rtol=1e-13):
    assert a.stats.n_samples == b.stats.n_samples
    for name in ("gram", "dty", "yty", "y_sum"):
        x, y = getattr(a.stats, name), getattr(b.stats, name)
        np.testing.assert_allclose(x, y, rtol=0, atol=rtol * np.max(np.abs(y)), err_msg=name)


@pytest.mark.parametrize("strategy", STRATEGIES, ids=repr)
@pytest.mark.parametrize("sizes", [(777,), (2, 3, 5, 500), (4096, 5)], ids=["777", "tiny", "large"])
def test_chunks_give_the_statistics_of_the_whole_record(record, strategy, sizes):
    ref = regression_stats(record, LIB, derivative=strategy)
    got = stream_stats(chunked(_pieces(record, sizes)), LIB, derivative=strategy, block_samples=600)
    _assert_same(got, ref)
    assert got.state_names == ref.state_names and got.input_names == ref.input_names


def test_array_chunks_from_a_generator_function(record):
    ref = regression_stats(record, LIB, derivative=CentralDifference())
    arr = _as_array(record)
    cuts = [0, 1, 2, 3, 1000, 1001, 2500, len(arr)]  # single-sample chunks included

    def pieces():
        return (arr[a:b] for a, b in zip(cuts[:-1], cuts[1:]))

    rec = chunked(pieces, states=("x1", "x2"), inputs=("F",))
    _assert_same(stream_stats(rec, LIB, derivative="central", block_samples=2), ref)
    _assert_same(stream_stats(rec, LIB, derivative="central"), ref)  # a function can be read again


def test_automatic_window_is_resolved_once_from_the_first_block(record):
    # A record shorter than block_samples: one block, the same window as the in-memory path.
    ref = regression_stats(record, LIB)
    got = stream_stats(chunked(_pieces(record, (1000,))), LIB)
    assert got.derivative == ref.derivative
    _assert_same(got, ref)
    # Several blocks: the window comes from the first block and serves every later one.
    first = WeakForm().resolve(record.t[:1024], record.states[:1024], n_terms=len(LIB))
    got = stream_stats(chunked(_pieces(record, (256,))), LIB, block_samples=1024)
    assert got.derivative == first
    _assert_same(got, regression_stats(record, LIB, derivative=first))


def test_several_records_add_their_rows(record):
    other = simulate(systems.duffing(), time_grid(0.3, 8192), inputs=Sine(80.0, 7.0)).with_noise(0.004, seed=2)
    strategy = WeakForm(window=40)
    ref = regression_stats([record, other], LIB, derivative=strategy)
    got = stream_stats([chunked(_pieces(record, (999,))), other], LIB, derivative=strategy, block_samples=700)
    _assert_same(got, ref)


@pytest.mark.parametrize("save", [np.savez, np.savez_compressed], ids=["mmap", "compressed"])
def test_npz_read_in_chunks(record, tmp_path, save):
    path = tmp_path / "long.npz"
    save(path, **record.to_dict())
    strategy = WeakForm(window=33)
    ref = regression_stats(record, LIB, derivative=strategy)
    rec = open_npz(path, states=("x1", "x2"), inputs=("F",), chunk_samples=1234)
    _assert_same(stream_stats(rec, LIB, derivative=strategy, block_samples=2000), ref)
    part = open_npz(path, states=("x1", "x2"), inputs=("F",), time=None, fs=8192, start=100, stop=3000)
    sub = record.slice(100, 3000)
    _assert_same(stream_stats(part, LIB, derivative=strategy), regression_stats(sub, LIB, derivative=strategy))


def test_threads_give_the_same_statistics(record):
    one = stream_stats(record, LIB, derivative=WeakForm(window=20), block_samples=500)
    two = stream_stats(record, LIB, derivative=WeakForm(window=20), block_samples=500, n_jobs=2)
    np.testing.assert_array_equal(one.stats.gram, two.stats.gram)
    np.testing.assert_array_equal(one.stats.dty, two.stats.dty)


def test_streamed_model_equals_in_memory_model(record):
    ref = identify(record, LIB)
    got = identify_stream(chunked(_pieces(record, (1500,))), LIB)
    assert str(got) == str(ref)
    for a, b in zip(got.equations, ref.equations):
        np.testing.assert_allclose(a.coefs, b.coefs, rtol=1e-10)


def test_streamed_identification_takes_identifys_options(record):
    """The rule, the refinement's options (a RefineOptions, as identify takes them) and declared kinematics give
    the in-memory model; kinematics with a member the records lack is refused in one line."""
    from symsbl import RefineOptions, SelectionRule

    asked = dict(
        refine=RefineOptions(noise="white", substeps=2),
        selection=SelectionRule(model_choice="evidence"),
        kinematics="x1:x2",
    )
    ref = identify(record, LIB, **asked)
    got = identify_stream(chunked(_pieces(record, (1500,))), LIB, **asked)
    assert got.equation("x1").fixed and str(got) == str(ref)
    assert got.metadata["refine"]["noise"]["x1"]["model"] == "white"
    for a, b in zip(got.equations, ref.equations):
        np.testing.assert_allclose(a.coefs, b.coefs, rtol=1e-10)
    with pytest.raises(DataError, match=r"^kinematics: expected position:velocity pairs of measured states"):
        identify_stream(chunked(_pieces(record, (1500,))), LIB, kinematics="x1:x2:a1", refine=False)


# ------------------------------------------------------------------------------------------- errors


def test_gap_between_chunks_is_named(record):
    pieces = [record.slice(0, 1000), record.slice(1001, 2000)]
    with pytest.raises(
        DataError,
        match=exactly(
            "records[0] (chunks) chunk 1: expected a start one sample interval "
            "(0.0001220703125 s) after the previous chunk, received t = "
            "np.float64(0.1221923828125), 0.000244140625 s after it; chunks must "
            "be consecutive pieces of one record; pass separate records as list "
            "entries"
        ),
    ):
        stream_stats(chunked(pieces), LIB)


def test_array_chunks_need_names(record):
    with pytest.raises(
        DataError,
        match=exactly(
            "records[0] (chunks) chunk 0: expected column names for array chunks, "
            "received none; pass states=... (and inputs=...) to symsbl.chunked"
        ),
    ):
        stream_stats(chunked([_as_array(record)]), LIB)
    with pytest.raises(
        DataError,
        match=exactly(
            "records[0] (chunks) chunk 0: expected an array of shape (n, 4) with "
            "columns ['t', 'x1', 'x2', 'F'], received shape (4097, 3)"
        ),
    ):
        stream_stats(chunked([_as_array(record)[:, :3]], states=("x1", "x2"), inputs=("F",)), LIB)


def test_iterator_is_read_once(record):
    rec = chunked(iter(_pieces(record, (2000,))))
    stream_stats(rec, LIB, derivative="point")
    with pytest.raises(
        DataError,
        match=exactly(
            "chunks: expected a record that can be read again, received an "
            "iterator, already read; pass a list or a function returning a new "
            "iterator"
        ),
    ):
        stream_stats(rec, LIB, derivative="point")


def test_bad_sources_are_named(record, tmp_path):
    with pytest.raises(DataError, match="chunks: expected a sequence, an iterator or a function"):
        chunked(record)
    with pytest.raises(
        DataError,
        match=exactly(
            "records: expected a Trajectory, a ChunkedRecord or a list of them, "
            "received the path 'a.npz'; open it with symsbl.open_npz(path, "
            "states=..., inputs=...)"
        ),
    ):
        stream_stats("a.npz", LIB)
    with pytest.raises(DataError, match=r"records\[1\]: expected a Trajectory or a ChunkedRecord"):
        stream_stats([record, np.zeros((10, 4))], LIB)
    path = tmp_path / "r.npz"
    np.savez(path, **record.to_dict())
    with pytest.raises(
        DataError,
        match=r"r\.npz: column 'x3': expected a column among \['F', 't', 'x1', 'x2'\], "
        r"received no such column$",
    ):
        open_npz(path, states=("x1", "x3"))
    with pytest.raises(DataError, match=r"start, stop: expected 0 <= start < stop <= 4097 samples"):
        open_npz(path, states=("x1", "x2"), start=5000)
    with pytest.raises(DataError, match="chunk_samples: expected an integer >= 2, received 1"):
        open_npz(path, states=("x1", "x2"), chunk_samples=1)


def test_unknown_strategy_and_bad_settings(record):
    class Custom(PointDifference):
        pass

    # A user's strategy declares its stencil (the Differentiator contract), so it streams like the built-in ones.
    streamed = stream_stats(chunked([record.slice(0, 1500), record.slice(1500, None)]), LIB, derivative=Custom())
    np.testing.assert_allclose(
        streamed.stats.gram, regression_stats(record, LIB, derivative=Custom()).stats.gram, rtol=1e-12
    )
    with pytest.raises(DataError, match="n_jobs: expected an integer >= 1, received 0"):
        stream_stats(record, LIB, n_jobs=0)


def test_records_must_share_names(record):
    renamed = Trajectory(record.t, record.states, record.inputs, ("x1", "x2"), ("G",))
    lib = paper(symbols("x1 x2"), (), degree=2)
    with pytest.raises(
        DataError,
        match=exactly(
            "records[1]: expected the states ('x1', 'x2') and inputs ('F',) of "
            "records[0], received states ('x1', 'x2'), inputs ('G',)"
        ),
    ):
        stream_stats([record, renamed], lib, derivative="point")


def test_data_errors_match_the_in_memory_path(record):
    flat = Trajectory(
        record.t,
        np.column_stack([record.states[:, 0], np.full(record.n_samples, 2.0)]),
        record.inputs,
        ("x1", "x2"),
        ("F",),
    )
    with pytest.raises(
        DataError,
        match=exactly(
            "state 'x2': expected a column that varies, received a constant 2; "
            "remove it from the states or record a response in which it moves"
        ),
    ):
        stream_stats(chunked(_pieces(flat, (1000,))), LIB, derivative="point")
    with pytest.raises(
        DataError,
        match=exactly(
            "rows: expected more regression rows than candidate terms (34), "
            "received 30 rows from 1 record(s) with PointDifference; use longer "
            "records, fewer candidate terms (a lower degree) or a derivative "
            "strategy with more rows"
        ),
    ):
        stream_stats(record.slice(0, 30), LIB, derivative="point")
    with pytest.raises(
        LibraryError,
        match=exactly(
            "library: expected variables named like the data's states ['x1', "
            "'x2'] and inputs ['F'], received a library that also uses ['y']; "
            "declare the library with symbols named like the columns"
        ),
    ):
        stream_stats(record, paper(symbols("x1 y"), (), degree=1), derivative="point")


# -------------------------------------------------------------------------------------------- batch


def test_batch_gives_the_models_of_separate_fits(record):
    from symsbl import identify, identify_many

    other = record.slice(0, 3000)
    models = identify_many([record, chunked(_pieces(other, (1000,)))], LIB, n_jobs=2, derivative="central")
    assert str(models[0]) == str(identify(record, LIB, derivative="central"))
    assert str(models[1]) == str(identify(other, LIB, derivative="central"))
    with pytest.raises(DataError, match="n_jobs: expected an integer >= 1, received 0"):
        identify_many([record], LIB, n_jobs=0)
    with pytest.raises(DataError, match="datasets: expected a non-empty sequence of records"):
        identify_many([], LIB)
