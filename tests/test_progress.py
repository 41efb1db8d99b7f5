"""Progress lines: shown on a terminal for long steps, silent in logs, pipes, threads and with --quiet."""

import io
import re
import sys
import threading

import numpy as np
import pytest
from helpers import exactly

import symsbl
import symsbl._base.progress as progress
from symsbl import Sine, discrepancy, simulate, symbols, systems, time_grid
from symsbl._base.progress import Progress, progress_enabled, set_progress
from symsbl._cli import main


class Terminal(io.StringIO):
    """A stream that says it is a terminal."""

    def isatty(self):
        return True


@pytest.fixture
def terminal(monkeypatch):
    """A function that replaces standard error by a terminal and shows every step at once.

    Called in the test body: pytest re-installs its own capture of standard error between a
    fixture's setup and the test call.
    """

    def attach() -> Terminal:
        stream = Terminal()
        monkeypatch.setattr("sys.stderr", stream)
        monkeypatch.setattr(progress, "DELAY", 0.0)
        monkeypatch.setattr(progress, "INTERVAL", 0.0)
        return stream

    return attach


def finished(text: str) -> list[str]:
    """The closing lines, ``label: done units in t s (done)``, without the terminal's escapes."""
    parts = re.split(r"[\r\n]", text.replace("\033[K", ""))
    return [p for p in parts if p.endswith("(done)")]


def test_a_terminal_gets_running_and_closing_lines():
    stream = Terminal()
    with Progress("work", total=4, unit="items", stream=stream, delay=0.0, interval=0.0) as bar:
        bar.update(1)
        bar.update(3)
    text = stream.getvalue().replace("\033[K", "")
    assert "\rwork: 1/4 items (25 %)" in text
    assert re.search(r"\rwork: 4/4 items in \d+\.\d s \(done\)\n$", text)


def test_an_unknown_total_shows_the_count():
    stream = Terminal()
    with Progress("read", unit="samples", stream=stream, delay=0.0, interval=0.0) as bar:
        bar.update(10)
    assert "\rread: 10 samples, " in stream.getvalue()
    assert finished(stream.getvalue())[0].startswith("read: 10 samples in ")


def test_a_failing_step_is_closed_as_stopped():
    stream = Terminal()
    with pytest.raises(RuntimeError):
        with Progress("work", total=2, stream=stream, delay=0.0) as bar:
            bar.update()
            raise RuntimeError("boom")
    assert re.search(r"work: 1/2 in \d+\.\d s \(stopped\)\n$", stream.getvalue().replace("\033[K", ""))


def test_a_step_left_short_of_its_total_is_closed_as_stopped():
    stream = Terminal()
    with Progress("simulate", total=10, stream=stream, delay=0.0) as bar:
        bar.update(4)  # e.g. the simulation diverged
    assert finished(stream.getvalue()) == []
    assert "simulate: 4/10 in" in stream.getvalue() and "(stopped)" in stream.getvalue()


class Broken(Terminal):
    """A terminal that has gone away: every write fails."""

    def write(self, text):
        raise OSError(5, "Input/output error")


def test_a_failing_stream_ends_the_display_not_the_work(monkeypatch):
    monkeypatch.setattr(progress, "DELAY", 0.0)
    with progress_enabled(True):
        traj = simulate(systems.coulomb(), time_grid(0.1, 8192), inputs=Sine(100.0, 10.0))
        assert traj.n_samples == 820
        with Progress("a", total=1, stream=Broken(), delay=0.0) as bar:
            bar.update()
        monkeypatch.setattr("sys.stderr", None)  # no standard error at all
        with Progress("b", total=1, delay=0.0) as bar:
            bar.update()
    ok = Terminal()
    with Progress("after", total=1, stream=ok, delay=0.0) as bar:  # nesting depth is back to 0
        bar.update()
    assert [line.split(" in ")[0] for line in finished(ok.getvalue())] == ["after: 1/1"]


def test_not_a_terminal_short_steps_switched_off_and_worker_threads_stay_silent():
    plain = io.StringIO()
    with Progress("a", total=1, stream=plain, delay=0.0) as bar:
        bar.update()
    assert plain.getvalue() == ""

    short = Terminal()
    with Progress("b", total=1, stream=short, delay=60.0) as bar:
        bar.update()
    assert short.getvalue() == ""

    off = Terminal()
    with progress_enabled(False):
        with Progress("c", total=1, stream=off, delay=0.0) as bar:
            bar.update()
    assert off.getvalue() == ""

    threaded = Terminal()

    def work():
        with Progress("d", total=1, stream=threaded, delay=0.0) as bar:
            bar.update()

    worker = threading.Thread(target=work)
    worker.start()
    worker.join()
    assert threaded.getvalue() == ""


