"""The sky section of an attitude candidate: what the console draws in its candidate view.

Given a candidate's rotation ``R`` (ICRS -> camera, ``v_cam = R v``), the
camera and the observation time, every catalogue star within the sensor
enlarged by ``margin`` on each side is mapped to pixels::

    v      = apparent direction of the star at t (proper motion + aberration)
    (x, y) = camera.vectors_to_pixels(R v)

so a star lands exactly where the sensor would have reported it if the
candidate were right.  The pattern points are drawn at their reference-frame
pixels; the residual of a matched point is the pixel vector from the point to
its star.  Nothing here touches the database or the network: the inputs are
arrays and plain dictionaries, the output is JSON-ready.
"""

from __future__ import annotations

from collections import defaultdict
from datetime import datetime

import numpy as np

from app.camera import Camera
from app.workflow.documents import CandidateDocument, PatternPoint
from app.catalogue import Catalogue, constellations, vectors_to_radec

#: Extra room around the sensor, as a fraction of its width and height on each side.
DEFAULT_MARGIN = 0.2


def _round(value: float, digits: int = 2) -> float | None:
    return round(float(value), digits) if np.isfinite(value) else None


def extended_bounds(camera: Camera, margin: float) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) of the sensor grown by ``margin`` x its size on each side."""
    dx, dy = margin * camera.width, margin * camera.height
    return (-0.5 - dx, camera.width - 0.5 + dx, -0.5 - dy, camera.height - 0.5 + dy)


def section_radius(camera: Camera, margin: float) -> float:
    """Angle from the boresight (radians) of the cone that holds the section."""
    return min(np.pi / 2 - 1e-6, 0.5 * camera.diagonal_fov_rad * (1 + 2 * margin))


def project_into_section(rotation: np.ndarray, camera: Camera, vectors: np.ndarray,
                         margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of ICRS ``vectors`` under ``rotation`` and a mask of those inside the section.

    A cone test comes first (angle from the boresight at most the half
    diagonal field grown by the margin): a distorted projection of a far
    off-axis direction can fold back onto the sensor and must not count.
    """
    cam = np.asarray(vectors, float).reshape(-1, 3) @ np.asarray(rotation, float).T
    xy, front = camera.vectors_to_pixels(cam)
    cone = np.cos(section_radius(camera, margin))
    x0, x1, y0, y1 = extended_bounds(camera, margin)
    with np.errstate(invalid="ignore"):
        inside = front & (cam[:, 2] >= cone) & (xy[:, 0] >= x0) & (xy[:, 0] <= x1) \
            & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
    return xy, inside


