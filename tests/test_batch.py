"""Batch reprocessing on Dask (issue 14): the same documents as ``solve --json``, the same stored searches
as the server, re-runs that skip what is done, and the catalogue loaded once per worker process.

One real local Dask cluster (two worker processes, each loading the catalogue) serves the module; the
archive tests run on both backends (SQLite, and the session's PostgreSQL server).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from app.cli.batch import summary
from app.identification import SearchOptions
from app.storage import Storage
from app.workflow import AppContext
from app.workflow import batch
from app.workflow.archive import set_pattern
from app.workflow.documents import PatternDefinition
from app.workflow.files import solve_document, telemetry_files

REPO = Path(__file__).resolve().parent.parent


def _sample_files(sample_dir: Path) -> list[str]:
    return sorted(str(p) for p in sample_dir.iterdir()
                  if p.suffix in (".json", ".csv") and not p.name.endswith(".truth.json"))


@pytest.fixture(scope="module")
def cluster():
    cluster = batch.start_cluster(workers=2)
    try:
        yield cluster
    finally:
        cluster.close()


def _without_timing(doc: dict) -> dict:
    return {k: v for k, v in doc.items() if k != "elapsed_ms"}


def test_every_worker_loads_the_catalogue_once_and_searches_the_index_of_this_machine(cluster, sky):
    assert len(cluster.workers) == 2 and cluster.threads == 2
    assert len({info["pid"] for info in cluster.workers}) == 2 and os.getpid() not in {i["pid"] for i in cluster.workers}
    assert all(info["index"] == batch.index_record(sky) for info in cluster.workers)
    # The plugin loaded it when the worker joined; tasks find that very object (one per process).
    loaded = cluster.client.run(lambda: id(batch._SKY) if batch._SKY is not None else None)
    assert None not in loaded.values()
    again = cluster.client.run(lambda: id(batch.worker_sky()))
    assert again == loaded


def test_files_to_json_lines_match_solve_and_a_rerun_skips_what_is_done(cluster, sky, sample_dir, tmp_path):
    files = _sample_files(sample_dir)
    broken = tmp_path / "broken.json"
    broken.write_text('{"format": "tubsat-snapshots/1", "snapshots": "no"}')
    paths = files + [str(broken)]
    out = tmp_path / "results.jsonl"
    report = batch.files_to_jsonl(cluster, paths, out)
    assert (report.total, report.processed, report.invalid, report.skipped, report.failed) == (len(paths), len(files), 1, 0, 0)
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    by_file = {doc["file"]: doc for doc in lines}
    assert len(lines) == len(paths) == len(by_file)
    assert by_file[str(broken)]["status"] == "invalid" and "snapshots" in by_file[str(broken)]["error"]
    # The same document `solve --json` prints, computed here in this process.
    for path, sequence, problem in telemetry_files(files):
        assert problem is None
        expected = solve_document(path, sequence, sky, options=SearchOptions()).model_dump(mode="json")
        assert _without_timing(by_file[path]) == _without_timing(expected), path
    assert report.statuses == {status: sum(d["status"] == status for d in lines) for status in report.statuses}

    # A re-run does nothing; one cut short by a crash redoes only the file whose line was cut.
    before = out.read_bytes()
    again = batch.files_to_jsonl(cluster, paths, out)
    assert (again.skipped, again.processed, again.invalid) == (len(paths), 0, 0) and out.read_bytes() == before
    kept = before.splitlines(keepends=True)
    out.write_bytes(b"".join(kept[:-1]) + kept[-1][:25])
    cut = json.loads(kept[-1])["file"]
    third = batch.files_to_jsonl(cluster, paths, out)
    assert third.skipped == len(paths) - 1 and third.processed + third.invalid == 1
    redone = [json.loads(line) for line in out.read_text().splitlines()]
    assert sorted(d["file"] for d in redone) == sorted(paths) and redone[-1]["file"] == cut


def test_a_file_changed_since_its_line_is_solved_again_and_its_line_replaced(cluster, sample_dir, tmp_path):
    """A re-run goes by content (input_sha256), not by path: the broken file mended, or one file's telemetry
    replaced by another's at the same path, is solved again, and the output keeps one line per file."""
    first, second = tmp_path / "a.json", tmp_path / "b.json"
    first.write_bytes((sample_dir / "01-clean.json").read_bytes())
    second.write_text('{"format": "tubsat-snapshots/1", "snapshots": "no"}')
    paths, out = [str(first), str(second)], tmp_path / "results.jsonl"
    report = batch.files_to_jsonl(cluster, paths, out)
    assert (report.processed, report.invalid, report.again) == (1, 1, 0)
    lines = {doc["file"]: doc for doc in map(json.loads, out.read_text().splitlines())}
    assert lines[str(first)]["input_sha256"] == hashlib.sha256(b"a.json\0" + first.read_bytes()).hexdigest()

    first.write_bytes((sample_dir / "04-big-dipper.json").read_bytes())
    second.write_bytes((sample_dir / "03-jupiter.json").read_bytes())
    again = batch.files_to_jsonl(cluster, paths, out)
    assert (again.skipped, again.again, again.processed, again.invalid) == (0, 2, 2, 0)
    assert f"{again.skipped} skipped as done, 2 solved again (changed since their line, or failed)" in summary(again)
    now = [json.loads(line) for line in out.read_text().splitlines()]
    assert sorted(doc["file"] for doc in now) == sorted(paths)  # one line per file
    by_file = {doc["file"]: doc for doc in now}
    assert by_file[str(first)]["sequence_id"] == json.loads(first.read_text())["sequence_id"] != lines[str(first)][
        "sequence_id"]
    assert by_file[str(second)]["status"] != "invalid"
    assert batch.files_to_jsonl(cluster, paths, out).skipped == 2


