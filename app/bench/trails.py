"""Trailed stars: ``python -m app bench --suite trails [--n N] [--seed S] [--json]``.

A photograph from a fixed tripod trails every star along the sky's turning: 15 arcsec a second at the
equator, so 20 s through a 50 mm lens (22 arcsec a pixel on a 6000 px full-frame sensor) draws 14 px; a star
camera on a turning spacecraft smears its stars the same way.  ``N`` photographs (default 4) at each of
:data:`FIELDS_DEG` and each trail length of :data:`TRAILS_PX` are rendered as :func:`app.bench.wide.photograph`
renders them (3000 x 2000 px, 8-bit JPEG, the lens's distortion, stars to Hp 4.5-6.5, a landscape under a
town's glow), every star a trail of that length in one direction (drawn), no Milky Way (its own row in the
wide bench), and solved through the ``solve`` workflow with their exact field of view: what is measured is
the detection of trailed stars, not the field-of-view search.  The same pointings, lenses and skies at every
trail length (the photographs differ only in their trails).  Right and wrong as in :mod:`app.bench.wide`.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from app.bench.real import RIGHT_DEG, SUMMARY_HEADER, WRONG_DEG, solve_ours, summarise, summary_columns
from app.bench.wide import jpeg, photograph, photographed_frame

FIELDS_DEG = (40.0, 60.0, 90.0)
#: Trail lengths of the rows, px (0: points).
TRAILS_PX = (0.0, 8.0, 14.0, 20.0)
DEFAULT_N = 4


def run(n_sequences: int | None = None, seed: int = 1) -> dict:
    from app.identification import Sky

    n = DEFAULT_N if n_sequences is None else n_sequences
    sky = Sky()
    load_before = round(os.getloadavg()[0], 2)
    rows = []
    with tempfile.TemporaryDirectory(prefix="starid-trails-") as scratch:
        for trail in TRAILS_PX:
            for fov in FIELDS_DEG:
                for i in range(n):
                    rng = np.random.default_rng([seed, 75, int(fov), i])
                    pixels, true, rotation, described = photograph(fov, rng, smear_px=trail, milky_way=False)
                    name = f"trailed-{trail:g}px-{fov:g}deg-{i}"
                    path = Path(scratch, f"{name}.jpg")
                    path.write_bytes(jpeg(pixels))
                    frame = photographed_frame(name, path, true, rotation)
                    answer = solve_ours(frame, sky, frame.fov_deg, Path(scratch))
                    rows.append({"name": name, "trail_px": trail, "fov_deg": fov, "photograph": described,
                                 "ours": answer})
                    print(f"trails: {name} ({described}): {answer['status']}", file=sys.stderr)
    summary = {f"{trail:g}": summarise([r["ours"] for r in rows if r["trail_px"] == trail]) for trail in TRAILS_PX}
    return {"n_per_cell": n, "seed": seed, "fields_deg": list(FIELDS_DEG), "rows": rows, "summary": summary,
            "load_average_before": load_before, "load_average_after": round(os.getloadavg()[0], 2)}


def format_table(result: dict) -> str:
    lines = [f"{result['n_per_cell']} photographs a field of view ({', '.join(f'{f:g}' for f in result['fields_deg'])} "
             f"deg) and trail, seed {result['seed']}; exact field of view; load average "
             f"{result['load_average_before']} before, {result['load_average_after']} after", "",
             f"{'trail px':<9} {SUMMARY_HEADER}"]
    for trail, s in result["summary"].items():
        lines.append(f"{trail:<9} {summary_columns(s)}")
    lines.append(f"(right: identified within {RIGHT_DEG} deg of the image centre's true direction; wrong: identified "
                 f"and over {WRONG_DEG} deg off)")
    return "\n".join(lines)