def sky_section(*, rotation: np.ndarray, camera: Camera, t: datetime, catalogue: Catalogue,
                names: dict[int, tuple[str, str]], mag_limit: float, pattern: list[PatternPoint],
                candidate: CandidateDocument, planets: dict[str, np.ndarray] | None = None,
                velocity_km_s=None, margin: float = DEFAULT_MARGIN) -> dict:
    """The candidate view's data.

    ``pattern`` is the searched pattern; ``candidate`` the stored candidate,
    whose ``matches``/``planets`` name pattern rows (``pattern_index``),
    ``generating_edge`` (two pattern rows) and ``generating_pair_hip``.
    Stars down to ``mag_limit`` are listed, plus every matched or generating
    star whatever its magnitude.  ``planets`` maps names to apparent ICRS
    unit vectors at ``t``.

    Returns ``{"mag_limit", "margin", "bounds", "center", "stars",
    "pattern_points", "generating_edge", "planets", "constellations"}``; pixel
    coordinates follow the camera convention (x right, y down).
    """
    R = np.asarray(rotation, dtype=float)
    match_of_point = {m.pattern_index: m for m in candidate.matches}
    planet_of_point = {p.pattern_index: p for p in candidate.planets}
    pair_hip = list(candidate.generating_pair_hip)
    wanted_hip = {m.hip for m in match_of_point.values()} | {h for h in pair_hip if h >= 0}

    # Stars: the bright ones around the field and the ones the candidate names.
    near = catalogue.rows_near(R[2], section_radius(camera, margin))
    row_of_hip = catalogue.index_of_hip()
    named = [row_of_hip[h] for h in wanted_hip if h in row_of_hip]
    rows = np.union1d(near[catalogue.mag[near] <= mag_limit], np.array(named, dtype=int))
    sub = catalogue.subset(rows)
    vectors = sub.apparent_vectors(t, velocity_km_s)
    xy, inside = project_into_section(R, camera, vectors, margin)
    shown = np.flatnonzero(inside)
    on_sensor = camera.on_sensor(xy[shown])
    pixel_of_hip = {int(sub.hip[k]): (float(xy[k, 0]), float(xy[k, 1])) for k in shown}
    # Stars of the candidate outside the section (a bad candidate) still get their pixels.
    for k in np.flatnonzero(np.isin(sub.hip, list(wanted_hip)) & ~inside):
        pixel_of_hip[int(sub.hip[k])] = (float(xy[k, 0]), float(xy[k, 1]))
    point_of_hip = {m.hip: i for i, m in match_of_point.items()}

    # One astropy call for the field centre and every star shown.
    centre = R[2]
    labels = constellations(np.vstack([centre[None, :], vectors[shown]]))
    centre_ra, centre_dec = vectors_to_radec(centre)
    ra, dec = vectors_to_radec(vectors[shown]) if len(shown) else (np.zeros(0), np.zeros(0))

    stars = []
    by_constellation: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for n, k in enumerate(shown):
        hip = int(sub.hip[k])
        name = names.get(hip, (None, None))[0]
        stars.append({"hip": hip, "name": name or None, "mag": round(float(sub.mag[k]), 2),
                      "constellation": labels[n + 1], "ra_deg": round(float(np.degrees(ra[n])), 5),
                      "dec_deg": round(float(np.degrees(dec[n])), 5),
                      "x": _round(xy[k, 0]), "y": _round(xy[k, 1]), "on_sensor": bool(on_sensor[n]),
                      "matched": hip in point_of_hip, "pattern_index": point_of_hip.get(hip)})
        by_constellation[labels[n + 1]].append((float(xy[k, 0]), float(xy[k, 1])))
    stars.sort(key=lambda s: s["mag"])

    # Planets in the section, and which pattern point each explains.
    planet_rows = []
    planet_points = {p.name: i for i, p in planet_of_point.items()}
    for name, vector in sorted((planets or {}).items()):
        pxy, pin = project_into_section(R, camera, vector, margin)
        if pin[0] or name in planet_points:
            planet_rows.append({"name": name, "x": _round(pxy[0, 0]), "y": _round(pxy[0, 1]),
                                "on_sensor": bool(camera.on_sensor(pxy)[0]),
                                "pattern_index": planet_points.get(name)})
    planet_pixel = {p["name"]: (p["x"], p["y"]) for p in planet_rows}

    points = []
    # Points picked by hand follow the tracked ones; each is named by its place among them
    # (``manual_points[k]``, as the pattern's errors name it).
    n_tracked = sum(row.track is not None for row in pattern)
    for i, row in enumerate(pattern):
        match = match_of_point.get(i)
        planet = planet_of_point.get(i)
        point = {"index": i, "track": row.track, "hand": None if row.track is not None else i - n_tracked,
                 "x": row.x, "y": row.y,
                 "hip": None, "name": None, "planet": None, "star_x": None, "star_y": None,
                 "residual_x": None, "residual_y": None, "residual_arcsec": None}
        target = None
        if match is not None:
            target = pixel_of_hip.get(match.hip)
            point.update(hip=match.hip, name=match.name, residual_arcsec=match.residual_arcsec)
        elif planet is not None:
            target = planet_pixel.get(planet.name)
            point.update(planet=planet.name, residual_arcsec=planet.residual_arcsec)
        if target is not None and None not in target and row.x is not None and row.y is not None:
            point.update(star_x=_round(target[0]), star_y=_round(target[1]),
                         residual_x=_round(target[0] - row.x, 3), residual_y=_round(target[1] - row.y, 3))
        points.append(point)

    edge = list(candidate.generating_edge)
    edge_doc = None
    if len(edge) == 2 and all(0 <= i < len(pattern) for i in edge):
        edge_doc = {
            "pattern_indices": edge,
            "points": [{"x": pattern[i].x, "y": pattern[i].y} for i in edge],
            "stars": [{"hip": h, "name": names.get(h, (None, None))[0] or None,
                       "x": _round(pixel_of_hip[h][0]) if h in pixel_of_hip else None,
                       "y": _round(pixel_of_hip[h][1]) if h in pixel_of_hip else None} for h in pair_hip],
        }

    x0, x1, y0, y1 = extended_bounds(camera, margin)
    constellation_labels = [
        {"constellation": abbrev, "n_stars": len(pix),
         "x": _round(float(np.median([p[0] for p in pix]))), "y": _round(float(np.median([p[1] for p in pix])))}
        for abbrev, pix in sorted(by_constellation.items(), key=lambda kv: -len(kv[1]))]
    return {
        "mag_limit": float(mag_limit),
        "margin": float(margin),
        "sensor": {"width": camera.width, "height": camera.height},
        "bounds": {"x_min": x0, "x_max": x1, "y_min": y0, "y_max": y1},
        "center": {"ra_deg": round(float(np.degrees(centre_ra[0])), 6),
                   "dec_deg": round(float(np.degrees(centre_dec[0])), 6), "constellation": labels[0]},
        "stars": stars,
        "pattern_points": points,
        "generating_edge": edge_doc,
        "planets": planet_rows,
        "constellations": constellation_labels,
    }