def test_forced_on_writes_to_a_plain_stream_and_the_setting_is_restored():
    plain = io.StringIO()
    before = set_progress(None)
    with progress_enabled(True):
        with Progress("e", total=1, stream=plain, delay=0.0) as bar:
            bar.update()
    assert finished(plain.getvalue()) == [finished(plain.getvalue())[0]]
    assert set_progress(before) is None


def test_nested_steps_show_only_the_outer_line():
    stream = Terminal()
    with Progress("outer", total=2, stream=stream, delay=0.0) as outer:
        for _ in range(2):
            with Progress("inner", total=1, stream=stream, delay=0.0) as inner:
                inner.update()
            outer.update()
    assert "inner" not in stream.getvalue()
    assert [line.split(":")[0] for line in finished(stream.getvalue())] == ["outer"]


def test_set_progress_rejects_a_non_boolean():
    with pytest.raises(symsbl.ParameterError, match=exactly("enabled: expected True, False or None, received 'yes'")):
        set_progress("yes")


# --------------------------------------------------------------------- the long steps report
def test_simulation_reports_its_samples_with_both_integrators(terminal):
    stream = terminal()
    t = time_grid(0.25, 8192)
    simulate(systems.duffing(), t, inputs=Sine(100.0, 10.0))
    simulate(systems.coulomb(), t, inputs=Sine(100.0, 10.0))
    lines = finished(stream.getvalue())
    assert [line.split(" in ")[0] for line in lines] == [
        "simulate duffing (cvodes): 2048/2048 steps",
        "simulate coulomb (rk4): 2048/2048 steps",
    ]


def test_a_long_cvodes_run_in_segments_matches_one_call(monkeypatch):
    """Progress comes from segmenting long cvodes runs; the segments must not change the answer."""
    t = time_grid(0.5, 8192)
    whole = simulate(systems.duffing(), t, inputs=Sine(100.0, 10.0))
    monkeypatch.setattr(sys.modules["symsbl._simulation.cvodes"], "CVODES_SEGMENT", 1000)  # 5 segments
    parts = simulate(systems.duffing(), t, inputs=Sine(100.0, 10.0))
    scale = abs(whole.states).max(axis=0)
    assert (abs(parts.states - whole.states).max(axis=0) / scale).max() < 1e-7


def test_cvodes_segments_follow_a_measured_grid_with_jitter(monkeypatch):
    """Segments of equal length but different spacing must not share one integrator's grid:
    x' = -5 x on a grid whose step drifts by -/+ 0.08 %, against exp(-5 t)."""
    (x,) = symbols("x")
    decay = symsbl.OdeSystem((x,), (), (-5 * x,), name="decay")
    h = 1e-3
    t = np.concatenate([[0.0], np.cumsum(np.r_[np.full(1000, h * (1 + 8e-4)), np.full(1000, h * (1 - 8e-4))])])
    monkeypatch.setattr(sys.modules["symsbl._simulation.cvodes"], "CVODES_SEGMENT", 1000)
    traj = simulate(decay, t, x0=[1.0], method="cvodes")
    assert np.max(np.abs(traj.states[:, 0] - np.exp(-5 * t))) < 1e-8


def test_a_cvodes_failure_in_a_later_segment_reports_its_absolute_time(monkeypatch):
    """x' = x^2 from x(0) = 1 blows up at t = 1; with segments of 100 samples the failure lies in
    the tenth segment and must be reported near t = 1, not near the segment's own start."""
    (x,) = symbols("x")
    blowup = symsbl.OdeSystem((x,), (), (x**2,), name="blowup")
    monkeypatch.setattr(sys.modules["symsbl._simulation.cvodes"], "CVODES_SEGMENT", 100)
    traj = simulate(blowup, np.linspace(0.0, 1.5, 1501), x0=[1.0], method="cvodes", on_divergence="truncate")
    assert 0.99 < traj.diverged_at <= 1.0
    good = traj.t < 0.99
    assert np.allclose(traj.states[good, 0], 1 / (1 - traj.t[good]), rtol=1e-6)


