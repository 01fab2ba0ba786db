"""`python -m app batch (FILES | --archive) [--scheduler ADDRESS] [--workers N] [--out results.jsonl]`.

Extraction and identification of many sequences on Dask (see
:mod:`app.workflow.batch`):

* ``FILES --out results.jsonl``: one ``solve --json`` line per file, appended
  as chunks finish (in completion order; ``file`` names each line);
* ``FILES`` (no ``--out``): the files are stored in the archive (``--db``,
  else STARID_DB / DATABASE_URL / the default SQLite file) and searched, each
  search stored as the server stores it (method, catalogue index, camera
  calibration version), by the workers themselves;
* ``--archive``: every archived sequence is searched again.

Directories are read (not recursively) for ``*.json`` and ``*.csv``;
``*.truth.json`` files are left out, named or in a directory (stderr says how
many).  A re-run skips what is done (files whose line in the output was made
from the same content, ``input_sha256``; sequences whose latest search would
be reused) and solves again a file changed since its line, replacing it;
``--redo`` starts the JSON-lines output afresh.  By default a
local cluster of ``--workers`` processes (one per core) runs the work;
``--scheduler tcp://host:8786`` uses an existing Dask cluster (one whose scheduler does not answer within
20 s, :data:`app.workflow.batch.SCHEDULER_CONNECT_TIMEOUT_S`, is reported), whose workers need this
package installed, the files at the same paths (shared storage) and, to
store results, a ``postgresql://`` archive they can reach.  A progress bar goes to stderr, then the figures: how
many were done and skipped, and sequences per second (start-up excluded).
Exit status 0 when everything was processed, 2 when some input was invalid
or failed, 1 when the cluster or the archive could not be used.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

from app.cli.upload import BAR_WIDTH, inputs, progress_bar, truth_note
from app.filenames import special_file

METHODS = ("bright_pair", "tf")


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("paths", nargs="*", metavar="FILE_OR_DIR", help="telemetry files or directories of them")
    p.add_argument("--archive", action="store_true", help="search every archived sequence again (instead of FILES)")
    p.add_argument("--out", metavar="RESULTS.jsonl", default=None,
                   help="write one `solve --json` line per file here instead of storing into the archive")
    p.add_argument("--db", metavar="PATH_OR_URL", default=None,
                   help="the archive (SQLite path or postgresql:// URL; default STARID_DB, DATABASE_URL or "
                        "~/.local/share/starid/starid.sqlite3)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="an existing Dask scheduler, e.g. tcp://host:8786 (default: a local cluster)")
    p.add_argument("--workers", type=_positive, default=None, metavar="N",
                   help="worker processes of the local cluster (default: one per core)")
    p.add_argument("--method", choices=METHODS, default="bright_pair", help="identifier (default bright_pair)")
    p.add_argument("--candidates", type=_positive, default=None, metavar="N", help="candidates per sequence")
    p.add_argument("--redo", action="store_true", help="with --out: start the output afresh instead of skipping")
    p.add_argument("--json", action="store_true", help="print the figures as one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(message)s", stream=sys.stderr)
    if args.archive == bool(args.paths):
        print("batch: give FILES or --archive (one of them)", file=sys.stderr)
        return 2
    if args.archive and args.out:
        print("batch: --archive stores into the archive; --out is for FILES", file=sys.stderr)
        return 2
    if args.scheduler and args.workers:
        print("batch: --workers is for the local cluster; an existing cluster has its own workers", file=sys.stderr)
        return 2
    missing = [p for p in args.paths if not os.path.exists(p)]
    if missing:  # before a cluster starts for nothing (the workers read the paths the driver sees)
        print(f"batch: no such file or directory: {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}",
              file=sys.stderr)
        return 2
    if args.out is not None and (kind := special_file(args.out)):
        # It is read back to resume (the lines done): a device answers forever (/dev/full, /dev/zero) or waits.
        print(f"batch: --out {args.out}: not a regular file ({kind}); the output is read back to resume a batch, "
              "so it must be a file", file=sys.stderr)
        return 2
    special = [f"{p}: not a regular file ({kind})" for p in args.paths if (kind := special_file(p))]
    if special:  # a device or FIFO: reading it never ends (a folder's files are regular ones)
        print(f"batch: {'; '.join(special[:5])}{' ...' if len(special) > 5 else ''}", file=sys.stderr)
        return 2
    paths = None
    if args.paths:
        files, truth = inputs(args.paths)
        if truth:
            print(f"batch: {truth_note(len(truth))}", file=sys.stderr)
        paths = [str(p) for p in files]
    if paths is not None and not paths:
        print("batch: no .json or .csv files found", file=sys.stderr)
        return 2

    from app.storage import StorageError
    from app.workflow import batch

    interactive = sys.stderr.isatty()

    def progress(done: int, total: int, label: str) -> None:
        if interactive or done == total:
            sys.stderr.write(progress_bar(done, total, label) + ("\r" if interactive and done < total else "\n"))
            sys.stderr.flush()

    cluster = None
    try:
        database = None if args.out is not None else _database(args.db)
        n = args.workers or os.cpu_count() or 1
        where = args.scheduler or f"a local cluster of {n} worker process{'es' if n > 1 else ''}"
        into = f"into {args.out}" if args.out is not None else f"into the archive {_shown(database)}"
        print(f"batch: starting {where} (each loads the catalogue once), {into}...", file=sys.stderr)
        cluster = batch.start_cluster(args.scheduler, args.workers or os.cpu_count() or 1)
        if args.out is not None:
            report = batch.files_to_jsonl(cluster, paths, Path(args.out), method=args.method,
                                          max_candidates=args.candidates, redo=args.redo, progress=progress)
        else:
            report = batch.to_archive(database, cluster, paths=paths, method=args.method,
                                      max_candidates=args.candidates, progress=progress)
    except (StorageError, ValueError, OSError, TimeoutError) as exc:
        if interactive:
            sys.stderr.write(" " * (BAR_WIDTH + 20) + "\r")
        print(f"batch: {exc}", file=sys.stderr)
        return 1
    finally:
        if cluster is not None:
            cluster.close()
    if args.json:
        print(json.dumps(report.to_json()))
    print(summary(report), file=sys.stderr)
    return 0 if report.invalid == 0 and report.failed == 0 else 2


def _shown(database: str) -> str:
    """The archive as the operator should see it: a file path, or a PostgreSQL URL without its password."""
    if database.startswith(("postgresql://", "postgres://")):
        from app.storage.postgres import redacted

        return redacted(database)
    return database


def _database(given: str | None) -> str:
    """The archive every worker opens: --db, else STARID_DB / DATABASE_URL, else the default SQLite file."""
    from app.config import settings
    from app.storage import default_database_path

    return given or settings().database or str(default_database_path())


def summary(report) -> str:
    statuses = ", ".join(f"{n} {status}" for status, n in sorted(report.statuses.items())) or "none"
    rate = report.sequences_per_s
    lines = [f"{report.mode}: {report.total} sequences, {report.processed} processed ({statuses}), "
             f"{report.skipped} skipped as done, "
             + (f"{report.again} solved again (changed since their line, or failed), " if report.again else "")
             + f"{report.invalid} invalid, {report.failed} failed",
             f"{report.workers} worker{'s' if report.workers != 1 else ''} ({report.threads} thread"
             f"{'s' if report.threads != 1 else ''}), start-up {report.startup_s:.1f} s; "
             f"processing {report.processing_s:.2f} s"
             + (f" = {rate} sequences/s" if rate is not None else "")]
    lines += [f"  {message}" for message in report.errors[:10]]
    lines += [f"  note: {note}" for note in report.notes[:10]]
    return "\n".join(lines)
