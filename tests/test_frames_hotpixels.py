"""Hot-pixel maps (issue 15): built across frames, stored versioned and append-only, applied to frames and spot lists."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from app.camera import CAMERAS
from app.frames import HotPixelMap, drop_hot_pixel_sources, frames_to_sequence
from app.frames.hotpixels import MIN_FRAMES
from app.simulate import frames_fits_bytes, render_frame, simulate_frames, simulate_sequence
from app.storage import StaleHotPixelMap, Storage

CAMERA = CAMERAS["tubsat-752x582-20deg"]


def test_a_pixel_seen_in_many_frames_is_hot_a_cosmic_ray_is_not():
    m = HotPixelMap.empty(100, 80)
    m = m.with_frames([[(5, 5), (40, 30)], [(5, 5)], [(5, 5), (70, 10)]])
    assert m.frames == 3 and m.hot == [(5, 5)]
    # A pixel that turns hot later is hot after MIN_FRAMES frames, however many frames came before.
    m = m.with_frames([[]] * 50).with_frames([[(60, 60)]] * MIN_FRAMES)
    assert (60, 60) in m.hot
    # And one that stops being a candidate fades out.
    assert (5, 5) not in m.hot
    again = HotPixelMap.from_json(m.to_json())
    assert again.hot == m.hot and again.frames == m.frames


PAIRS = [(100, 100), (400, 250), (650, 500), (300, 450)]  # hot pixel pairs: (x, y) and (x + 1, y)


def _pass(seed: int, n_frames: int):
    """Rendered frames (no simulator hot pixels) with hot pixel *pairs* added: sharper than any star (one lit
    neighbour), and staying put while the stars move."""
    frames, times, _ = simulate_frames(np.random.default_rng([31, seed]), CAMERA, n_frames=n_frames, hot_pixels=False)
    for frame in frames:
        for x, y in PAIRS:
            frame[y, x:x + 2] += np.uint16(900)
    return frames_fits_bytes(frames, times, camera=CAMERA, spacecraft="HOT-1")


def _on_pairs(sequence) -> int:
    return sum(1 for snap in sequence.snapshots for x, y in snap.xy
               if any(x0 - 1 <= x <= x0 + 2 and abs(y - y0) <= 1 for x0, y0 in PAIRS))


def test_mapped_hot_pixels_never_become_stars():
    alone = frames_to_sequence([("one.fits", _pass(0, 1))])
    assert _on_pairs(alone.sequence) == 0  # a pair is two sharp pixels, no star, even without a map
    stored = None
    for seed in (1, 2):  # two passes of 4 frames: the pairs stay put while the stars move
        result = frames_to_sequence([("p.fits", _pass(seed, 4))], hot_map=stored)
        assert _on_pairs(result.sequence) == 0
        stored = result.hot_map
    assert {(x, y) for x, y in PAIRS} <= set(stored.hot) | {(x + 1, y) for x, y in PAIRS} or \
        all((x, y) in stored.hot or (x + 1, y) in stored.hot for x, y in PAIRS)
    later = frames_to_sequence([("later.fits", _pass(3, 1))], hot_map=stored)  # one frame: only the map knows
    assert _on_pairs(later.sequence) == 0
    assert later.sequence.snapshots[0].n_sources >= 10


def test_a_static_sky_maps_no_stars():
    _, times, truth = simulate_frames(np.random.default_rng(8), CAMERA, n_frames=4, hot_pixels=False)
    stars = [s for s in truth["frame_sources"][0] if s["kind"] == "star"]
    xy, flux = [[s["x"], s["y"]] for s in stars], [s["flux_e"] for s in stars]
    # The same sky four times (inertial pointing), each with its own noise: stars stay put, nothing is hot.
    still = [render_frame(np.random.default_rng(k), CAMERA, xy, flux) for k in range(4)]
    result = frames_to_sequence([("still.fits", frames_fits_bytes(still, times, camera=CAMERA))])
    assert result.hot_map.hot == []


def test_spot_lists_lose_their_sources_on_mapped_hot_pixels():
    sequence, truth = simulate_sequence(np.random.default_rng(5), CAMERA, "ghosts", n_snapshots=8)
    hot = sorted({(int(round(x)), int(round(y))) for labels, snap in zip(truth["sources"], sequence.snapshots)
                  for label, (x, y) in zip(labels, snap.xy) if label["kind"] == "hot_pixel"})
    filtered, dropped = drop_hot_pixel_sources(sequence, hot)
    for labels, snap, removed, kept in zip(truth["sources"], sequence.snapshots, dropped, filtered.snapshots):
        expected = [k for k, label in enumerate(labels) if label["kind"] == "hot_pixel"]
        # a star may sit on a hot pixel by chance: it goes too (as the sensor could not tell them apart)
        assert set(expected) <= set(removed)
        assert kept.n_sources == snap.n_sources - len(removed)
    unchanged, none = drop_hot_pixel_sources(sequence, [])
    assert unchanged is sequence and not any(none)


def test_maps_are_versioned_and_append_only(tmp_path):
    storage = Storage.open(tmp_path / "hot.sqlite3")
    first = storage.add_hot_pixel_map("SAT", "752x582", map_doc={"width": 752, "height": 582, "frames": 4,
                                                                  "pixels": []}, frames=4, hot_pixels=0, based_on=None)
    second = storage.add_hot_pixel_map("SAT", "752x582", map_doc={"width": 752, "height": 582, "frames": 8,
                                                                   "pixels": [[1, 2, 4, 0]]}, frames=8, hot_pixels=1,
                                       based_on=first.version)
    assert (first.version, second.version) == (1, 2)
    assert storage.current_hot_pixel_map("SAT", "752x582").version == 2
    assert storage.current_hot_pixel_map("SAT", "576x604") is None
    assert [r.version for r in storage.hot_pixel_map_history("SAT", "752x582")] == [1, 2]
    with pytest.raises(StaleHotPixelMap):  # computed from version 1 while 2 exists: nothing written
        storage.add_hot_pixel_map("SAT", "752x582", map_doc={}, frames=8, hot_pixels=0, based_on=1)
    storage.close()
    conn = sqlite3.connect(tmp_path / "hot.sqlite3")
    for statement in ("UPDATE hot_pixel_maps SET frames = 0", "DELETE FROM hot_pixel_maps"):
        with pytest.raises(sqlite3.DatabaseError, match="append-only"):
            conn.execute(statement)
    conn.close()