def test_identification_and_the_band_report_their_rows_equations_and_draws(terminal):
    stream = terminal()
    x1, x2, F = symsbl.symbols("x1 x2 F")
    train = simulate(systems.duffing(), time_grid(0.5, 8192), inputs=Sine(100.0, 10.0)).with_noise(0.004, seed=0)
    model = symsbl.identify(train, symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F]))
    symsbl.validate_model(model, train.slice(0, 1000), n_band=3)
    lines = [line.split(" in ")[0] for line in finished(stream.getvalue())]
    labels = [line for line in lines if not line.startswith("simulate")]
    done, total = map(int, re.fullmatch(r"dictionary \(\d+ terms\) and Gram: (\d+)/(\d+) rows", labels[0]).groups())
    assert done == total == model.metadata["n_rows"]
    assert labels[1:] == ["fit: 2/2 equations", "output-error refinement: 2/2 fits"]
    # the band's draws run as one batched simulation, reported with their count
    assert lines[-1] == "simulate identified x 3 draws (rk4): 999/999 steps", lines


def test_streamed_statistics_report_the_samples_read(terminal, monkeypatch):
    stream = terminal()
    x1, x2, F = symsbl.symbols("x1 x2 F")
    train = simulate(systems.duffing(), time_grid(0.5, 8192), inputs=Sine(100.0, 10.0))
    seen = []  # what the display said when each block started its reduction
    reduce_block = sys.modules["symsbl._scale.stream"].block_stats

    def spy(*args):
        seen.append(stream.getvalue())
        return reduce_block(*args)

    monkeypatch.setattr(sys.modules["symsbl._scale.stream"], "block_stats", spy)
    records = [train.slice(k * 1024, (k + 1) * 1024) for k in range(4)]  # four records, one block each
    symsbl.stream_stats(records, symsbl.polynomial([x1, x2], 2) + symsbl.inputs([F]))
    # samples count once their block is reduced: each block starts with only the earlier ones counted
    shown = [re.findall(r"streamed: (\d+)/4096 samples", text)[-1] for text in seen]
    assert shown == ["0", "1024", "2048", "3072"]
    (line,) = [line for line in finished(stream.getvalue()) if not line.startswith("simulate")]
    assert re.fullmatch(r"dictionary \(\d+ terms\) and Gram, streamed: 4096/4096 samples in .*", line)


@pytest.mark.parametrize("evidence, unit", [("equation-error", "fits"), ("output-error", "stages")])
def test_the_discrepancy_scan_reports_every_fit_or_stage(terminal, evidence, unit):
    stream = terminal()
    train = simulate(systems.linear(), time_grid(1.0, 8192), inputs=Sine(100.0, 10.0)).with_noise(0.004, seed=0)
    discrepancy(
        train, "x1: x2; x2: F, x1, x2", rule=symsbl.DecisionRule(n_bootstrap=1), max_iterations=1, evidence=evidence
    )
    scans = [line for line in finished(stream.getvalue()) if line.startswith("discrepancy iteration 1")]
    assert len(scans) == 1
    done, total = map(int, re.search(rf": (\d+)/(\d+) {unit}", scans[0]).groups())
    assert done == total > 0


# --------------------------------------------------------------------------- command line
def test_cli_shows_progress_on_a_terminal_and_not_with_quiet(terminal, tmp_path):
    stream = terminal()
    train = simulate(systems.duffing(), time_grid(0.5, 8192), inputs=Sine(100.0, 10.0)).with_noise(0.004, seed=0)
    symsbl.write_trajectory(train, tmp_path / "train.npz")
    argv = ["identify", str(tmp_path / "train.npz"), "--states", "x1,x2", "--inputs", "F", "--library", "poly"]
    assert main(argv) == 0
    assert any(line.startswith("fit: 2/2 equations") for line in finished(stream.getvalue()))
    stream.seek(0)
    stream.truncate()
    assert main(argv + ["--quiet"]) == 0
    assert stream.getvalue() == ""


def test_cli_stays_silent_when_standard_error_is_not_a_terminal(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(progress, "DELAY", 0.0)
    train = simulate(systems.duffing(), time_grid(0.5, 8192), inputs=Sine(100.0, 10.0)).with_noise(0.004, seed=0)
    symsbl.write_trajectory(train, tmp_path / "train.npz")
    assert (
        main(["identify", str(tmp_path / "train.npz"), "--states", "x1,x2", "--inputs", "F", "--library", "poly"]) == 0
    )
    assert capsys.readouterr().err == ""