def test_files_to_the_archive_store_searches_as_the_server_does_and_a_rerun_skips_them(
        cluster, sky, sample_dir, archive_url, tmp_path):
    files = _sample_files(sample_dir)[:5]
    report = batch.to_archive(archive_url, cluster, paths=files + files[:1])  # one file twice: stored once
    assert (report.processed, report.skipped, report.failed, report.invalid) == (len(files), 1, 0, 0), report.errors
    ctx = AppContext(storage=Storage.open(archive_url), sky=sky)
    try:
        rows, total = ctx.storage.list_sequences(0, 50)
        assert total == len(files)
        for row in rows:
            search = ctx.storage.latest_search(row.id)
            assert search is not None and search.method == "bright_pair"
            # The record the server's searches keep: options, index searched, camera calibration version.
            assert search.options["index"] == batch.index_record(sky)
            assert "camera_calibration" in search.options and search.pattern_version == 1
            assert ctx.storage.get_sequence(row.id).status == search.status
            assert [v.kind for v in ctx.storage.pattern_history(row.id)] == ["automatic"]
        assert sum(report.statuses.values()) == len(files)

        again = batch.to_archive(archive_url, cluster, paths=files)
        assert (again.processed, again.skipped) == (0, len(files))
        assert ctx.storage.health()["counts"]["searches"] == len(files)

        # The archive again: nothing to do until a sequence's pattern changes; then that one only.
        assert batch.to_archive(archive_url, cluster).skipped == len(files)
        edited = rows[0].id
        first_track = ctx.storage.get_sequence(edited).extraction["tracks"][0]["id"]
        set_pattern(ctx, edited, PatternDefinition(exclude_tracks=[first_track]), operator="ann")
        redo = batch.to_archive(archive_url, cluster)
        assert (redo.processed, redo.skipped, redo.failed) == (1, len(files) - 1, 0)
        newest = ctx.storage.latest_search(edited)
        assert newest.pattern_version == 2 and ctx.storage.health()["counts"]["searches"] == len(files) + 1

        # The same telemetry in other bytes (CRLF line endings) is another upload: the report names the one
        # stored before, as `upload` does, and so does the command's summary.
        crlf = tmp_path / "crlf-copy.json"
        crlf.write_bytes(Path(files[0]).read_bytes().replace(b"\n", b"\r\n"))
        first = next(row for row in rows if row.filename == Path(files[0]).name)
        other = batch.to_archive(archive_url, cluster, paths=[str(crlf)])
        assert other.processed == 1 and other.notes == [
            f'{crlf}: another stored upload (#{first.id} "{first.filename}") has the same spacecraft and sequence id; '
            "its telemetry differs in bytes (line endings, byte-order mark or content)"]
        assert f"  note: {other.notes[0]}" in summary(other).splitlines()
        assert again.notes == [] and redo.notes == []
    finally:
        ctx.close()
    # The workers closed the archive after the batch (the plugin's teardown).
    assert all(not opened for opened in cluster.client.run(lambda: list(batch._ARCHIVES)).values())


def test_invalid_files_are_reported_and_a_sqlite_archive_is_refused_for_an_existing_cluster(
        cluster, tmp_path, sample_dir):
    broken = tmp_path / "broken.json"
    broken.write_text('{"format": "tubsat-snapshots/1", "snapshots": "no"}')
    missing = str(tmp_path / "missing.json")
    report = batch.to_archive(str(tmp_path / "a.sqlite3"), cluster, paths=[str(broken), missing])
    assert (report.invalid, report.processed, report.failed) == (2, 0, 0)
    assert any("snapshots" in e for e in report.errors) and any("missing.json" in e for e in report.errors)
    remote = batch.Cluster(client=cluster.client, local=None, threads=cluster.threads, startup_s=0.0,
                           workers=cluster.workers)
    with pytest.raises(ValueError, match="postgresql"):
        batch.to_archive(str(tmp_path / "b.sqlite3"), remote, paths=_sample_files(sample_dir)[:1])
    assert not (tmp_path / "b.sqlite3").exists()


def test_the_command_runs_a_local_cluster_with_a_progress_bar_and_figures(tmp_path, sample_dir):
    out = tmp_path / "r.jsonl"
    files = _sample_files(sample_dir)[:3]
    run = subprocess.run([sys.executable, "-m", "app", "batch", *files, "--workers", "1", "--out", str(out), "--json"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    figures = json.loads(run.stdout)
    assert figures["processed"] == 3 and figures["workers"] == 1 and figures["sequences_per_s"] > 0
    assert "[" + "#" * 30 + "] 3/3" in run.stderr and "sequences/s" in run.stderr
    assert len(out.read_text().splitlines()) == 3
    for args in (["--archive", *files], [], ["--archive", "--out", str(out)]):
        refused = subprocess.run([sys.executable, "-m", "app", "batch", *args], cwd=REPO, capture_output=True,
                                 text=True, timeout=60)
        assert refused.returncode == 2 and "batch:" in refused.stderr
