"""Hostile inputs on the command line: devices and FIFOs named as files, bad time-outs, a scheduler that is not there.

Every command here that could hang runs in a subprocess under a time-out, so that a hang fails the test
instead of blocking the suite.
"""

from __future__ import annotations

import json
import os
import pathlib
import socket
import subprocess
import sys
import time

import pytest

from app.bench.server import REPO
from app.cli import main as cli_main
from app.cli import upload

#: A hang fails the test after this long (each command below answers within seconds, or 20 s for the scheduler).
HANG_S = 60
#: An address where nothing listens: the refusal of a device must come before any use of the network.
NO_SERVER = "http://127.0.0.1:9"


def _run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "app", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=HANG_S)


@pytest.fixture
def special_files(tmp_path) -> tuple[str, str]:
    """``zero.json``, a symbolic link to /dev/zero (endless), and ``fifo.json``, a FIFO nobody writes to."""
    zero, fifo = tmp_path / "zero.json", tmp_path / "fifo.json"
    zero.symlink_to("/dev/zero")
    os.mkfifo(fifo)
    return str(zero), str(fifo)


def test_solve_refuses_a_device_and_a_fifo_unread_and_goes_on(special_files, sample_dir):
    zero, fifo = special_files
    good = str(sample_dir / "07-single.json")
    done = _run_cli("solve", zero, fifo, good, "--json")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert [line["file"] for line in lines] == [zero, fifo, good]
    assert lines[0]["error"] == f"{zero}: invalid telemetry: file: not a regular file (a character device)"
    assert lines[1]["error"] == f"{fifo}: invalid telemetry: file: not a regular file (a FIFO)"
    assert lines[0]["input_sha256"] is None and lines[1]["input_sha256"] is None
    assert lines[2]["status"] != "invalid"


def test_upload_refuses_a_device_and_a_fifo_before_asking_the_server(special_files):
    zero, fifo = special_files
    done = _run_cli("upload", zero, fifo, "--server", NO_SERVER)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stdout.splitlines() == [f"{zero}: invalid (not sent): not a regular file (a character device)",
                                        f"{fifo}: invalid (not sent): not a regular file (a FIFO)"]
    assert "cannot reach" not in done.stderr  # no server was asked


def test_upload_reads_no_more_than_one_byte_past_the_servers_limit(tmp_path, monkeypatch):
    """A file that grew past the limit after ``stat`` (here: a stat saying 0 bytes, as a device's does) is
    answered 413 from what was read, unsent."""
    path = tmp_path / "grown.json"
    path.write_bytes(b"{" + b" " * 100 + b"}")
    monkeypatch.setattr(pathlib.Path, "stat", lambda self, **kw: os.stat_result((0,) * 10))
    status, doc, error = upload.upload_one(NO_SERVER, path, None, 5.0, max_bytes=10)
    assert (status, error) == (413, None)
    assert doc["detail"] == "the file is over 10 bytes; the server accepts at most 10"


def test_batch_refuses_a_device_before_starting_a_cluster(special_files, tmp_path, capsys, monkeypatch):
    from app.workflow import batch

    def no_cluster(*args, **kwargs):
        raise AssertionError("a cluster was started for a device")

    monkeypatch.setattr(batch, "start_cluster", no_cluster)
    zero, fifo = special_files
    assert cli_main(["batch", zero, fifo, "--out", str(tmp_path / "o.jsonl")]) == 2
    assert capsys.readouterr().err.strip() == (f"batch: {zero}: not a regular file (a character device); "
                                               f"{fifo}: not a regular file (a FIFO)")


def test_batch_refuses_a_device_as_its_output_before_starting_a_cluster(special_files, sample_dir, capsys,
                                                                      monkeypatch):
    """``--out /dev/full`` was read back to resume (answered_files) for ever: 35 s of a growing process, then
    the kernel killed it (exit 137)."""
    from app.workflow import batch

    def no_cluster(*args, **kwargs):
        raise AssertionError("a cluster was started to write into a device")

    monkeypatch.setattr(batch, "start_cluster", no_cluster)
    zero, _ = special_files
    assert cli_main(["batch", str(sample_dir / "01-clean.json"), "--out", zero]) == 2
    assert capsys.readouterr().err.strip() == (f"batch: --out {zero}: not a regular file (a character device); the "
                                               "output is read back to resume a batch, so it must be a file")


@pytest.mark.parametrize("value", ["-1", "nan", "0", "inf", "soon"])
def test_upload_refuses_a_timeout_that_is_not_a_positive_number(value, capsys):
    with pytest.raises(SystemExit) as stopped:
        cli_main(["upload", "x.json", "--server", NO_SERVER, "--timeout", value])
    assert stopped.value.code == 2
    assert f"argument --timeout: must be a positive number of seconds, got '{value}'" in capsys.readouterr().err


def test_batch_on_a_scheduler_that_refuses_connections_fails_soon_naming_it(tmp_path, sample_dir):
    """Within app.workflow.batch.SCHEDULER_CONNECT_TIMEOUT_S (20 s) and the start-up, not CLUSTER_TIMEOUT_S (300 s)."""
    with socket.socket() as bound:  # bound, not listening: connections are refused, and no one else takes the port
        bound.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{bound.getsockname()[1]}"
        t0 = time.monotonic()
        done = _run_cli("batch", str(sample_dir / "07-single.json"), "--out", str(tmp_path / "o.jsonl"),
                        "--scheduler", address)
        elapsed = time.monotonic() - t0
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert f"batch: no Dask scheduler answered at {address} within 20 s" in done.stderr
    assert elapsed < 45
