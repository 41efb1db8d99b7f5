"""Trajectory validation, noise and CSV/NPZ/MAT reading and writing."""

import hashlib
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from helpers import exactly

from symsbl import DataError, Trajectory, read_trajectory, write_trajectory
from symsbl._data.trajectory import validate

EMPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "EMPS" / "DATA_EMPS.mat"


def make(n=50, fs=100.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    return Trajectory(t, rng.standard_normal((n, 2)), rng.standard_normal((n, 1)), ("x1", "x2"), ("F",))


def test_properties_and_accessors():
    tr = make()
    assert tr.n_samples == 50 and tr.dt == pytest.approx(0.01) and tr.fs == pytest.approx(100.0)
    np.testing.assert_array_equal(tr.column("x2"), tr.states[:, 1])
    np.testing.assert_array_equal(tr.column("F"), tr.inputs[:, 0])
    np.testing.assert_array_equal(tr.column("t"), tr.t)
    assert list(tr.to_dict()) == ["t", "x1", "x2", "F"]
    part = tr.slice(10, 20)
    np.testing.assert_array_equal(part.states, tr.states[10:20])
    assert part.t[0] == tr.t[10] and part.diverged_at is None
    assert not tr.states.flags.writeable


def test_no_inputs_is_empty_matrix():
    tr = Trajectory(np.arange(5.0), np.ones((5, 1)), None, ("x",))
    assert tr.inputs.shape == (5, 0) and tr.input_names == ()


def test_column_missing_lists_available():
    with pytest.raises(DataError, match=exactly("column: expected one of ['t', 'x1', 'x2', 'F'], received 'y'")):
        make().column("y")


@pytest.mark.parametrize(
    "t, states, match",
    [
        (
            [0, 1, 2, 2, 4],
            np.zeros(5),
            exactly(
                "time: expected strictly increasing values, received t = 2.0 at row 3 "
                "after t = 2.0; sort the rows or pass --fs/fs for a rounded time "
                "column"
            ),
        ),
        (
            [0, 1, 2, 3.5, 4],
            np.zeros(5),
            exactly(
                "time: expected uniform sampling (steps within 0.001 of the mean step "
                "1.0), received a step of 1.5 before row 3 (relative deviation 0.5); "
                "resample onto a uniform grid, or pass --fs/fs when the time column "
                "is only rounded"
            ),
        ),
        (
            [0, 1, 2, 3, 4],
            [0, 0, 0, 0, np.nan],
            exactly(
                "column 'x': expected finite values, received nan at row 4 (1 "
                "non-finite in total); remove or repair those rows"
            ),
        ),
        (
            [0, 1, np.inf, 3, 4],
            np.zeros(5),
            exactly(
                "column 'time': expected finite values, received inf at row 2 (1 "
                "non-finite in total); remove or repair those rows"
            ),
        ),
        ([0, 1, 2, 3], np.zeros(5), exactly("states: expected one row per time sample (4), received 5 rows")),
        ([0.0], np.zeros(1), exactly("trajectory: expected at least 2 samples, received 1")),
        (np.zeros((2, 2)), np.zeros(2), exactly("time: expected shape (n_samples,), received shape (2, 2)")),
    ],
)
def test_validate_errors(t, states, match):
    with pytest.raises(DataError, match=match):
        validate(t, states, None, ("x",))


def test_validate_accepts_logger_jitter():
    t = np.arange(100) * 1e-3
    t[50] += 2e-8  # 2e-5 of a step, like the EMPS record
    validate(t, np.zeros(100), None, ("x",))


@pytest.mark.parametrize(
    "states, names, inputs, input_names, match",
    [
        (
            np.zeros((3, 2)),
            ("x",),
            None,
            (),
            exactly("states: expected shape (n_samples, 1), one column per name, received shape (3, 2)"),
        ),
        (
            np.zeros((3, 2)),
            ("x", "x"),
            None,
            (),
            exactly("state names: expected distinct names, received ['x', 'x']; rename the repeated ['x']"),
        ),
        (
            np.zeros(3),
            ("x",),
            np.zeros(3),
            ("x",),
            exactly(
                "state and input names together: expected distinct names, "
                "received ['x', 'x']; rename the repeated ['x']"
            ),
        ),
        (
            np.zeros(3),
            ("t",),
            None,
            (),
            exactly(
                "names: expected state and input names other than 't' (the time "
                "column), received ['t']; rename that state or input"
            ),
        ),
        (
            np.zeros(3),
            ("x",),
            np.zeros((2, 1)),
            ("u",),
            exactly("inputs: expected one row per time sample (3), received 2 rows"),
        ),
    ],
)
def test_validate_name_and_shape_errors(states, names, inputs, input_names, match):
    with pytest.raises(DataError, match=match):
        validate(np.arange(3.0), states, inputs, names, input_names)


def test_noise_relative_std_and_seed():
    n = 200_000
    t = np.arange(n) / 1000.0
    clean = np.column_stack([1e-3 * np.sin(2 * np.pi * 3 * t), 50 * np.cos(2 * np.pi * 7 * t) + 4])
    tr = Trajectory(t, clean, np.full((n, 1), 2.0), ("x1", "x2"), ("F",))
    noisy = tr.with_noise(rel_std=0.004, seed=3)
    ratio = (noisy.states - clean).std(axis=0) / clean.std(axis=0)
    np.testing.assert_allclose(ratio, 0.004, rtol=0.01)  # 200k draws: std of the estimate ~0.16 %
    np.testing.assert_array_equal(noisy.inputs, tr.inputs)
    np.testing.assert_array_equal(tr.with_noise(0.004, seed=3).states, noisy.states)
    assert not np.array_equal(tr.with_noise(0.004, seed=4).states, noisy.states)
    # a constant channel has zero std, so it stays noise-free
    np.testing.assert_array_equal(tr.with_noise(0.01, seed=0, channels="all").inputs, tr.inputs)


def test_noise_channels():
    tr = make(n=2000)
    only_in = tr.with_noise(0.01, seed=0, channels="inputs")
    np.testing.assert_array_equal(only_in.states, tr.states)
    assert np.std(only_in.inputs - tr.inputs) == pytest.approx(0.01 * tr.inputs.std(), rel=0.1)
    both = tr.with_noise(0.01, seed=0, channels="all")
    assert not np.array_equal(both.states, tr.states) and not np.array_equal(both.inputs, tr.inputs)
    with pytest.raises(DataError, match=exactly("channels: expected one of ['states', 'inputs', 'all'], received 'x'")):
        tr.with_noise(channels="x")
    with pytest.raises(DataError, match=exactly("rel_std: expected a finite number >= 0.0, received -1")):
        tr.with_noise(rel_std=-1)


@pytest.mark.parametrize("ext", [".csv", ".npz", ".mat"])
def test_round_trip_is_exact(tmp_path, ext):
    rng = np.random.default_rng(1)
    n = 300
    t = np.arange(n) / 32768.0
    tr = Trajectory(
        t,
        rng.standard_normal((n, 3)) * 10.0 ** rng.integers(-9, 9, (n, 3)),
        rng.standard_normal((n, 1)),
        ("x1", "x2", "x3"),
        ("F",),
    )
    path = tmp_path / f"traj{ext}"
    write_trajectory(tr, path)
    back = read_trajectory(path, states=tr.state_names, inputs=tr.input_names)
    for a, b in ((tr.t, back.t), (tr.states, back.states), (tr.inputs, back.inputs)):
        np.testing.assert_array_equal(a, b)
    assert back.state_names == tr.state_names and back.input_names == tr.input_names


def test_csv_header_and_column_selection(tmp_path):
    path = tmp_path / "d.csv"
    path.write_text("time, u, pos, vel\n0,1,2,3\n0.5,4,5,6\n1.0,7,8,9\n\n")
    tr = read_trajectory(path, states=["vel", "pos"], inputs=["u"], time="time")
    np.testing.assert_array_equal(tr.states, [[3, 2], [6, 5], [9, 8]])
    np.testing.assert_array_equal(tr.inputs[:, 0], [1, 4, 7])


@pytest.mark.parametrize("shape", ["row", "column"])
def test_mat_vectors_1xN_and_Nx1(tmp_path, shape):
    t = np.arange(10) * 0.1
    x = np.sin(t)
    as_shape = (lambda v: v[None, :]) if shape == "row" else (lambda v: v[:, None])
    path = tmp_path / "d.mat"
    scipy.io.savemat(path, {"t": as_shape(t), "y": as_shape(x), "u": as_shape(2 * x), "fs": 10.0})
    tr = read_trajectory(path, states=["y"], inputs=["u"])
    np.testing.assert_array_equal(tr.states[:, 0], x)
    np.testing.assert_array_equal(tr.inputs[:, 0], 2 * x)


def test_time_from_sample_rate(tmp_path):
    path = tmp_path / "d.npz"
    np.savez(path, y=np.arange(5.0), u=np.ones(5))
    tr = read_trajectory(path, states=["y"], inputs=["u"], time=None, fs=750.0)
    np.testing.assert_array_equal(tr.t, np.arange(5) / 750.0)
    with pytest.raises(
        DataError,
        match=exactly(
            "fs: expected a positive sample rate in Hz when there is no time column, received none; name the time "
            "column, or give the rate (--fs HZ on the command line, fs= in Python)"
        ),
    ):
        read_trajectory(path, states=["y"], time=None)


def test_read_errors(tmp_path):
    csv = tmp_path / "d.csv"
    csv.write_text("t,x1,x2\n0,1,2\n1,1,2\n2,1,nan\n")
    with pytest.raises(
        DataError,
        match=r"d\.csv: column 'x9': expected a column among \['t', 'x1', 'x2'\], received "
        r"no such column; check "
        r"--states/--inputs/--time against the header$",
    ):
        read_trajectory(csv, states=["x9"])
    with pytest.raises(
        DataError,
        match=r"d\.csv: column 'x2': expected finite values, received nan at row 2 \(1 "
        r"non-finite in total\)",
    ):
        read_trajectory(csv, states=["x1", "x2"])
    with pytest.raises(DataError, match=exactly("states: expected at least one column name, received an empty list")):
        read_trajectory(csv, states=[])
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x\n0,1\n1,oops\n")
    with pytest.raises(
        DataError,
        match=r"bad\.csv: column 'x' at line 3: expected a number, received 'oops'; repair "
        r"or remove the row$",
    ):
        read_trajectory(bad, states=["x"])
    ragged = tmp_path / "ragged.csv"
    ragged.write_text("t,x\n0,1\n1\n")
    with pytest.raises(
        DataError,
        match=r"ragged\.csv: line 3: expected 2 fields, one per header column, received 1 "
        r"field; every row needs",
    ):
        read_trajectory(ragged, states=["x"])
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(DataError, match=r"empty\.csv: expected a header row of column names, received an empty file$"):
        read_trajectory(empty, states=["x"])
    npz = tmp_path / "d.npz"
    np.savez(npz, t=np.arange(4.0), x=np.zeros(4), u=np.zeros(3), m=np.zeros((4, 2)))
    with pytest.raises(
        DataError, match=r"d\.npz: expected columns of one length, received lengths \{'x': 4, 'u': 3\}$"
    ):
        read_trajectory(npz, states=["x"], inputs=["u"])
    with pytest.raises(
        DataError,
        match=r"d\.npz: column 'm': expected a real numeric vector \(N, 1xN or Nx1\), "
        r"received shape \(4, 2\) and dtype float64$",
    ):
        read_trajectory(npz, states=["m"])
    np.savez(tmp_path / "short.npz", t=np.arange(3.0), x=np.zeros(4))
    with pytest.raises(
        DataError,
        match=r"short\.npz: time column 't': expected 4 samples like the data columns, "
        r"received 3 samples$",
    ):
        read_trajectory(tmp_path / "short.npz", states=["x"])
    np.savez(tmp_path / "one.npz", t=np.zeros(1), x=np.zeros(1))
    with pytest.raises(DataError, match=r"one\.npz: trajectory: expected at least 2 samples, received 1$"):
        read_trajectory(tmp_path / "one.npz", states=["x"])
    with pytest.raises(
        DataError,
        match=r"d\.txt: expected a file ending in one of \['\.csv', '\.mat', '\.npz'\], "
        r"received the extension '\.txt'$",
    ):
        read_trajectory(tmp_path / "d.txt", states=["x"])
    with pytest.raises(DataError, match=r"missing\.csv: expected an existing data file, received no such file$"):
        read_trajectory(tmp_path / "missing.csv", states=["x"])


def test_write_errors(tmp_path):
    tr = Trajectory(np.arange(3.0), np.zeros((3, 1)), None, ("x dot",))
    with pytest.raises(
        DataError,
        match=exactly(
            "column name: expected a MATLAB variable name (a letter, then letters, "
            "digits or underscores, at most 63 characters), received 'x dot'; "
            "rename it or write .csv/.npz"
        ),
    ):
        write_trajectory(tr, tmp_path / "d.mat")
    tr = Trajectory(np.arange(3.0), np.zeros((3, 1)), None, ("a,b",))
    with pytest.raises(
        DataError,
        match=exactly("column name: expected a name without commas, quotes or newlines for CSV, received 'a,b'"),
    ):
        write_trajectory(tr, tmp_path / "d.csv")


def test_reading_leaves_files_unchanged(tmp_path):
    tr = make()
    digests = {}
    for ext in (".csv", ".npz", ".mat"):
        path = tmp_path / f"d{ext}"
        write_trajectory(tr, path)
        digests[path] = hashlib.sha256(path.read_bytes()).hexdigest()
        read_trajectory(path, states=["x1", "x2"], inputs=["F"])
    assert all(hashlib.sha256(p.read_bytes()).hexdigest() == d for p, d in digests.items())


@pytest.mark.skipif(not EMPS.exists(), reason="EMPS data not found at ../shared/data/EMPS")
def test_reads_real_emps_record():
    tr = read_trajectory(EMPS, states=["qm"], inputs=["vir"])
    assert tr.n_samples == 24841 and tr.fs == pytest.approx(1000.0, rel=1e-4)
    assert 0.24 < tr.states.max() < 0.25


def test_noise_levels_needs_a_trajectory_of_four_samples():
    from symsbl import noise_levels

    short = Trajectory(np.arange(3.0), np.zeros((3, 1)) + np.arange(3.0)[:, None], state_names=("x",))
    with pytest.raises(
        DataError,
        match=exactly("traj: expected a Trajectory of at least 4 samples to estimate its noise, received 3 samples"),
    ):
        noise_levels(short)
    with pytest.raises(DataError, match="received ndarray"):
        noise_levels(np.zeros((10, 2)))
