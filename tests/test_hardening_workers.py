"""Issue 12, item 4: the compute pool's workers live and die with the server; deadlines and limits hold.

Every process a test starts carries a marker in its environment, which its
children inherit; a process of this test is found by that marker in
``/proc/<pid>/environ``, whoever its parent is by then (a worker orphaned by
a SIGKILL is re-parented to init, so a walk down from the dead server would
miss exactly the processes this is about).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import pytest

from app.bench.server import REPO, free_port, start_server, wait_ready
from app.workflow.compute import BULK, ComputePool, JobExpired, JobKilled, WorkerLost

MARKER = "STARID_TEST_MARKER"
#: How long processes may take to exit once their server is gone (the parent-death signal is
#: immediate; the watcher thread polls every 0.2 s).
EXIT_DEADLINE_S = 10.0

JOBS = '''
import os, sys, time


def pid(*, sky=None):
    return os.getpid()


def announce_and_sleep(seconds, *, sky=None):
    print("job running", flush=True)
    time.sleep(seconds)


def crash(*, sky=None):
    os._exit(3)


def scheduler(*, sky=None):
    return os.sched_getscheduler(0)
'''

PARENT = '''
import sys, time
sys.path.insert(0, sys.argv[2])
import jobs
from app.workflow.compute import BULK, ComputePool

if __name__ == "__main__":
    stage = sys.argv[1]
    pool = ComputePool(1, load_sky=False, bulk_processes=1)  # one worker per lane: both kinds, quick to start
    print("pool created", flush=True)
    if stage != "starting":
        pool.submit(jobs.pid).result(120)
        pool.submit_within(jobs.pid, lane=BULK).result(120)
        print("workers idle", flush=True)
    if stage == "busy":
        pool.submit(jobs.announce_and_sleep, 120)
    if stage == "stop":
        pool.shutdown()
        print("stopped", flush=True)
        sys.exit(0)
    time.sleep(300)  # stays alive until the test kills it
'''


def marked_processes(marker: str) -> list[int]:
    """Live (not zombie) processes whose environment carries ``MARKER=marker``."""
    needle = f"{MARKER}={marker}".encode()
    found = []
    for environ in Path("/proc").glob("[0-9]*/environ"):
        try:
            if needle not in environ.read_bytes().split(b"\0"):
                continue
            state = (environ.parent / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            found.append(int(environ.parent.name))
    return found


def wait_until_gone(marker: str, deadline_s: float = EXIT_DEADLINE_S) -> list[int]:
    """Poll until no marked process is left or the deadline passes; the survivors."""
    deadline = time.monotonic() + deadline_s
    alive = marked_processes(marker)
    while alive and time.monotonic() < deadline:
        time.sleep(0.05)
        alive = marked_processes(marker)
    return alive


def read_until(process: subprocess.Popen, wanted: str, deadline_s: float = 120.0) -> None:
    """Read the process's stdout lines until one equals ``wanted`` (fail on exit or deadline)."""
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        if not line:
            pytest.fail(f"the process ended before {wanted!r}: {process.stderr.read()}")
        if line.strip() == wanted:
            return
    pytest.fail(f"no {wanted!r} within {deadline_s} s")


