"""The manual: the site builds without a broken link, and every command and REST route is documented.

* The MkDocs site (``mkdocs.yml``, ``docs/``) builds with ``--strict``: a link to a missing page, an
  anchor no heading makes, or a page left out of the nav is a warning there (``validation`` in
  ``mkdocs.yml``), and strict turns warnings into a failed build.  That the build does fail on each of
  those is checked on a copy of the site with one fault put in.  The README's links into docs/ must
  reach a built page and, where they name one, an anchor of it.
* Every subcommand of ``python -m app`` (read from its argparse parser) has a row in the command table
  of ``docs/cli-and-api.md``, and every row names a real command.
* Every route of the FastAPI application (``app.api.create_app``) is in the endpoint table of
  ``docs/cli-and-api.md`` as ``METHOD /api/path``, and every ``METHOD /api/...`` any page or the README
  names is a real route.  Path parameters are compared by position only (``{id}`` in the manual,
  ``{seq_id}`` in the code).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.routing import APIRoute

from app.api import create_app
from app.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
CLI_AND_API = DOCS / "cli-and-api.md"

HTTP_METHODS = ("GET", "POST", "PUT", "PATCH", "DELETE")
#: ``METHOD /api/path`` as the manual writes it; a query (``?...``) or an optional part (``[...]``) ends the path.
ENDPOINT = re.compile(r"\b(" + "|".join(HTTP_METHODS) + r") (/api[^\s`?\[,|)]*)")


# -- the site -----------------------------------------------------------------

def build_site(config: Path, out: Path) -> subprocess.CompletedProcess:
    # Not -q: mkdocs counts warnings for --strict only at the log level it prints, so a quiet strict build
    # passes with broken links (the faults below caught that).
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(out)],
                          cwd=config.parent, capture_output=True, text=True, timeout=300)


def test_the_site_builds_in_strict_mode_with_every_page(tmp_path):
    done = build_site(ROOT / "mkdocs.yml", tmp_path / "site")
    assert done.returncode == 0, done.stderr
    pages = sorted(p.stem for p in DOCS.glob("*.md"))
    built = sorted(p.stem for p in (tmp_path / "site").glob("*.html") if p.stem not in ("404", "search"))
    assert built == pages
    # The README is outside the site: its links into docs/ are checked against the pages built from them.
    readme_links = re.findall(r"\]\((docs/[^)#\s]+\.md)(?:#([^)\s]+))?\)", (ROOT / "README.md").read_text(encoding="utf-8"))
    assert len(readme_links) >= 10
    for page, anchor in readme_links:
        html = tmp_path / "site" / (Path(page).stem + ".html")
        assert html.is_file(), f"README.md links to {page}, which is not a page of the site"
        assert not anchor or f'id="{anchor}"' in html.read_text(encoding="utf-8"), f"README.md: {page}#{anchor}"


def copy_of_site(tmp_path: Path) -> Path:
    shutil.copy(ROOT / "mkdocs.yml", tmp_path / "mkdocs.yml")
    shutil.copytree(DOCS, tmp_path / "docs")
    return tmp_path / "mkdocs.yml"


@pytest.mark.parametrize("fault, page, text, warning", [
    ("an anchor no heading makes", "index.md", "\nSee [the time](benchmarks.md#where-the-time-goes-issue-16).\n",
     "where-the-time-goes-issue-16"),
    ("a link to a missing page", "pipeline.md", "\nSee [the old page](layout.md).\n", "layout.md"),
    ("a page left out of the nav", "orphan.md", "# Orphan\n", "orphan.md"),
])
def test_the_strict_build_fails_on(tmp_path, fault, page, text, warning):
    config = copy_of_site(tmp_path)
    with open(tmp_path / "docs" / page, "a", encoding="utf-8") as f:
        f.write(text)
    done = build_site(config, tmp_path / "site")
    assert done.returncode != 0, fault
    assert warning in done.stderr, done.stderr


# -- commands -------------------------------------------------------------------

def cli_commands() -> set[str]:
    parser = build_parser(load_arguments=False)
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return set(sub.choices)


def section(markdown: str, heading: str) -> str:
    """The text under ``## heading`` up to the next heading of that level."""
    start = markdown.index(f"\n## {heading}\n")
    end = markdown.find("\n## ", start + 1)
    return markdown[start:end if end >= 0 else len(markdown)]


