"""`python -m app upload DIR_OR_FILES --server URL [--token T] [--fov-deg DEG] [--time ISO8601] [--search]`: send telemetry.

Directories are searched (not recursively) for ``*.json`` and ``*.csv``
files, leaving out ``*.truth.json`` (the simulator's truth files; stderr
says how many); files named explicitly are always sent.  Spot lists go to
``POST /api/sequences``.
Full frames go to ``POST /api/frames``, as ``solve`` reads them:
an image file named explicitly (FITS, PNG, JPEG, TIFF) is one pass, with
``<stem>.frames.json`` beside it as its sidecar if there is one; a
directory holding images is one pass of all of them, with its
``frames.json`` as the sidecar (not sent as a spot list).  ``--fov-deg``
(horizontal field of view, degrees, 0.1 to 120, known to +-5 %) is sent as
the passes' ``fov_deg`` field, ``--time`` (ISO 8601, the time of a pass of one frame) as their
``time`` field; a spot-list file is refused with either, unsent (it carries its own camera and
times), and the others go on.  A progress bar goes to stderr and one
line per file to stdout: ``created``, ``duplicate``, ``invalid`` with the
server's message, ``too large`` or ``error``; a stored file is followed by
an indented ``note:`` line when other stored uploads have its spacecraft
and sequence id (the same pass sent before in other bytes, e.g. CRLF line
endings or a byte-order mark: uploads are told apart by their exact
bytes).  ``--search`` asks the server to search each upload right after answering (bright pairs, the
``search=true`` of both endpoints, as the console's "search new uploads automatically" box does: a new
sequence, or one stored before and never searched), waits for that search (up to ``--timeout``) and prints
its outcome on an indented ``search:`` line, in the API's words (``identified``, ``ambiguous``,
``no_match``); a file stored and searched before keeps its search, which the line names.  The server is asked
for its health first, which checks the URL
(``--server`` is the server's base URL, without ``/api``) and gives the size limit, so that files above it are
reported without being sent (and none is read past it).  A device, FIFO or socket named as a file
(``/dev/zero``, a pipe) is refused unsent, before the server is asked anything: it has no size to
check, and reading it never ends or waits for a writer.  One file's failure never stops the folder;
only a server that cannot be reached at all does.  Exit status 0 when every
file was accepted (and every search asked for finished), 2 when some were refused (or a search asked for
did not finish within ``--timeout``), 1 when the server could not be reached (or is not a starid server).

Only the standard library is used (urllib), so no client package is needed.
"""

from __future__ import annotations

import argparse
import errno
import json
import math
import socket
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

# What files are, by name and kind: the rule every interface follows (a standard-library module).
from app.filenames import (FOLDER_SIDECAR, IMAGE_SUFFIXES, SPOT_LIST_SUFFIXES, TRUTH_SUFFIX, image_sidecar,
                           image_sidecars, passes_of_folder, special_file)
from app.timefmt import parse_utc_time, utc_text  # standard library only, as app.filenames

#: --fov-deg's bounds (the API's fov_deg field).
FOV_MIN_DEG, FOV_MAX_DEG = 0.1, 120.0
#: A file answered 503 (the server was busy past its time-out; nothing was stored) is sent again this
#: many times, after 1 s, then 2 s, ... (the server asks for a second with Retry-After).
BUSY_RETRIES = 2
BUSY_PAUSE_S = 1.0
BAR_WIDTH = 30
#: How often ``--search`` reads a sequence while its search runs (seconds).
SEARCH_POLL_S = 0.25
#: ``--time`` of ``upload``, ``extract`` and ``solve``.
TIME_HELP = ("the time of an image pass of one frame, ISO 8601 (UTC unless it says its zone, e.g. "
             "2024-03-12T21:04:10Z); wins over a sidecar's, the FITS header's and the EXIF time. Without any "
             "time a frame is solved at an assumed one (J2000.0, mean places, no planets) and says so. "
             "Refused for spot-list files, which carry their own times")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("paths", nargs="+", metavar="DIR_OR_FILE", help="telemetry files or directories of them")
    p.add_argument("--server", required=True, metavar="URL", help="server base URL, e.g. http://127.0.0.1:8000")
    p.add_argument("--token", default=None, help="bearer token (needed when the server is not on loopback)")
    p.add_argument("--timeout", type=timeout_s, default=60.0, metavar="SECONDS",
                   help="seconds to wait for each upload, a positive number (default 60)")
    p.add_argument("--fov-deg", type=fov_deg, default=None, metavar="DEG",
                   help="horizontal field of view of the image passes, degrees (0.1 to 120, known to +-5 %%; "
                        "wins over a sidecar's camera and the FITS header's optics); a spot-list file given "
                        "with it is refused, unsent: it carries its own camera")
    p.add_argument("--time", type=utc_time, default=None, metavar="ISO8601", help=TIME_HELP)
    p.add_argument("--search", action="store_true",
                   help="search each upload right after it is stored (bright pairs, as the console's 'search new "
                        "uploads automatically'), wait for it (up to --timeout) and print its outcome as the API "
                        "names it (identified, ambiguous, no_match) under the file's line")


