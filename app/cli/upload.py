"""`python -m app upload DIR_OR_FILES --server URL [--token T]`: send telemetry files to a server.

Directories are searched (not recursively) for ``*.json`` and ``*.csv``
files, leaving out ``*.truth.json`` (the simulator's truth files); files
named explicitly are always sent.  A progress bar goes to stderr and one
line per file to stdout: ``created``, ``duplicate`` or ``invalid`` with the
server's message.  Exit status 0 when every file was accepted, 2 when some
were refused, 1 when the server could not be reached.

Only the standard library is used (urllib), so no client package is needed.
"""

from __future__ import annotations

import argparse
import json
import sys
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

SUFFIXES = (".json", ".csv")
BAR_WIDTH = 30


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("paths", nargs="+", metavar="DIR_OR_FILE", help="telemetry files or directories of them")
    p.add_argument("--server", required=True, metavar="URL", help="server base URL, e.g. http://127.0.0.1:8000")
    p.add_argument("--token", default=None, help="bearer token (needed when the server is not on loopback)")
    p.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for each upload (default 60)")


def telemetry_files(paths: list[str]) -> list[Path]:
    """Explicit files as given, then the telemetry files of each directory in name order."""
    files: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            files += sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in SUFFIXES
                            and not p.name.lower().endswith(".truth.json"))
        else:
            files.append(path)
    return files


def progress_bar(done: int, total: int, label: str = "") -> str:
    """``[#######.......]  7/15 label`` (plain text)."""
    filled = BAR_WIDTH * done // max(total, 1)
    return f"[{'#' * filled}{'.' * (BAR_WIDTH - filled)}] {done}/{total} {label}"


def summary_line(name: str, status: int | None, doc: dict | None, error: str | None = None) -> str:
    """One line per file from the server's answer (status None: no answer)."""
    if status in (200, 201) and doc:
        seq = doc.get("sequence", {})
        kind = "created" if status == 201 else "duplicate"
        return f"{name}: {kind} id={doc.get('id')} sequence_id={seq.get('sequence_id')}"
    if status is None:
        return f"{name}: error: {error}"
    detail = (doc or {}).get("detail") or error or f"HTTP {status}"
    problems = (doc or {}).get("problems") or []
    text = f"{name}: invalid (HTTP {status}): {detail}"
    if len(problems) > 1:
        text += "".join(f"\n  {p.get('location')}: {p.get('message')}" for p in problems)
    return text


def upload_one(server: str, path: Path, token: str | None, timeout: float) -> tuple[int | None, dict | None, str | None]:
    """POST the file as a raw body; (HTTP status, JSON answer, error text)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        return None, None, f"cannot read the file: {exc.strerror or exc}"
    media = "text/csv" if path.suffix.lower() == ".csv" else "application/json"
    url = server.rstrip("/") + "/api/sequences?" + urllib.parse.urlencode({"filename": path.name})
    headers = {"Content-Type": media, "Accept": "application/json"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    request = urllib.request.Request(url, data=data, headers=headers, method="POST")
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, _json(response.read()), None
    except urllib.error.HTTPError as exc:
        return exc.code, _json(exc.read()), exc.reason
    except (urllib.error.URLError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise ConnectionError(f"cannot reach {server}: {reason}") from None


def _json(raw: bytes) -> dict | None:
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def run(args: argparse.Namespace) -> int:
    if urllib.parse.urlparse(args.server).scheme not in ("http", "https"):
        print(f"upload: --server must be an http:// or https:// URL, not {args.server!r}", file=sys.stderr)
        return 2
    files = telemetry_files(args.paths)
    if not files:
        print("upload: no .json or .csv files found", file=sys.stderr)
        return 2
    interactive = sys.stderr.isatty()
    end = "\r" if interactive else "\n"
    counts = {"created": 0, "duplicate": 0, "refused": 0}
    for k, path in enumerate(files):
        sys.stderr.write(progress_bar(k, len(files), path.name) + end)
        sys.stderr.flush()
        try:
            status, doc, error = upload_one(args.server, path, args.token, args.timeout)
        except ConnectionError as exc:
            sys.stderr.write("\n" if interactive else "")
            print(f"upload: {exc}", file=sys.stderr)
            return 1
        line = summary_line(str(path), status, doc, error)
        if interactive:  # clear the bar before the line
            sys.stderr.write(" " * (BAR_WIDTH + 60) + "\r")
        print(line, flush=True)
        counts["created" if status == 201 else "duplicate" if status == 200 else "refused"] += 1
    sys.stderr.write(progress_bar(len(files), len(files), "done") + "\n")
    print(f"{len(files)} files: {counts['created']} created, {counts['duplicate']} duplicate, "
          f"{counts['refused']} refused", file=sys.stderr)
    return 0 if counts["refused"] == 0 else 2
