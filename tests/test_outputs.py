"""Output paths: a file is replaced through a temporary file, a link's target likewise (the link stays), a FIFO or
a character device is written through and never replaced, and what cannot be written is refused in one line."""

import json
import os
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from helpers import exactly

import symsbl
from symsbl._cli import main


@pytest.fixture(scope="module")
def model(duffing_short):
    x1, x2, F = symsbl.symbols("x1 x2 F")
    return symsbl.identify(duffing_short, symsbl.polynomial([x1, x2], 1) + symsbl.inputs([F]), refine=False)


@pytest.fixture(scope="module")
def record_file(tmp_path_factory, duffing_short):
    path = tmp_path_factory.mktemp("record") / "train.csv"
    symsbl.write_trajectory(duffing_short.slice(0, 800), path)
    return path


@pytest.fixture()
def model_file(tmp_path, model):
    path = tmp_path / "model.json"
    model.save(path)
    return path


def _drain(fifo: Path) -> tuple[threading.Thread, list]:
    """A reader on ``fifo`` (a writer's open blocks until one exists), collecting what it reads."""
    got: list = []

    def read():
        with open(fifo, "rb") as fh:
            got.append(fh.read())

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return thread, got


def _char_device(tmp_path: Path) -> Path:
    """A private copy of /dev/null (never the machine's own): root only."""
    if os.geteuid() != 0:
        pytest.skip("making a device node needs root")
    node = tmp_path / "null"
    os.mknod(node, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    return node


def test_a_symbolic_link_is_followed_and_stays_a_link(tmp_path, model):
    target = tmp_path / "target.json"
    target.write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to("target.json")
    model.save(link)
    assert link.is_symlink() and os.readlink(link) == "target.json"
    assert json.loads(target.read_text())["format"] == "symsbl-model"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "target.json"]  # no temporary file left


def test_a_dangling_link_creates_its_target_or_is_refused(tmp_path, model):
    (tmp_path / "dir").mkdir()
    link = tmp_path / "dangling.json"
    link.symlink_to("dir/new.json")
    model.save(link)
    assert link.is_symlink() and (tmp_path / "dir" / "new.json").is_file()
    lost = tmp_path / "lost.json"
    lost.symlink_to("nowhere/new.json")
    with pytest.raises(
        symsbl.DataError,
        match=exactly(
            f"path: expected a file in an existing directory, received {str(lost)!r} (a symbolic link to "
            f"{str(tmp_path / 'nowhere' / 'new.json')!r}); create {str(tmp_path / 'nowhere')!r} first"
        ),
    ):
        model.save(lost)
    assert lost.is_symlink() and not (tmp_path / "nowhere").exists()


def test_a_loop_of_links_is_refused(tmp_path, model):
    (tmp_path / "a").symlink_to("b")
    (tmp_path / "b").symlink_to("a")
    with pytest.raises(
        symsbl.DataError,
        match=exactly(
            f"path: expected a path that can be opened, received {str(tmp_path / 'a')!r} (Too many levels of "
            "symbolic links)"
        ),
    ):
        model.save(tmp_path / "a")


def test_a_fifo_is_written_through_not_replaced(tmp_path, model):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    thread, got = _drain(fifo)
    model.save(fifo)
    thread.join(10)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert json.loads(got[0])["format"] == "symsbl-model"


def test_a_character_device_is_written_through_not_replaced(tmp_path, model, record_file, capsys):
    node = _char_device(tmp_path)
    model.save(node)
    assert stat.S_ISCHR(os.lstat(node).st_mode)
    code = main(
        [
            "identify",
            str(record_file),
            "--states",
            "x1,x2",
            "--inputs",
            "F",
            "--library",
            "poly",
            "--degree",
            "1",
            "--no-refine",
            "--quiet",
            "--json",
            str(node),
        ]
    )
    assert code == 0 and stat.S_ISCHR(os.lstat(node).st_mode)
    assert capsys.readouterr().out.endswith(f"model written to {node}\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["null"]


def test_dev_stdout_redirected_to_a_file_gets_the_model_after_what_was_printed(tmp_path, record_file):
    out = tmp_path / "out.txt"
    with open(out, "w") as fh:
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "symsbl",
                "identify",
                str(record_file),
                "--states",
                "x1,x2",
                "--inputs",
                "F",
                "--library",
                "poly",
                "--degree",
                "1",
                "--no-refine",
                "--quiet",
                "--json",
                "/dev/stdout",
            ],
            stdout=fh,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONPATH": str(Path(symsbl.__file__).parents[1])},
        )
    assert proc.returncode == 0, proc.stderr
    text = out.read_text()
    head, rest = text.split("{\n", 1)
    assert head.startswith("identified from 800 samples") and rest.endswith("}\nmodel written to /dev/stdout\n")
    assert json.loads("{\n" + rest.removesuffix("model written to /dev/stdout\n"))["format"] == "symsbl-model"


@pytest.mark.parametrize(
    "path, message",
    [
        ("", "path: expected a file path, received ''; name the file to write"),
        (".", "path: expected a file path, received '.', which is a directory"),
    ],
)
def test_an_empty_path_or_a_directory_is_refused(model, path, message):
    with pytest.raises(symsbl.DataError, match=exactly(message)):
        model.save(path)


def test_a_socket_is_refused(tmp_path, model):
    import socket

    where = tmp_path / "sock"
    with socket.socket(socket.AF_UNIX) as server:
        server.bind(str(where))
        with pytest.raises(
            symsbl.DataError,
            match=exactly(
                f"path: expected a file, a FIFO or a character device, received {str(where)!r}, which is a socket; "
                "choose a file name"
            ),
        ):
            model.save(where)


def _cli(argv, capsys):
    code = main([*argv, "--quiet"])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_an_empty_json_path_is_refused_before_any_work(model_file, record_file, capsys):
    code, out, err = _cli(["validate", str(model_file), str(record_file), "--json", ""], capsys)
    assert (code, out) == (2, "")
    assert err == "symsbl validate: error: --json: expected a file path, received ''; name the file to write\n"


def test_json_and_plot_on_one_file_are_refused_before_any_work(tmp_path, model_file, record_file, capsys):
    pytest.importorskip("matplotlib")
    report = tmp_path / "r.png"
    code, out, err = _cli(
        ["validate", str(model_file), str(record_file), "--json", str(report), "--plot", str(report)], capsys
    )
    assert (code, out) == (2, "") and not report.exists()
    assert err == (
        f"symsbl validate: error: --plot: expected a file other than --json's, received {str(report)!r}, "
        "which --json writes too; give each output its own file\n"
    )
    link = tmp_path / "link.png"
    link.symlink_to(report.name)
    code, _, err = _cli(
        ["validate", str(model_file), str(record_file), "--json", str(report), "--plot", str(link)], capsys
    )
    assert code == 2 and err == (
        f"symsbl validate: error: --plot: expected a file other than --json's, received "
        f"{str(link)!r}, which --json writes too (as {str(report)!r}); give each output its "
        "own file\n"
    )