@pytest.fixture
def pool_script(tmp_path):
    (tmp_path / "jobs.py").write_text(JOBS)
    (tmp_path / "parent.py").write_text(PARENT)

    def start(stage: str) -> tuple[subprocess.Popen, str]:
        marker = uuid.uuid4().hex
        process = subprocess.Popen([sys.executable, str(tmp_path / "parent.py"), stage, str(tmp_path)], cwd=REPO,
                                   env={**os.environ, MARKER: marker, "PYTHONUNBUFFERED": "1"},
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        return process, marker
    return start


def test_no_worker_or_tracker_survives_a_sigkilled_parent_20_times(pool_script):
    """Killed while the workers start (the race that left orphans), while idle and while a job runs."""
    stages = {"starting": "pool created", "idle": "workers idle", "busy": "job running"}
    for attempt in range(20):
        stage = list(stages)[attempt % 3]
        process, marker = pool_script(stage)
        try:
            read_until(process, stages[stage])
            if stage != "starting":
                children = [pid for pid in marked_processes(marker) if pid != process.pid]
                assert len(children) >= 2, children  # an interactive and a bulk worker (+ the tracker)
        finally:
            process.kill()
            process.wait(30)
            process.stdout.close()
            process.stderr.close()
        survivors = wait_until_gone(marker)
        assert not survivors, f"attempt {attempt} ({stage}): still alive {survivors}"


def test_a_normal_stop_is_clean(pool_script):
    process, marker = pool_script("stop")
    out, err = process.communicate(timeout=120)
    assert process.returncode == 0, err
    assert "stopped" in out
    assert "leaked" not in err and "resource_tracker" not in err and "Traceback" not in err, err
    assert not wait_until_gone(marker)


def test_deadlines_hard_limits_and_crashes_are_reported_and_the_pool_recovers(tmp_path, monkeypatch):
    (tmp_path / "jobs.py").write_text(JOBS)
    monkeypatch.syspath_prepend(str(tmp_path))
    import jobs

    pool = ComputePool(1, load_sky=False, bulk_processes=1, hard_limit_s=2.0)
    try:
        first = pool.submit(jobs.pid).result(120)
        busy = pool.submit(jobs.announce_and_sleep, 1.0)  # holds the only interactive worker
        late = pool.submit_within(jobs.pid, deadline=time.monotonic() + 0.2)
        with pytest.raises(JobExpired):
            late.result(30)  # answered at its deadline, while the worker is still busy
        assert not busy.done()
        busy.result(30)
        with pytest.raises(JobKilled):  # a job with a deadline has the pool's hard limit (2 s here)
            pool.submit_within(jobs.announce_and_sleep, 60, deadline=time.monotonic() + 30).result(60)
        with pytest.raises(WorkerLost):
            pool.submit(jobs.crash).result(60)
        again = pool.submit(jobs.pid).result(120)  # a replacement worker serves
        assert again != first and again in pool.pids()
        assert pool.submit_within(jobs.pid, lane=BULK).result(120) in pool.pids()
        # The bulk lane runs only on CPU time nothing else wants; the interactive one normally.
        assert pool.submit_within(jobs.scheduler, lane=BULK).result(120) == os.SCHED_IDLE
        assert pool.submit(jobs.scheduler).result(120) == os.SCHED_OTHER
        queued = [pool.submit(jobs.announce_and_sleep, 0.5) for _ in range(3)]
        assert queued[2].cancel()  # still waiting: cancelling removes it
        queued[1].result(30)
        assert queued[2].cancelled()
    finally:
        workers = pool.pids()
        pool.shutdown()
    assert all(not Path(f"/proc/{pid}").exists() or
               (Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z") for pid in workers)


def test_the_server_stops_cleanly_and_logs_its_setup(tmp_path):
    """SIGTERM: exit status 0, no leaked-semaphore warning, nothing left behind; the start-up log names
    the database and the default camera (item 5)."""
    marker = uuid.uuid4().hex
    log = tmp_path / "server.log"
    port = free_port()
    server = start_server(tmp_path / "db.sqlite3", port, log, ("--no-viewer",),
                          env={MARKER: marker, "STARID_DEFAULT_CAMERA": "liebe-576x604-30deg"})
    try:
        wait_ready(port, server, log)
        assert len(marked_processes(marker)) >= 4  # the server, 2 + 1 workers (and the tracker)
    finally:
        server.send_signal(signal.SIGTERM)
        status = server.wait(60)
    text = log.read_text()
    assert status == 0, text[-3000:]
    assert "leaked" not in text and "Traceback" not in text, text[-3000:]
    assert not wait_until_gone(marker)
    assert f"database: {tmp_path / 'db.sqlite3'}" in text
    assert "default camera (files without a camera block): liebe-576x604-30deg (576x604 px" in text
    assert textwrap.dedent("magnitude limit 4.5") in text


def test_a_stop_sent_to_every_process_is_not_taken_for_crashed_workers(tmp_path):
    """SIGTERM to the server and its workers at once (Ctrl-C in a terminal, a service manager stopping
    the control group): exit status 0, and no worker reported dead or replaced while stopping."""
    marker = uuid.uuid4().hex
    log = tmp_path / "server.log"
    port = free_port()
    server = start_server(tmp_path / "db.sqlite3", port, log, ("--no-viewer",), env={MARKER: marker})
    try:
        wait_ready(port, server, log)
        everyone = marked_processes(marker)
        assert len(everyone) >= 4  # the server, 2 + 1 workers (and the tracker)
    finally:
        for pid in marked_processes(marker):
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        status = server.wait(60)
    text = log.read_text()
    assert status == 0, text[-3000:]
    assert "starting another" not in text and "Traceback" not in text, text[-3000:]
    assert not wait_until_gone(marker)
