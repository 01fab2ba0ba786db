"""The annotated frame (issue 26 item 6): drawn where hand-computed pinhole geometry says, written by
``solve IMAGE --annotate OUT.png`` for a real frame, and served for a stored frame by the API.

The drawing tests use a blank frame, a centred pinhole camera (f = 1000 px) and the attitude of RA 0,
Dec 0, roll 0, whose rows are written out by hand from docs/conventions.md (north up, east to the
left): camera x = -east = (0, -1, 0), y = -north = (0, 0, -1), z = the boresight (1, 0, 0).  A
direction at RA a, Dec d is then camera (-cos d sin a, -sin d, cos d cos a), so it lands on

    x = cx - f tan a,    y = cy - f tan d / cos a.
"""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from app.attitude import rotation_from_radec_roll
from app.camera import Camera
from app.catalogue import constellations, load_catalogue, radec_to_vectors
from app.cli import main as cli_main
from app.frames.annotate import (FIGURE_ALPHA, FIGURE_COLOUR, GRID_ALPHA, GRID_COLOUR, STAR_COLOUR,
                                 UNMATCHED_COLOUR, Annotation, Figure, SkyLabel, annotate, canvas_zoom,
                                 grid_lines, image_centre_pointing, marker_sizes)
from app.workflow.annotate import figure_table

REAL_FRAMES = Path(__file__).resolve().parent.parent.parent / "shared" / "real-frames"

F = 1000.0
CAMERA = Camera(width=800, height=600, focal_length_px=F, cx=399.5, cy=299.5)
R0 = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def pinhole(ra_deg: float, dec_deg: float) -> tuple[float, float]:
    """The hand formula of the module docstring."""
    a, d = math.radians(ra_deg), math.radians(dec_deg)
    return CAMERA.cx - F * math.tan(a), CAMERA.cy - F * math.tan(d) / math.cos(a)


def sky(ra_deg: float, dec_deg: float) -> np.ndarray:
    return radec_to_vectors(np.radians([ra_deg]), np.radians([dec_deg]))[0]


