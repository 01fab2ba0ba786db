"""A spacecraft's attitude timeline (app/workflow/timeline.py, GET /api/spacecraft/{name}/timeline).

Gaps, overlaps and jumps are checked on hand-built spans and attitudes whose answers are worked out by
hand; the API on simulated sequences uploaded, searched, confirmed and rejected through the API, whose
points are compared with the stored searches and confirmations and with the simulation's truth; the
archive's query on both backends.
"""

from __future__ import annotations

import dataclasses
import json
import math
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api import create_app
from app.attitude import rotation_from_radec_roll
from app.attitude.rotations import boresight_and_roll_error, radec_roll_from_rotation, rotation_angle_between
from app.camera import CAMERAS
from app.simulate import simulate_sequence
from app.storage import Storage
from app.telemetry.formats import dump_csv, dump_json
from app.workflow import AppContext
from app.workflow.timeline import (ARCSEC, JUMP_CHI2, PlottedAttitude, TimelineEntry, coverage_flags, find_flags,
                                   judge_jump)

T0 = datetime(2021, 3, 4, 5, 0, tzinfo=timezone.utc)
CAMERA = CAMERAS["tubsat-752x582-20deg"]


# ---------------------------------------------------------------------------
# Hand-built spans and attitudes
# ---------------------------------------------------------------------------

def test_gaps_and_overlaps_of_hand_built_spans():
    # 0 = [0, 100] reaches furthest over 1 and 2, which lie inside it: both overlap 0 (by 10 s each); 3 starts
    # 20 s after that reach (no gap at 60 s); 4 starts 700 s after 3 ends (a gap); 5 overlaps 4 by 10 s.
    start = np.array([0.0, 10.0, 30.0, 120.0, 850.0, 860.0])
    end = np.array([100.0, 20.0, 40.0, 150.0, 900.0, 870.0])
    flags = coverage_flags(start, end, gap_s=60.0)
    assert [(f.kind, f.earlier, f.later) for f in flags] == [
        ("overlap", 0, 1), ("overlap", 0, 2), ("gap", 3, 4), ("overlap", 4, 5)]
    assert [f.seconds for f in flags] == [10.0, 10.0, 700.0, 10.0]  # 20-10, 40-30, 850-150, 870-860
    # Spans that only touch, or a pause no longer than the threshold, are neither.
    assert coverage_flags(np.array([0.0, 30.0, 90.0]), np.array([30.0, 60.0, 95.0]), gap_s=30.0) == []
    assert coverage_flags(np.array([5.0]), np.array([9.0]), gap_s=1.0) == []


def _rodrigues(axis, angle):
    """exp(angle [axis]x), written out (independent of app.attitude)."""
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _attitude(R, sigma_arcsec=(10.0, 10.0), rate=None, rate_sigma=None) -> PlottedAttitude:
    ra, dec, roll = radec_roll_from_rotation(R)
    return PlottedAttitude(rank=1, rotation=np.asarray(R), ra_deg=ra, dec_deg=dec, roll_deg=roll,
                           sigma_cross_rad=sigma_arcsec[0] * ARCSEC, sigma_roll_rad=sigma_arcsec[1] * ARCSEC,
                           rate_rad_s=None if rate is None else np.asarray(rate, dtype=float),
                           rate_sigma_rad_s=None if rate is None else np.asarray(rate_sigma, dtype=float))


RATE = np.array([0.0, 1e-3, 0.0])  # rad/s about the camera's y axis
R_A = rotation_from_radec_roll(10.0, 20.0, 30.0)
# 60 s later at that rate: a fixed direction seen from the turning camera turns by -w dt, so R_B = exp(-[w]x dt) R_A.
R_B = _rodrigues([0, 1, 0], -0.06) @ R_A