def utc_time(text: str) -> datetime:
    """``--time`` of ``upload``, ``extract`` and ``solve``: an ISO 8601 time (:func:`app.timefmt.parse_utc_time`)."""
    try:
        return parse_utc_time(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def fov_deg(text: str) -> float:
    """``--fov-deg`` of ``upload``, ``extract`` and ``solve``: a finite number of degrees from 0.1 to 120."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or not FOV_MIN_DEG <= value <= FOV_MAX_DEG:
        raise argparse.ArgumentTypeError(f"must be a number from {FOV_MIN_DEG:g} to {FOV_MAX_DEG:g} degrees, "
                                         f"got {text!r}")
    return value


def timeout_s(text: str) -> float:
    """``--timeout``: a positive, finite number of seconds.  The socket module refuses a negative, NaN or
    infinite time-out with a traceback, and takes 0 as "never wait", which fails every connection."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text!r}")
    return value


def special_inputs(files: list[Path | FramePass]) -> tuple[list[Path | FramePass], list[str]]:
    """``(the inputs to send, a line per input refused unsent)``: a file named on the command line that is
    a device, FIFO or socket (see :func:`special_file`; a folder's files are regular already)."""
    kept, refused = [], []
    for item in files:
        kinds = [(path, special_file(path)) for path in (item.images if isinstance(item, FramePass) else (item,))]
        problems = [f"{path}: invalid (not sent): not a regular file ({kind})" for path, kind in kinds if kind]
        refused += problems
        if not problems:
            kept.append(item)
    return kept, refused


def is_image(path: Path) -> bool:
    return path.name.lower().endswith(IMAGE_SUFFIXES)


@dataclass(frozen=True)
class FramePass:
    """One pass of frames to send to ``/api/frames``: its label, images and optional sidecar."""

    label: Path
    images: tuple[Path, ...]
    sidecar: Path | None


def inputs(paths: list[str]) -> tuple[list[Path | FramePass], list[Path]]:
    """``(what to send, truth files left out)``: explicit files as given, then the telemetry files of each
    directory in name order, leaving out ``*.truth.json`` files, named or in a directory (a shell glob such
    as ``sample_telemetry/*.json`` names them), as ``solve`` does.

    An explicit image file is a :class:`FramePass` of its own; a directory holding images gives its passes
    (:func:`app.filenames.passes_of_folder`: one :class:`FramePass` of them all with its ``frames.json``, or one
    a photograph with its own sidecar), before its spot-list files.
    """
    files: list[Path | FramePass] = []
    truth: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            entries = sorted(p for p in path.iterdir() if p.is_file())
            passes, sidecars = passes_of_folder(entries), image_sidecars(entries)
            sidecar = path / FOLDER_SIDECAR
            if len(passes) == 1:
                files.append(FramePass(path, tuple(passes[0]), sidecar if sidecar.is_file() else None))
            else:
                files += [_picture(image) for (image,) in passes]
            spot_lists = [p for p in entries if p.suffix.lower() in SPOT_LIST_SUFFIXES
                          and not (passes and p.name == FOLDER_SIDECAR) and p not in sidecars]
            truth += [p for p in spot_lists if p.name.lower().endswith(TRUTH_SUFFIX)]
            files += [p for p in spot_lists if not p.name.lower().endswith(TRUTH_SUFFIX)]
        elif is_image(path):
            files.append(_picture(path))
        elif path.name.lower().endswith(TRUTH_SUFFIX):
            truth.append(path)
        else:
            files.append(path)
    return files, truth


def _picture(image: Path) -> FramePass:
    """One image as a pass of its own, with its ``<stem>.frames.json`` when there is one."""
    sidecar = image_sidecar(image)
    return FramePass(image, (image,), sidecar if sidecar.is_file() else None)


def truth_note(count: int) -> str:
    """The line saying how many truth files were left out."""
    return f"left out {count} truth file{'s' * (count != 1)} (*{TRUTH_SUFFIX}): the simulator's answers, not telemetry"


