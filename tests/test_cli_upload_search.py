"""`python -m app upload --search`: the upload asks the server for its automatic search (``search=true``, as the
console's "search new uploads automatically" does), waits for it and prints its outcome in the API's words.

Against a real server in a thread (tests/test_cli_fov.py's ``live_server``): the printed status, candidate count
and search id are the ones the API then answers for the sequence, and the samples' known outcomes hold
(01-clean is identified; 05-earth, clouds and glints with no star, is no match).
"""

from __future__ import annotations

import json
import re
import urllib.request

from app.cli import main as cli_main
from test_cli_fov import live_server  # noqa: F401  (the fixture)

SEARCH_LINE = re.compile(r"^  search: (\w+) \((\d+) candidates?, search #(\d+)\)(; searched before, kept)?$")


def _get(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=30) as response:
        return json.loads(response.read())


def _outcomes(out: str) -> dict[str, tuple[int, re.Match]]:
    """File name -> (archive id, its search line's match), from upload's stdout."""
    lines = out.splitlines()
    found = {}
    for k, line in enumerate(lines):
        stored = re.match(r"^(.+): (created|duplicate) id=(\d+) ", line)
        if stored:
            search = next(SEARCH_LINE.match(s) for s in lines[k + 1:] if s.startswith("  search: "))
            found[stored.group(1).rsplit("/", 1)[-1]] = (int(stored.group(3)), search)
    return found


def test_upload_search_prints_what_the_search_found(live_server, sample_dir, capsys):  # noqa: F811
    url, _ = live_server
    clean, earth = sample_dir / "01-clean.json", sample_dir / "05-earth.json"
    assert cli_main(["upload", str(clean), str(earth), "--server", url, "--search"]) == 0
    out = capsys.readouterr().out
    outcomes = _outcomes(out)
    assert set(outcomes) == {"01-clean.json", "05-earth.json"}, out
    expected = {"01-clean.json": "identified", "05-earth.json": "no_match"}  # the samples' README
    for name, (seq_id, line) in outcomes.items():
        assert line is not None and line.group(4) is None, out
        detail = _get(f"{url}/api/sequences/{seq_id}")
        search = detail["search"]
        assert (line.group(1), int(line.group(2)), int(line.group(3))) == \
            (search["status"], len(search["candidates"]), search["search_id"])
        assert search["status"] == expected[name] and search["method"] == "bright_pair"

    # Sent again: the same sequences, searched before; their searches are kept and named, not redone.
    assert cli_main(["upload", str(clean), "--server", url, "--search"]) == 0
    again = _outcomes(capsys.readouterr().out)
    seq_id, line = again["01-clean.json"]
    assert seq_id == outcomes["01-clean.json"][0] and line.group(4) == "; searched before, kept"
    assert int(line.group(3)) == int(outcomes["01-clean.json"][1].group(3))


def test_upload_without_search_searches_nothing_and_a_later_search_upload_does(live_server, sample_dir,
                                                                              capsys):  # noqa: F811
    url, _ = live_server
    path = sample_dir / "06-sparse.json"
    assert cli_main(["upload", str(path), "--server", url]) == 0
    out = capsys.readouterr().out
    assert "search:" not in out
    seq_id = int(re.search(r"created id=(\d+)", out).group(1))
    assert _get(f"{url}/api/sequences/{seq_id}")["status"] == "new"
    # Stored before but never searched: --search has it searched now (the API's rule), and says so.
    assert cli_main(["upload", str(path), "--server", url, "--search"]) == 0
    (got_id, line), = _outcomes(capsys.readouterr().out).values()
    assert got_id == seq_id and line.group(4) is None
    detail = _get(f"{url}/api/sequences/{seq_id}")
    assert line.group(1) == detail["search"]["status"] == "identified"