def test_an_attitude_the_body_rate_carries_to_is_no_jump_and_one_off_by_more_than_its_sigma_is():
    a = _attitude(R_A, rate=RATE, rate_sigma=[1e-7] * 3)
    angle, sigma, chi2 = judge_jump(a, _attitude(R_B), 60.0)
    assert angle < 1e-12 and chi2 < 1e-12
    # sigma: sqrt(2 (10")^2 x-axis + the same on y + 2 (10")^2 roll + 3 (1e-7 rad/s 60 s)^2)
    assert sigma == pytest.approx(math.sqrt(6 * (10 * ARCSEC) ** 2 + 3 * (6e-6) ** 2), rel=1e-9)
    # 36" off about the camera's x axis: chi2 = 36^2 / (2 * 10^2 + (6e-6 rad)^2) = 6.4 or so, below 16.3.
    small = _rodrigues([1, 0, 0], 36 * ARCSEC) @ R_B
    angle, _, chi2 = judge_jump(a, _attitude(small), 60.0)
    assert angle == pytest.approx(36 * ARCSEC, rel=1e-6)
    assert chi2 == pytest.approx(36 ** 2 / (200 + (6e-6 / ARCSEC) ** 2), rel=1e-6) and chi2 < JUMP_CHI2
    # 0.05 deg (180") off: chi2 = 180^2 / 201.5 = 161 > 16.3.
    big = _rodrigues([1, 0, 0], math.radians(0.05)) @ R_B
    angle, _, chi2 = judge_jump(a, _attitude(big), 60.0)
    assert math.degrees(angle) == pytest.approx(0.05, rel=1e-6) and chi2 > JUMP_CHI2
    # The same 0.05 deg is no jump when the rate is that uncertain: 1e-4 rad/s over 60 s is 1238" per axis.
    loose = _attitude(R_A, rate=RATE, rate_sigma=[1e-4] * 3)
    assert judge_jump(loose, _attitude(big), 60.0)[2] < 1.0
    # Roll is judged with the roll sigma: 0.05 deg about the boresight against a roll sigma of 200".
    rolled = _rodrigues([0, 0, 1], math.radians(0.05)) @ R_B
    chi2 = judge_jump(_attitude(R_A, (10.0, 200.0), RATE, [1e-7] * 3), _attitude(rolled, (10.0, 200.0)), 60.0)[2]
    assert chi2 == pytest.approx(180 ** 2 / (2 * 200 ** 2 + (6e-6 / ARCSEC) ** 2), rel=1e-6)
    # Without a rate on the earlier attitude the later one's carries it back; with none, no judgment.
    assert judge_jump(_attitude(R_A), _attitude(R_B, rate=RATE, rate_sigma=[1e-7] * 3), 60.0)[2] < 1e-12
    assert judge_jump(_attitude(R_A), _attitude(R_B), 60.0) is None
    assert judge_jump(a, dataclasses.replace(_attitude(R_B), sigma_cross_rad=None), 60.0) is None


def _entry(k, start_s, end_s, status="identified", attitude=None, epoch_s=None) -> TimelineEntry:
    t = lambda s: T0 + timedelta(seconds=s)  # noqa: E731
    return TimelineEntry(seq_id=100 + k, sequence_id=f"s{k}", filename=None, status=status, start=t(start_s),
                         end=t(end_s), epoch=t(start_s if epoch_s is None else epoch_s), n_snapshots=16,
                         search_id=None, method=None, by=None, verdict_at=None, reason=None, attitude=attitude)


def test_find_flags_judges_consecutive_trusted_attitudes_within_coverage():
    rate = dict(rate=RATE, rate_sigma=[1e-7] * 3)
    off = _rodrigues([1, 0, 0], math.radians(1.0)) @ R_B
    entries = [
        _entry(0, 0, 30, attitude=_attitude(R_A, **rate), epoch_s=0),
        # ambiguous, 1 deg off: not trusted, so neither judged nor the attitude the next is judged against
        _entry(1, 40, 70, "ambiguous", _attitude(off, **rate), epoch_s=60),
        _entry(2, 50, 80, "confirmed", _attitude(R_B, **rate), epoch_s=60),   # overlaps 1; R_B is no jump
        _entry(3, 90, 100, "no_match"),
        _entry(4, 110, 140, attitude=_attitude(off), epoch_s=120),           # 1 deg off R_B carried: a jump
        _entry(5, 1000, 1010, attitude=_attitude(R_A, **rate), epoch_s=1000),  # after a gap: not judged
    ]
    flags = find_flags(entries, gap_s=600.0)
    assert [(f.kind, f.earlier, f.later) for f in flags] == [("overlap", 1, 2), ("jump", 2, 4), ("gap", 4, 5)]
    jump = flags[1]
    assert jump.seconds == 60.0
    # R_B carried 60 s more is exp(-[w]x 60) R_B; the 1 deg offset about x of R_B, seen from there:
    expected = rotation_angle_between(_rodrigues([0, 1, 0], -0.06) @ R_B, off)
    assert jump.angle_rad == pytest.approx(expected, rel=1e-9) and math.degrees(jump.angle_rad) > 1.0


# ---------------------------------------------------------------------------
# The API over simulated sequences
# ---------------------------------------------------------------------------

SPACECRAFT = "TL-SAT"


