"""Processes wanting the same derived data at once take turns (app.cache): the first builds, the others load.

A server's workers now start while the server builds the bright-pair index on a first start: without the
lock each would build it too.  The test holds the index's lock itself, as a first builder would, while
another process asks for the same index; that process must load what the test wrote, not build its own.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from app.index import DEFAULT_INDEX_EPOCH, _build_and_keep, index_cache_path, load_index
from app.cache import exclusive

ROOT = Path(__file__).resolve().parents[1]

ASK = '''
import logging, sys
from pathlib import Path
logging.basicConfig(level=logging.INFO, format="%(message)s")
from app.index import load_index
print("asking", flush=True)
index = load_index(mag_limit=2.5, max_edge_deg=30.0, cache_dir=Path(sys.argv[1]))
print("pairs", index.n_pairs, flush=True)
'''


def test_a_process_asking_for_an_index_another_is_building_waits_and_loads_it(tmp_path):
    path = index_cache_path(2.5, 30.0, cache_dir=tmp_path)
    env = {**os.environ, "STARID_CACHE_DIR": str(tmp_path)}
    with exclusive(path.with_suffix(".lock")) as locked:
        assert locked
        asking = subprocess.Popen([sys.executable, "-c", ASK, str(tmp_path)], cwd=ROOT, env=env, text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert asking.stdout.readline().strip() == "asking"  # it has looked, or is about to: no file yet
        built = _build_and_keep(path, 2.5, 30.0, DEFAULT_INDEX_EPOCH)  # as the first builder does
        assert asking.poll() is None  # still waiting for the lock
    out, err = asking.communicate(timeout=120)
    assert asking.returncode == 0, err
    assert f"pairs {built.n_pairs}" in out
    assert "building the bright-pair index" not in err  # loaded what the test wrote
    again = load_index(mag_limit=2.5, max_edge_deg=30.0, cache_dir=tmp_path)
    assert np.array_equal(again.star_a, built.star_a) and np.array_equal(again.length_rad, built.length_rad)


def test_a_damaged_index_is_built_again_and_an_unwritable_cache_is_only_said(tmp_path, caplog):
    """The index and the sky's maps share one loader and one writer (app.cache): a truncated file is made
    again, never trusted (the index once let numpy's BadZipFile through), and a cache directory that cannot
    be written leaves the index built in memory, said in the log."""
    import logging

    built = load_index(mag_limit=2.5, max_edge_deg=30.0, cache_dir=tmp_path)
    path = index_cache_path(2.5, 30.0, cache_dir=tmp_path)
    path.write_bytes(path.read_bytes()[:100])  # truncated: not a zip archive any more
    with caplog.at_level(logging.WARNING, logger="app.cache"):
        again = load_index(mag_limit=2.5, max_edge_deg=30.0, cache_dir=tmp_path)
    assert "unreadable" in caplog.text and np.array_equal(again.star_a, built.star_a)
    blocked = tmp_path / "not-a-directory"
    blocked.write_text("a file where the cache directory should be")
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="app.cache"):
        made = load_index(mag_limit=2.5, max_edge_deg=30.0, cache_dir=blocked)
    assert np.array_equal(made.length_rad, built.length_rad) and "not written" in caplog.text


def test_a_sky_map_made_here_has_the_types_a_later_process_loads_it_with(tmp_path, monkeypatch):
    """The bright triangles, the alone-within chords and a cell map, made by this process (the first search after
    an install) and loaded by the next, give the compiled kernels the same argument types: a strided column
    among the made triangles once compiled the shape lookup a second time inside a first search (0.26 s)."""
    import dataclasses

    from numba import typeof

    from app.identification import Sky

    monkeypatch.setenv("STARID_CACHE_DIR", str(tmp_path))
    index = load_index(mag_limit=4.0, max_edge_deg=30.0, cache_dir=tmp_path)

    def kernel_types(sky):
        triangles = sky.bright_triangles()
        cells = sky.near_star_cells(index.n_stars, 0.01)
        arrays = {f.name: getattr(triangles, f.name) for f in dataclasses.fields(triangles)}
        arrays |= {"alone_within": sky.alone_within(), **{f"cells.{k}": v for k, v in cells.arrays().items()}}
        return {name: typeof(a) for name, a in arrays.items()}

    made = kernel_types(Sky(index))
    assert sorted(p.name.split("-")[0] for p in tmp_path.glob("*.npz")) == [
        "alone", "bright", "bright", "near"]  # the index, and the three maps made here
    assert kernel_types(Sky(index)) == made  # loaded from those files