def blank(camera: Camera = CAMERA, scale: int = 1) -> np.ndarray:
    return np.zeros((-(-camera.height // scale), -(-camera.width // scale)), np.uint8)


def is_colour(pixel, colour, alpha: int = 255, tolerance: int = 2) -> bool:
    """The colour drawn at ``alpha`` over black."""
    want = np.round(np.array(colour) * alpha / 255.0)
    return bool(np.all(np.abs(np.asarray(pixel, float) - want) <= tolerance))


def test_the_hand_attitude_is_the_conventions_ra0_dec0_roll0():
    assert np.allclose(rotation_from_radec_roll(0.0, 0.0, 0.0), R0, atol=1e-12)
    ra, dec, roll = image_centre_pointing(CAMERA, R0)
    assert abs(ra) < 1e-9 or abs(ra - 360) < 1e-9
    assert abs(dec) < 1e-9 and min(roll, 360 - roll) < 1e-6
    # Elsewhere: the title's centre and roll are the attitude's for a centred camera.
    ra, dec, roll = image_centre_pointing(CAMERA, rotation_from_radec_roll(123.0, 45.0, 30.0))
    assert (ra, dec, roll) == pytest.approx((123.0, 45.0, 30.0), abs=1e-6)


def test_a_star_is_circled_around_its_projected_position_and_named_beside_it():
    x, y = pinhole(-3.0, 2.0)  # 451.9, 264.5
    r = marker_sizes(CAMERA.width).radius
    image = annotate(blank(), 1, Annotation(camera=CAMERA, status="identified", rotation=R0,
                                            stars=(SkyLabel("Testar", sky(-3.0, 2.0)),)))
    assert image.shape == (600, 800, 3) and image.dtype == np.uint8
    hits = 0
    for phi in np.radians(np.arange(0, 360, 15)):
        px, py = x + r * math.cos(phi), y + r * math.sin(phi)
        window = image[round(py) - 1:round(py) + 2, round(px) - 1:round(px) + 2].reshape(-1, 3)
        hits += any(is_colour(p, STAR_COLOUR) for p in window)
    assert hits == 24
    inner = image[round(y) - r // 2:round(y) + r // 2, round(x) - r // 2:round(x) + r // 2].reshape(-1, 3)
    assert not any(is_colour(p, STAR_COLOUR) for p in inner)  # the star itself stays as it was
    # Its name: star-coloured text to the right of the circle, clear of it.
    beside = image[round(y) - r:round(y) + r, round(x + r + 3):round(x + r + 80)].reshape(-1, 3)
    assert sum(is_colour(p, STAR_COLOUR, tolerance=40) for p in beside) > 20


def test_the_grid_line_of_a_declination_passes_where_the_geometry_says():
    lines = grid_lines(CAMERA, R0)
    dec10 = next(line for line in lines if line.kind == "dec" and line.value_deg == 10.0)
    points = np.concatenate(dec10.runs)
    alpha = np.arctan((CAMERA.cx - points[:, 0]) / F)  # the RA of each point's column
    assert np.max(np.abs(points[:, 1] - (CAMERA.cy - F * math.tan(math.radians(10)) / np.cos(alpha)))) < 1e-6
    assert points[:, 0].min() < 0 and points[:, 0].max() > CAMERA.width - 1  # across the frame
    assert dec10.label == "Dec +10°"
    assert {line.value_deg for line in lines if line.kind == "dec"} == {-10.0, 0.0, 10.0}

    image = annotate(blank(), 1, Annotation(camera=CAMERA, status="identified", rotation=R0))
    for ra in (-5.0, 4.0):  # between the RA lines (every 10 deg)
        x, y = pinhole(ra, 10.0)
        column = image[:, round(x)]
        on = [row for row in range(round(y) - 1, round(y) + 2) if is_colour(column[row], GRID_COLOUR, GRID_ALPHA)]
        assert on, (ra, x, y)
        assert not is_colour(column[round(y) + 15], GRID_COLOUR, GRID_ALPHA)  # a line, not a band
    # The RA 0 line is the central column.
    assert is_colour(image[450, round(CAMERA.cx)], GRID_COLOUR, GRID_ALPHA) \
        or is_colour(image[450, round(CAMERA.cx) + 1], GRID_COLOUR, GRID_ALPHA)


def test_unmatched_sources_are_squares_at_their_pixels_and_nothing_is_drawn_unsolved():
    half = marker_sizes(CAMERA.width).square_half
    xy = np.array([[120.0, 500.0], [700.25, 420.75]])
    image = annotate(blank(), 1, Annotation(camera=CAMERA, status="no_match", unmatched_xy=xy))
    for x, y in xy:
        for dx, dy in ((-half, -half), (half, -half), (-half, half), (half, half), (0, half), (-half, 0)):
            assert is_colour(image[round(y + dy), round(x + dx)], UNMATCHED_COLOUR), (x, y, dx, dy)
        assert not image[round(y), round(x)].any()  # hollow
    # No attitude: no grid, no star; only the squares and the title (top left).
    below_title = image[80:]
    marked = below_title.any(axis=2)
    assert marked.sum() == sum(
        int(is_colour(p, UNMATCHED_COLOUR)) for p in below_title[marked])


def test_a_constellation_line_joins_its_stars_without_covering_them():
    a, b = sky(-8.0, -6.0), sky(6.0, -9.0)
    figure = Figure("Tst", "Testlineae", (np.array([a, b]),))
    image = annotate(blank(), 1, Annotation(camera=CAMERA, status="identified", rotation=R0, figures=(figure,)))
    (xa, ya), (xb, yb) = pinhole(-8.0, -6.0), pinhole(6.0, -9.0)
    # The great-circle arc's midpoint, projected: the pinhole keeps great circles straight.
    mid = a + b
    xm, ym = pinhole(math.degrees(math.atan2(mid[1], mid[0])), math.degrees(math.asin(mid[2] / np.linalg.norm(mid))))
    assert abs((ym - ya) * (xb - xa) - (yb - ya) * (xm - xa)) / math.hypot(xb - xa, yb - ya) < 0.01
    window = image[round(ym) - 2:round(ym) + 3, round(xm) - 2:round(xm) + 3].reshape(-1, 3)
    assert any(is_colour(p, FIGURE_COLOUR, FIGURE_ALPHA) for p in window)
    r = marker_sizes(CAMERA.width).radius
    for x, y in ((xa, ya), (xb, yb)):  # a gap around each star
        around = image[round(y) - r:round(y) + r, round(x) - r:round(x) + r].reshape(-1, 3)
        assert not any(is_colour(p, FIGURE_COLOUR, FIGURE_ALPHA, tolerance=30) for p in around)


def test_a_preview_is_enlarged_back_to_its_frames_size_with_the_same_geometry():
    assert canvas_zoom(696, 2) == 2 and canvas_zoom(1024, 4) == 2 and canvas_zoom(3000, 1) == 1
    x, y = pinhole(-3.0, 2.0)
    r = marker_sizes(CAMERA.width).radius
    image = annotate(blank(scale=2), 2, Annotation(camera=CAMERA, status="identified", rotation=R0,
                                                   stars=(SkyLabel("Testar", sky(-3.0, 2.0)),)))
    assert image.shape == (600, 800, 3)
    assert is_colour(image[round(y), round(x + r)], STAR_COLOUR) or is_colour(image[round(y), round(x + r) - 1],
                                                                               STAR_COLOUR)
    with pytest.raises(ValueError, match="not a 800 x 600 frame"):
        annotate(blank(), 2, Annotation(camera=CAMERA, status="identified"))


def test_the_figures_are_the_88_constellations_each_mostly_within_its_iau_boundary():
    table = figure_table()
    assert len(table) == 88 and len({abbrev for abbrev, _, _ in table}) == 88
    catalogue = load_catalogue()
    rows = catalogue.index_of_hip()
    for abbrev, name, lines in table:
        hips = sorted({v for line in lines for v in line if isinstance(v, int)})
        assert all(h in rows for h in hips), abbrev  # every vertex is a catalogue star
        vectors = catalogue.subset(np.array([rows[h] for h in hips])).mean_vectors(2000.0)
        inside = np.mean([c == abbrev for c in constellations(vectors)])
        assert inside >= 0.7, (abbrev, name, inside)


def _png(data: bytes) -> Image.Image:
    image = Image.open(io.BytesIO(data))
    image.load()
    return image


@pytest.fixture
def session_sky(monkeypatch, sky):
    monkeypatch.setattr("app.identification.Sky", lambda: sky)
    return sky


@pytest.mark.parametrize("optics", [["--fov-deg", "13.266"], []])  # given; none (the field of view searched)
def test_solve_annotate_writes_the_real_frame_with_its_stars_where_astrometry_net_puts_them(tmp_path, session_sky,
                                                                                            capsys, optics):
    from astropy.io import fits
    from astropy.wcs import WCS

    frame = tmp_path / "feb16-2.png"
    frame.write_bytes((REAL_FRAMES / "feb16-2.png").read_bytes())
    (tmp_path / "feb16-2.frames.json").write_text(json.dumps(
        {"format": "tubsat-frames/1", "frames": [{"file": "feb16-2.png", "time": "2018-02-16T06:00:00Z"}]}))
    out = tmp_path / "annotated.png"
    assert cli_main(["solve", "--json", *optics, "--annotate", str(out), str(frame)]) == 0
    said = capsys.readouterr()
    doc = json.loads(said.out)
    assert f"--annotate: wrote {out} ({frame} with the first candidate's stars named)" in said.err  # not silent
    assert doc["status"] == "identified"
    image = _png(out.read_bytes())
    assert image.size == (1392, 1040) and image.mode == "RGB"
    pixels = np.asarray(image)

    # The identified stars, circled where astrometry.net's own solution (the WCS) puts them.
    wcs = WCS(fits.getheader(REAL_FRAMES / "feb16-2.wcs"), naxis=2)
    catalogue = load_catalogue()
    rows = catalogue.index_of_hip()
    matches = doc["candidates"][0]["matches"]
    assert len(matches) >= 8
    r = marker_sizes(1392).radius
    for m in matches:
        row = rows[m["hip"]]
        x, y = wcs.all_world2pix([[math.degrees(catalogue.ra_rad[row]), math.degrees(catalogue.dec_rad[row])]], 0)[0]
        hits = 0
        for phi in np.radians(np.arange(0, 360, 30)):
            px, py = x + r * math.cos(phi), y + r * math.sin(phi)
            if not (2 <= px < 1390 and 2 <= py < 1038):
                hits += 1
                continue
            window = pixels[round(py) - 3:round(py) + 4, round(px) - 3:round(px) + 4].reshape(-1, 3)
            hits += any(is_colour(p, STAR_COLOUR, tolerance=8) for p in window)
        assert hits >= 10, (m, x, y, hits)


def test_solve_annotate_takes_one_file(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli_main(["solve", "--annotate", str(tmp_path / "a.png"), "x.json", "y.json"])
    assert exit_.value.code == 2
    assert "takes one FILE" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main(["solve", "--annotate", str(tmp_path / "missing" / "a.png"), "x.json"])
    assert "no folder" in capsys.readouterr().err


def test_the_api_annotates_a_stored_frame_with_a_candidate_at_the_attitude_of_that_snapshot(tmp_path, sky, sample_dir):
    from fastapi.testclient import TestClient

    from app.api import create_app
    from app.camera import CAMERAS
    from app.simulate import frame_png_bytes, frames_sidecar, simulate_frames
    from app.storage import Storage
    from app.workflow import AppContext

    camera = CAMERAS["tubsat-752x582-20deg"]
    frames, times, truth = simulate_frames(np.random.default_rng(2626), camera, n_frames=3)
    names = [f"f{i}.png" for i in range(3)]
    sidecar = json.dumps(frames_sidecar(names, times, camera, sequence_id="annotated-pass"))
    files = [("files", (n, frame_png_bytes(f), "image/png")) for n, f in zip(names, frames)]
    files.append(("sidecar", ("frames.json", sidecar.encode(), "application/json")))
    ctx = AppContext(storage=Storage.open(tmp_path / "api.sqlite3"), sky=sky)
    try:
        api = TestClient(create_app(ctx))
        seq_id = api.post("/api/frames", files=files).json()["id"]
        url = f"/api/sequences/{seq_id}/frames/{{}}/annotated.png"
        not_searched = api.get(url.format(0))
        assert not_searched.status_code == 404 and "not been searched" in not_searched.json()["detail"]
        result = api.post(f"/api/sequences/{seq_id}/search", json={"method": "bright_pair"}).json()
        assert result["status"] == "identified"

        # A snapshot other than the reference: its stars circled where the true attitude puts them.
        snapshot = next(i for i in range(3) if i != result["reference_snapshot"])
        r = api.get(url.format(snapshot), params={"rank": 1})
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        image = _png(r.content)
        assert image.size == (752, 582) and image.mode == "RGB"
        pixels = np.asarray(image)
        catalogue = load_catalogue()
        rows = catalogue.index_of_hip()
        hips = [m["hip"] for m in result["candidates"][0]["matches"]]
        vectors = catalogue.subset(np.array([rows[h] for h in hips])).apparent_vectors(times[snapshot])
        xy, front = camera.vectors_to_pixels(vectors @ np.asarray(truth["rotation_matrices"][snapshot]).T)
        sizes = marker_sizes(752)
        radius = sizes.radius
        # Every star on the sensor, but under the title (drawn over the circles, on a dark box).
        shown = front & camera.on_sensor(xy, margin=radius + 3) & (xy[:, 1] - radius > 3 * sizes.font_px)
        circled = 0
        for x, y in xy[shown]:
            ring = [pixels[round(y + radius * math.sin(p)) - 1:round(y + radius * math.sin(p)) + 2,
                           round(x + radius * math.cos(p)) - 1:round(x + radius * math.cos(p)) + 2].reshape(-1, 3)
                    for p in np.radians(np.arange(0, 360, 30))]
            circled += sum(any(is_colour(q, STAR_COLOUR, tolerance=8) for q in window) for window in ring) >= 11
        assert circled >= 5 and circled == np.count_nonzero(shown)

        for params, snap, status, words in (({"rank": 99}, 0, 404, "no candidate of rank 99"),
                                            ({}, 7, 404, "snapshot 7"),
                                            ({"rank": 0}, 0, 422, None), ({"rank": "first"}, 0, 422, None)):
            r = api.get(url.format(snap), params=params)
            assert r.status_code == status, r.text
            if words:
                assert words in r.json()["detail"]
            else:
                assert any(p["location"] == "query.rank" for p in r.json()["problems"])
        sample = sample_dir / "01-clean.json"
        spot_list = api.post("/api/sequences", files={"file": (sample.name, sample.read_bytes(), "application/json")})
        r = api.get(f"/api/sequences/{spot_list.json()['id']}/frames/0/annotated.png")
        assert r.status_code == 404 and "no frame images" in r.json()["detail"]
    finally:
        ctx.close()