def _simulated(seed: int, start: datetime, pointing_R: np.ndarray | None, spacecraft: str, name: str = "",
               scenario: str = "nominal") -> tuple:
    """A sequence of ``spacecraft``; the same seed gives the same body rate and snapshot spacing (drawn first)."""
    pointing = None if pointing_R is None else radec_roll_from_rotation(pointing_R)
    seq, truth = simulate_sequence(np.random.default_rng(seed), CAMERA, scenario, pointing=pointing,
                                   start_time=start, sequence_id=name)
    return dataclasses.replace(seq, spacecraft=spacecraft), truth


def _mid_time(truth) -> datetime:
    return datetime.fromisoformat(truth["times"][len(truth["times"]) // 2].replace("Z", "+00:00"))


def trajectory_uploads(spacecraft: str, prefix: str = "tl") -> list[tuple[str, str, str, dict]]:
    """``(key, file name, text, truth)`` of five uploads of ``spacecraft``: one trajectory at one body rate over
    three sequences 2 min apart (``s1``, ``s2``; ``s3`` turned 2 deg off it about the camera's x axis), ``s2``
    again as CSV (``s2csv``: the same span, an overlap), and the Earth filling the view two hours later
    (``earth``: no match).  Sequence ids ``{prefix}-1``, ``{prefix}-2``, ``{prefix}-3``, ``{prefix}-earth``."""
    R1 = rotation_from_radec_roll(150.0, 40.0, 20.0)
    s1, t1 = _simulated(7, T0, R1, spacecraft, f"{prefix}-1")
    rate = np.asarray(t1["body_rate_rad_s"])

    def on_track(start):  # the attitude of the trajectory at the middle snapshot of a sequence from `start`
        dt = (_mid_time(_simulated(7, start, R1, spacecraft)[1]) - _mid_time(t1)).total_seconds()
        return _rodrigues(rate, -np.linalg.norm(rate) * dt) @ R1  # exp(-[w]x dt) R1

    s2, t2 = _simulated(7, T0 + timedelta(seconds=120), on_track(T0 + timedelta(seconds=120)), spacecraft,
                        f"{prefix}-2")
    turned = _rodrigues([1, 0, 0], math.radians(2.0)) @ on_track(T0 + timedelta(seconds=240))
    s3, t3 = _simulated(7, T0 + timedelta(seconds=240), turned, spacecraft, f"{prefix}-3")
    s5, t5 = _simulated(8, T0 + timedelta(hours=2), None, spacecraft, f"{prefix}-earth", scenario="earth")
    assert np.allclose(t2["body_rate_rad_s"], rate) and np.allclose(t3["body_rate_rad_s"], rate)
    return [("s1", "s1.json", dump_json(s1), t1), ("s2", "s2.json", dump_json(s2), t2),
            ("s2csv", "s2.csv", dump_csv(s2), t2), ("s3", "s3.json", dump_json(s3), t3),
            ("earth", "earth.json", dump_json(s5), t5)]


@pytest.fixture(scope="module")
def stored(tmp_path_factory, sky):
    """The five :func:`trajectory_uploads` of TL-SAT uploaded and searched through the API; ``s1`` confirmed by
    ann, ``earth`` (no match) rejected by bob."""
    ctx = AppContext(storage=Storage.open(tmp_path_factory.mktemp("timeline") / "t.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    ids, truths = {}, {}
    for key, filename, text, truth in trajectory_uploads(SPACECRAFT):
        csv = filename.endswith(".csv")
        r = client.post(f"/api/sequences?filename={filename}", content=text.encode(),
                        headers={"Content-Type": "text/csv" if csv else "application/json"})
        assert r.status_code == 201, r.text
        ids[key], truths[key] = r.json()["id"], truth
        search = client.post(f"/api/sequences/{ids[key]}/search", json={"method": "bright_pair"})
        assert search.status_code == 200, search.text
    r = client.post(f"/api/sequences/{ids['s1']}/confirm", json={"rank": 1, "operator": "ann"})
    assert r.status_code == 201, r.text
    r = client.post(f"/api/sequences/{ids['earth']}/reject", json={"operator": "bob", "reason": "the Earth"})
    assert r.status_code == 201, r.text
    yield client, ids, truths
    ctx.close()


def _get(client, **params):
    return client.get(f"/api/spacecraft/{SPACECRAFT}/timeline", params=params)


def test_timeline_points_are_the_stored_attitudes_and_the_truth(stored):
    client, ids, truths = stored
    doc = _get(client).json()
    assert doc["total"] == 5 and doc["start"] is None and doc["limit"] == 200
    points = {p["sequence"]: p for p in doc["points"]}
    assert [p["sequence"] for p in doc["points"]] == [ids[k] for k in ("s1", "s2", "s2csv", "s3", "earth")]
    for key, seq_id in ids.items():
        p, detail = points[seq_id], client.get(f"/api/sequences/{seq_id}").json()
        truth = truths[key]
        assert (p["start"], p["end"]) == (truth["times"][0], truth["times"][-1])
        assert p["search_id"] == detail["search"]["search_id"] and p["method"] == "bright_pair"
        if key == "earth":
            assert p["status"] == "rejected" and p["by"] == "bob" and p["reason"] == "the Earth"
            assert p["ra_deg"] is None and p["rank"] is None
            continue
        stored_candidate = detail["confirmation"]["candidate"] if key == "s1" else detail["search"]["candidates"][0]
        assert p["status"] == ("confirmed" if key == "s1" else "identified")
        assert p["by"] == ("ann" if key == "s1" else None)
        assert [p["ra_deg"], p["dec_deg"], p["roll_deg"]] == [stored_candidate[k] for k in ("ra_deg", "dec_deg",
                                                                                           "roll_deg")]
        assert p["epoch"] == detail["search"]["reference_time"]
        # The truth at the reference snapshot: the boresight within 0.01 deg, the roll within 5 sigma.
        ref = truth["times"].index(p["epoch"])
        R = rotation_from_radec_roll(p["ra_deg"], p["dec_deg"], p["roll_deg"])
        boresight, roll = boresight_and_roll_error(R, np.array(truth["rotation_matrices"][ref]))
        assert math.degrees(boresight) < 0.01
        assert math.degrees(roll) < 5 * stored_candidate["sigma_roll_arcsec"] / 3600, (key, math.degrees(roll))
        # 1-sigma bands from the stored candidate's sigmas; the rate's magnitude against the truth's.
        cross = stored_candidate["sigma_cross_boresight_arcsec"] / 3600
        assert p["sigma_dec_deg"] == pytest.approx(cross, rel=1e-6)
        assert p["sigma_ra_deg"] == pytest.approx(cross / math.cos(math.radians(p["dec_deg"])), rel=1e-6)
        rate = math.degrees(np.linalg.norm(truth["body_rate_rad_s"]))
        assert p["rate_deg_s"] == pytest.approx(rate, abs=max(5 * p["sigma_rate_deg_s"], 1e-4 * rate))
    flags = [(f["kind"], f["earlier"], f["later"]) for f in doc["flags"]]
    assert ("overlap", ids["s2"], ids["s2csv"]) in flags
    assert ("gap", ids["s3"], ids["earth"]) in flags
    jumps = [f for f in doc["flags"] if f["kind"] == "jump"]
    assert [f["later"] for f in jumps] == [ids["s3"]], doc["flags"]
    # 2 deg turned off the trajectory, found to within the rate's uncertainty carried over the 106 s between them.
    assert abs(jumps[0]["angle_deg"] - 2.0) < 3 * jumps[0]["sigma_deg"] and jumps[0]["chi2"] > JUMP_CHI2
    assert "jump" in jumps[0]["text"] and f"#{ids['s3']}" in jumps[0]["text"]
    assert len(flags) == 3


def test_a_range_and_the_limit_bound_the_answer(stored):
    client, ids, truths = stored
    within = _get(client, start=truths["s2"]["times"][0], end=truths["s3"]["times"][0]).json()
    assert [p["sequence"] for p in within["points"]] == [ids["s2"], ids["s2csv"]] and within["total"] == 2
    newest = _get(client, limit=2).json()  # no range: the newest two, oldest first
    assert [p["sequence"] for p in newest["points"]] == [ids["s3"], ids["earth"]] and newest["total"] == 5
    empty = _get(client, start="2030-01-01T00:00:00Z", end="2030-01-02T00:00:00Z")
    assert empty.status_code == 200 and empty.json()["points"] == [] and empty.json()["flags"] == []
    # A gap threshold longer than the two-hour pause: no gap.
    assert all(f["kind"] != "gap" for f in _get(client, gap_s=3 * 3600).json()["flags"])


@pytest.mark.parametrize("params, status, where", [
    ({"start": "2021-03-04T06:00:00Z", "end": "2021-03-04T05:00:00Z"}, 422, "query.end"),
    ({"start": "2021-03-04T05:00:00Z", "end": "2021-03-04T05:00:00Z"}, 422, "query.end"),
    ({"start": "yesterday"}, 422, "query.start"),
    ({"end": "2021-02-30T00:00:00Z"}, 422, "query.end"),
    ({"start": "0001-01-01T00:00:00+00:01"}, 422, "query.start"),
    ({"limit": 0}, 422, "query.limit"),
    ({"limit": 501}, 422, "query.limit"),
    ({"limit": "many"}, 422, "query.limit"),
    ({"gap_s": 0}, 422, "query.gap_s"),
    ({"gap_s": "nan"}, 422, "query.gap_s"),
    ({"gap_s": "inf"}, 422, "query.gap_s"),
    ({"start": "2000-01-01T00:00:00Z", "end": "2100-01-01T00:00:00Z", "limit": 4}, 422, "query"),
])
def test_bad_or_too_wide_ranges_are_refused_where_they_are_wrong(stored, params, status, where):
    client, _, _ = stored
    r = _get(client, **params)
    assert r.status_code == status, r.text
    assert where in [p["location"] for p in r.json()["problems"]], r.json()
    if where == "query":
        assert "holds 5 sequences" in r.json()["detail"] and "limit of 4" in r.json()["detail"]


def test_an_unknown_spacecraft_is_404(stored):
    client, _, _ = stored
    r = client.get("/api/spacecraft/NOBODY/timeline")
    assert r.status_code == 404 and "NOBODY" in r.json()["detail"]


# ---------------------------------------------------------------------------
# The archive's query, on both backends
# ---------------------------------------------------------------------------

def _telemetry(name: str, start: datetime) -> str:
    snapshots = [{"index": i, "time": (start + timedelta(seconds=2 * i)).isoformat().replace("+00:00", "Z"),
                  "sources": [{"x": 100.0, "y": 100.0, "brightness": 10.0}]} for i in range(3)]
    return json.dumps({"format": "tubsat-snapshots/1", "sequence_id": name, "spacecraft": "Q-SAT",
                       "camera": {"name": "tubsat-752x582-20deg"}, "snapshots": snapshots})


def test_timeline_rows_reads_range_searches_and_verdicts_on_both_backends(archive_url):
    with Storage.open(archive_url) as storage:
        ids = []
        for k in range(4):
            start = T0 + timedelta(minutes=k)
            row, _ = storage.add_sequence(raw_text=_telemetry(f"q{k}", start), sequence_id=f"q{k}",
                                          spacecraft="Q-SAT", first_time=start, n_snapshots=3)
            ids.append(row.id)
        storage.add_sequence(raw_text="untimed", spacecraft="Q-SAT")  # no time: in no range
        storage.add_sequence(raw_text=_telemetry("other", T0), spacecraft="OTHER", first_time=T0)
        for k in (0, 1):
            for n in range(2):  # the newest search is the one read
                storage.add_search(ids[k], pattern_version=None, method=f"m{n}", options={}, result={"n": n},
                                   status="identified")
        confirm = dict(search_id=None, rank=1, quaternion=[0, 0, 0, 1], rotation_matrix=np.eye(3).tolist(),
                       ra_deg=0, dec_deg=0, roll_deg=0, deviation_arcsec=None, false_match_probability=None,
                       pattern={}, candidate={}, apm_text="apm")
        storage.add_confirmation(ids[0], operator="ann", **confirm)
        second = storage.add_confirmation(ids[0], operator="cy", **confirm)  # supersedes ann's
        storage.add_rejection(ids[1], operator="bob", reason="no")
        storage.add_confirmation(ids[2], operator="dee", **confirm)
        withdrawn = storage.add_rejection(ids[2], operator="eve", reason="wrong", supersede=True)

        rows, total = storage.timeline_rows("Q-SAT", None, None, 10)
        assert total == 4 and [r.id for r, _, _ in rows] == ids
        assert all(r.raw_text == _telemetry(f"q{k}", T0 + timedelta(minutes=k)) for k, (r, _, _) in enumerate(rows))
        assert [None if s is None else s.result for _, s, _ in rows] == [{"n": 1}, {"n": 1}, None, None]
        verdicts = [v for _, _, v in rows]
        assert verdicts[0].id == second.id and verdicts[0].operator == "cy"
        assert verdicts[1].operator == "bob" and verdicts[2].id == withdrawn.id and verdicts[3] is None
        rows, total = storage.timeline_rows("Q-SAT", T0 + timedelta(minutes=1), T0 + timedelta(minutes=3), 10)
        assert total == 2 and [r.id for r, _, _ in rows] == ids[1:3]
        rows, total = storage.timeline_rows("Q-SAT", None, None, 2)  # the newest two, oldest first
        assert total == 4 and [r.id for r, _, _ in rows] == ids[2:]
        assert storage.timeline_rows("NOBODY", None, None, 5) == ([], 0)
        with pytest.raises(ValueError):
            storage.timeline_rows("Q-SAT", None, None, 0)