def progress_bar(done: int, total: int, label: str = "") -> str:
    """``[#######.......]  7/15 label`` (plain text)."""
    filled = BAR_WIDTH * done // max(total, 1)
    return f"[{'#' * filled}{'.' * (BAR_WIDTH - filled)}] {done}/{total} {label}"


def summary_line(name: str, status: int | None, doc: dict | None, error: str | None = None) -> str:
    """One line per file from the server's answer (status None: no answer); a stored file's note (other
    uploads of its spacecraft and sequence id) follows on an indented line."""
    if status in (200, 201) and doc:
        seq = doc.get("sequence", {})
        kind = "created" if status == 201 else "duplicate"
        line = f"{name}: {kind} id={doc.get('id')} sequence_id={seq.get('sequence_id')}"
        # The server's word on other stored uploads of this spacecraft and sequence id (the same pass in
        # other bytes); an older server sends none.
        return line + (f"\n  note: {doc['note']}" if isinstance(doc.get("note"), str) and doc["note"] else "")
    if status is None:
        return f"{name}: error: {error}"
    detail = (doc or {}).get("detail") or error or f"HTTP {status}"
    if status == 413:
        return f"{name}: too large (HTTP 413): {detail}"
    if status in (404, 405):
        return (f"{name}: refused (HTTP {status}): the server has no upload endpoint at this URL: "
                "--server must be the server's base URL, e.g. http://127.0.0.1:8000 (without /api)")
    if status == 503:
        return f"{name}: not processed (HTTP 503): {detail}"
    problems = (doc or {}).get("problems") or []
    text = f"{name}: invalid (HTTP {status}): {detail}"
    if len(problems) > 1:
        text += "".join(f"\n  {p.get('location')}: {p.get('message')}" for p in problems)
    return text


class ServerUnreachable(ConnectionError):
    """The server cannot be reached at all (refused, unknown host, not a starid server): stop the batch."""


def _unreachable(exc: BaseException) -> bool:
    """Whether a failed request means no server at all (rather than trouble with one request)."""
    reason = getattr(exc, "reason", exc)
    return isinstance(reason, (ConnectionRefusedError, socket.gaierror)) or (
        isinstance(reason, OSError) and reason.errno in (errno.ECONNREFUSED, errno.EHOSTUNREACH, errno.ENETUNREACH))


def server_health(server: str, token: str | None, timeout: float) -> dict:
    """The server's ``/api/health`` document; :class:`ServerUnreachable` saying what is wrong with the URL."""
    url = server.rstrip("/") + "/api/health"
    headers = {"Accept": "application/json", **({"Authorization": f"Bearer {token}"} if token else {})}
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout) as response:
            doc = _json(response.read())
            status = response.status
    except urllib.error.HTTPError as exc:
        doc, status = None, exc.code
    except (urllib.error.URLError, OSError) as exc:
        raise ServerUnreachable(f"cannot reach {server}: {getattr(exc, 'reason', exc)}") from None
    if status != 200 or not doc or "status" not in doc:
        answer = f"HTTP {status}" if status != 200 else "something other than the health document"
        raise ServerUnreachable(f"{server} does not look like a starid server (GET {url} gave {answer}): "
                                "--server must be the server's base URL, e.g. http://127.0.0.1:8000 (without /api)")
    return doc


def search_line(doc: dict | None, searched_now: bool, waited_s: float | None = None) -> str:
    """The indented line under a stored file's line saying what its search found: ``doc`` is the sequence
    as ``GET /api/sequences/{id}`` answers it (None: no answer), ``searched_now`` whether the upload queued
    the search (else it was searched before), ``waited_s`` how long it was waited for when it had not
    finished."""
    search = (doc or {}).get("search")
    if (doc or {}).get("status") == "new" or not isinstance(search, dict):
        waited = f" within {waited_s:g} s" if waited_s is not None else ""
        return (f"  search: not finished{waited} (the sequence is still new: search it from the console or "
                "POST /api/sequences/{id}/search; the server's log says why an automatic search failed)")
    n = len(search.get("candidates") or [])
    said = f"  search: {search.get('status')} ({n} candidate{'s' * (n != 1)}, search #{search.get('search_id')})"
    return said if searched_now else said + "; searched before, kept"