def documented_commands(markdown: str) -> set[str]:
    """The commands of the command table: each row's first cell begins with the command's name."""
    return set(re.findall(r"^\| `([a-z][a-z0-9_-]*)[ `]", section(markdown, "Command line"), flags=re.M))


def test_every_command_is_documented_and_every_documented_command_exists():
    commands = cli_commands()
    assert {"solve", "extract", "serve"} <= commands  # the parser was read, not an empty set
    documented = documented_commands(CLI_AND_API.read_text(encoding="utf-8"))
    assert commands - documented == set(), "commands without a row in docs/cli-and-api.md"
    assert documented - commands == set(), "rows in docs/cli-and-api.md for commands that do not exist"


def test_a_command_without_its_row_is_found_missing():
    text = CLI_AND_API.read_text(encoding="utf-8")
    without = re.sub(r"^\| `calibrate .*\n", "", text, flags=re.M)
    assert without != text
    assert cli_commands() - documented_commands(without) == {"calibrate"}


# -- REST routes ----------------------------------------------------------------

def shape(path: str) -> str:
    """A path with every parameter, named or a number in an example, as ``{}``."""
    path = re.sub(r"\{[^}]*\}", "{}", path)
    return re.sub(r"(?<=/)\d+(?=/|\.|$)", "{}", path)


def api_routes() -> set[tuple[str, str]]:
    """Every method and path of the API, as its OpenAPI description lists them (included routers too)."""
    app = create_app(context=None, static_dir=None)  # the factory only stores the context
    return {(method.upper(), shape(path)) for path, operations in app.openapi()["paths"].items()
            for method in operations if method.upper() in HTTP_METHODS}


def documented_endpoints(markdown: str) -> set[tuple[str, str]]:
    return {(method, shape(path)) for method, path in ENDPOINT.findall(markdown)}


def test_every_route_is_documented_in_the_endpoint_table():
    routes = api_routes()
    assert len(routes) >= 30 and ("POST", "/api/sequences/{}/search") in routes
    documented = documented_endpoints(section(CLI_AND_API.read_text(encoding="utf-8"), "REST API"))
    assert sorted(routes - documented) == [], "routes missing from the REST API table of docs/cli-and-api.md"


def test_every_endpoint_the_manual_names_exists():
    routes = api_routes()
    for page in [*sorted(DOCS.glob("*.md")), ROOT / "README.md"]:
        named = documented_endpoints(page.read_text(encoding="utf-8"))
        assert sorted(named - routes) == [], f"{page.relative_to(ROOT)} names endpoints the API does not have"


def test_the_openapi_page_is_documented():
    """The one route outside the OpenAPI description, the Swagger UI at /docs, defined on the app itself."""
    app = create_app(context=None, static_dir=None)
    hidden = {route.path for route in app.routes if isinstance(route, APIRoute) and not route.include_in_schema}
    assert hidden == {"/docs"}
    assert "`/docs`" in section(CLI_AND_API.read_text(encoding="utf-8"), "REST API")


def test_a_route_without_its_row_is_found_missing():
    text = section(CLI_AND_API.read_text(encoding="utf-8"), "REST API")
    without = re.sub(r"^\| `GET /api/spacecraft/\{name\}/calibrations` .*\n", "", text, flags=re.M)
    assert without != text
    assert api_routes() - documented_endpoints(without) == {("GET", "/api/spacecraft/{}/calibrations")}