def wait_for_search(server: str, seq_id: int, token: str | None, timeout: float, wait_s: float) -> dict | None:
    """``GET /api/sequences/{seq_id}`` (each read given ``timeout`` seconds) once its status has left ``new``
    (its queued search stored), or the last answer read when ``wait_s`` seconds have passed (None if none
    came)."""
    url = f"{server.rstrip('/')}/api/sequences/{seq_id}"
    headers = {"Accept": "application/json", **({"Authorization": f"Bearer {token}"} if token else {})}
    deadline = time.monotonic() + wait_s
    doc = None
    while True:
        status, answer, _ = _send(server, urllib.request.Request(url, headers=headers), timeout)
        if status == 200 and answer is not None:
            doc = answer
            if doc.get("status") != "new":
                return doc
        if time.monotonic() >= deadline:
            return doc
        time.sleep(SEARCH_POLL_S)  # the search runs on the server after its answer: read again shortly


def upload_one(server: str, path: Path, token: str | None, timeout: float,
               max_bytes: int | None = None, search: bool = False) -> tuple[int | None, dict | None, str | None]:
    """POST the file as a raw body; (HTTP status, JSON answer, error text).

    A file above ``max_bytes`` (the server's limit) is not sent: it is
    answered here as the server would, 413; no more than one byte past
    the limit is read, whatever ``stat`` said.  Raises
    :class:`ServerUnreachable` only when no server answers at all; trouble
    with this one request (a reset, a time-out) is this file's error.
    """
    try:
        size = path.stat().st_size
        if max_bytes is not None and size > max_bytes:
            return 413, {"detail": f"the file is {size} bytes; the server accepts at most {max_bytes}"}, None
        with path.open("rb") as stream:  # one byte past the limit at most: the file may have grown since stat
            data = stream.read() if max_bytes is None else stream.read(max_bytes + 1)
        if max_bytes is not None and len(data) > max_bytes:
            return 413, {"detail": f"the file is over {max_bytes} bytes; the server accepts at most {max_bytes}"}, None
    except OSError as exc:
        return None, None, f"cannot read the file: {exc.strerror or exc}"
    media = "text/csv" if path.suffix.lower() == ".csv" else "application/json"
    query = {"filename": path.name, **({"search": "true"} if search else {})}
    url = server.rstrip("/") + "/api/sequences?" + urllib.parse.urlencode(query)
    headers = {"Content-Type": media, "Accept": "application/json"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    request = urllib.request.Request(url, data=data, headers=headers, method="POST")
    return _send(server, request, timeout)


def multipart_body(fields: list[tuple[str, str | None, bytes]]) -> tuple[bytes, str]:
    """``(body, content type)`` of a multipart/form-data request: ``(name, filename or None, data)`` parts."""
    boundary = "starid-" + uuid.uuid4().hex
    parts = []
    for name, filename, data in fields:
        disposition = f'form-data; name="{name}"'
        if filename is not None:
            safe = filename.replace("\\", "_").replace('"', "_").replace("\r", "_").replace("\n", "_")
            disposition += f'; filename="{safe}"'
        head = f"--{boundary}\r\nContent-Disposition: {disposition}\r\n"
        if filename is not None:
            head += "Content-Type: application/octet-stream\r\n"
        parts.append(head.encode("utf-8") + b"\r\n" + data + b"\r\n")
    return b"".join(parts) + f"--{boundary}--\r\n".encode(), f"multipart/form-data; boundary={boundary}"


def upload_pass(server: str, frame_pass: FramePass, token: str | None, timeout: float,
                fov: float | None = None, when: datetime | None = None,
                search: bool = False) -> tuple[int | None, dict | None, str | None]:
    """POST one pass of frames (and its sidecar, ``fov_deg`` and ``time``) to ``/api/frames``; as
    :func:`upload_one`."""
    try:
        fields = [("files", image.name, image.read_bytes()) for image in frame_pass.images]
        if frame_pass.sidecar is not None:
            fields.append(("sidecar", frame_pass.sidecar.name, frame_pass.sidecar.read_bytes()))
    except OSError as exc:
        return None, None, f"cannot read the file: {exc.strerror or exc}"
    if fov is not None:
        fields.append(("fov_deg", None, repr(float(fov)).encode()))
    if when is not None:
        fields.append(("time", None, utc_text(when).encode()))
    body, content_type = multipart_body(fields)
    headers = {"Content-Type": content_type, "Accept": "application/json"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    url = server.rstrip("/") + "/api/frames" + ("?search=true" if search else "")
    request = urllib.request.Request(url, data=body, headers=headers, method="POST")
    return _send(server, request, timeout)


def _send(server: str, request: urllib.request.Request, timeout: float) -> tuple[int | None, dict | None, str | None]:
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, _json(response.read()), None
    except urllib.error.HTTPError as exc:
        return exc.code, _json(exc.read()), exc.reason
    except (urllib.error.URLError, OSError) as exc:
        if _unreachable(exc):
            raise ServerUnreachable(f"cannot reach {server}: {getattr(exc, 'reason', exc)}") from None
        return None, None, f"the upload failed: {getattr(exc, 'reason', exc)}"


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
    files, truth = inputs(args.paths)
    if truth:
        print(truth_note(len(truth)), file=sys.stderr)
    files, special = special_inputs(files)  # before the server is asked anything: reading them never ends
    for line in special:
        print(line, flush=True)
    if not files:
        if not special:
            print("upload: no .json, .csv or image files found", file=sys.stderr)
        return 2
    fov = getattr(args, "fov_deg", None)
    when = getattr(args, "time", None)
    search = bool(getattr(args, "search", False))
    interactive = sys.stderr.isatty()
    end = "\r" if interactive else "\n"
    try:
        health = server_health(args.server, args.token, args.timeout)
    except ServerUnreachable as exc:
        print(f"upload: {exc}", file=sys.stderr)
        return 1
    max_bytes = health.get("max_upload_bytes")
    if health.get("compute_ready") is False:
        print(f"upload: the server is still loading its compiled kernels (its first start after an install compiles "
              f"them, about a minute): the first files wait for them, each for at most --timeout "
              f"({args.timeout:g} s)", file=sys.stderr)
    counts = {"created": 0, "duplicate": 0, "refused": len(special), "unsearched": 0}
    for k, item in enumerate(files):
        path = item.label if isinstance(item, FramePass) else item
        sys.stderr.write(progress_bar(k, len(files), path.name) + end)
        sys.stderr.flush()
        if (fov is not None or when is not None) and not isinstance(item, FramePass):
            if interactive:
                sys.stderr.write(" " * (BAR_WIDTH + 60) + "\r")
            option, what = ("--fov-deg", "camera") if fov is not None else ("--time", "times")
            print(f"{path}: invalid (not sent): {option} applies to image files and folders of frames only; "
                  f"a spot list carries its own {what}: upload it without {option}", flush=True)
            counts["refused"] += 1
            continue
        try:
            for attempt in range(1 + BUSY_RETRIES):
                if isinstance(item, FramePass):
                    status, doc, error = upload_pass(args.server, item, args.token, args.timeout, fov, when, search)
                else:
                    status, doc, error = upload_one(args.server, path, args.token, args.timeout,
                                                    max_bytes if isinstance(max_bytes, int) else None, search)
                if status != 503 or attempt == BUSY_RETRIES:
                    break
                time.sleep(BUSY_PAUSE_S * (attempt + 1))  # the server said: busy, try again shortly
            line = summary_line(str(path), status, doc, error)
            if search and status in (200, 201) and doc and isinstance(doc.get("id"), int):
                line += "\n" + searched(args, doc, status, counts)
        except ServerUnreachable as exc:
            sys.stderr.write("\n" if interactive else "")
            print(f"upload: {exc}", file=sys.stderr)
            return 1
        if interactive:  # clear the bar before the line
            sys.stderr.write(" " * (BAR_WIDTH + 60) + "\r")
        print(line, flush=True)
        counts["created" if status == 201 else "duplicate" if status == 200 else "refused"] += 1
    sys.stderr.write(progress_bar(len(files), len(files), "done") + "\n")
    total = len(files) + len(special)
    unsearched = f", {counts['unsearched']} not searched in time" if counts["unsearched"] else ""
    print(f"{total} file{'s' * (total != 1)}: {counts['created']} created, {counts['duplicate']} duplicate, "
          f"{counts['refused']} refused{unsearched}", file=sys.stderr)
    return 0 if counts["refused"] == 0 and counts["unsearched"] == 0 else 2


def searched(args: argparse.Namespace, doc: dict, status: int, counts: dict[str, int]) -> str:
    """``--search``: the search line of a stored upload (answer ``doc``, HTTP ``status``), after waiting for the
    search the server queued, if it queued one (a new sequence, or one never searched: the API's rule);
    counts a search not finished in time."""
    queued = status == 201 or (doc.get("sequence") or {}).get("status") == "new"
    started = time.monotonic()
    sequence = wait_for_search(args.server, doc["id"], args.token, args.timeout, args.timeout if queued else 0.0)
    line = search_line(sequence, queued, round(time.monotonic() - started, 1))
    counts["unsearched"] += line.startswith("  search: not finished")
    return line
