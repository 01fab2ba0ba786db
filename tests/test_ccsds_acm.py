"""The CCSDS ACM (ADM 2.0 section 5) of a confirmed attitude, read by an independent parser (issue 14).

Samples are uploaded, searched and confirmed through the API; their ACMs
(``GET /api/attitudes/{id}/acm``) are parsed by ``ccsds-ndm-py`` (a Rust
implementation of CCSDS 504, nothing of ours) and checked against the
simulator's truth without :mod:`app.ccsds`: the data lines' times are seconds
after EPOCH_TZERO, each quaternion goes ICRF -> camera and transforms
coordinates (annex F2: ``M = from_quat([Q1, Q2, Q3, QC]).as_matrix().T``, as
in test_ccsds_independent.py), the rate columns are the fitted body rate, the
covariance holds the attitude's 1-sigma squared in deg**2, the attitude
determination block names the method and the sensor.  The writer itself is
checked for its refusals and its optional blocks.
"""

from __future__ import annotations

import json
from datetime import datetime, timedelta, timezone

import ccsds_ndm
import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from app.api import create_app
from app.ccsds import MAX_LINE_LENGTH, AcmDetermination, AcmSensor, KvnError, acm_kvn
from app.storage import Storage
from app.workflow import AppContext

SAMPLES = ("01-clean.json", "09-wide-30deg.json")
T0 = datetime(2024, 3, 1, 12, 0, 0, tzinfo=timezone.utc)


def _utc(text: str) -> datetime:
    return datetime.fromisoformat(text.rstrip("Z")).replace(tzinfo=timezone.utc)


def _matrix(q1, q2, q3, qc) -> np.ndarray:
    return Rotation.from_quat([q1, q2, q3, qc]).as_matrix().T


def _angle_deg(a, b) -> float:
    cos = (np.trace(np.asarray(a) @ np.asarray(b).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@pytest.fixture(scope="module")
def confirmed(tmp_path_factory, sky, sample_dir):
    """For each sample: (search, attitude document, ACM text, ACM text fetched again, truth, stored row)."""
    ctx = AppContext(storage=Storage.open(tmp_path_factory.mktemp("acm") / "acm.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    out = {}
    try:
        for name in SAMPLES:
            r = client.post("/api/sequences", files={"file": (name, (sample_dir / name).read_bytes(), "application/json")})
            assert r.status_code == 201, r.text
            sid = r.json()["id"]
            search = client.post(f"/api/sequences/{sid}/search", json={}).json()
            assert search["status"] == "identified", search
            r = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "Zoë Ünal"})
            assert r.status_code == 201, r.text
            attitude = r.json()
            assert attitude["acm_url"] == f"/api/attitudes/{attitude['id']}/acm"
            first, again = (client.get(attitude["acm_url"]) for _ in range(2))
            assert first.status_code == 200 and again.status_code == 200
            assert first.headers["content-disposition"].endswith('.acm"')
            truth = json.loads((sample_dir / name.replace(".json", ".truth.json")).read_text())
            out[name] = (search, attitude, first.text, again.text, truth, ctx.storage.get_confirmation(attitude["id"]))
        missing = client.get("/api/attitudes/999999/acm")
        assert missing.status_code == 404 and "999999" in missing.json()["detail"]
    finally:
        ctx.close()
    return out


@pytest.mark.parametrize("name", SAMPLES)
def test_acm_parses_and_holds_every_snapshot_attitude_the_rate_the_covariance_and_the_determination(confirmed, name):
    search, attitude, text, again, truth, stored = confirmed[name]
    assert text == again == stored.acm_text  # rendered once, at confirmation, byte for byte
    acm = ccsds_ndm.from_str(text)
    assert isinstance(acm, ccsds_ndm.Acm)
    acm.validate()  # raises on a violation the parser knows of
    assert str(acm.version) == "2.0" and acm.header.originator == "STARID GROUND STATION"
    meta, data = acm.segment.metadata, acm.segment.data
    assert meta.object_name == attitude["spacecraft"].upper() and str(meta.time_system) == "UTC"
    assert any(truth["sequence_id"] in c for c in meta.comment)  # the sequence named in the message
    t0 = _utc(meta.epoch_tzero)
    assert _utc(meta.start_time) == t0

    (att,) = data.att
    assert (str(att.ref_frame_a), str(att.ref_frame_b)) == ("ICRF", "SENSOR_1")
    assert att.att_type == "QUATERNION" and att.rate_type == "ANGVEL" and att.number_states == 7
    assert att.att_basis == "DETERMINED_GND" and att.att_basis_id == f"SEARCH_{search['search_id']}_RANK_1"
    lines = np.asarray(att.att_lines, dtype=float)
    assert lines.shape[1] == 1 + 4 + 3
    epochs = [t0 + timedelta(seconds=float(s)) for s in lines[:, 0]]
    truth_times = [_utc(t) for t in truth["times"]]
    assert len(epochs) == len(truth_times)  # every snapshot, with the fitted rate
    assert _utc(meta.stop_time) == epochs[-1]
    ref = search["reference_snapshot"]
    for i, (epoch, row) in enumerate(zip(epochs, lines)):
        assert abs((epoch - truth_times[i]).total_seconds()) < 1e-6
        assert np.linalg.norm(row[1:5]) == pytest.approx(1.0, abs=1e-12)
        M = _matrix(*row[1:5])
        assert _angle_deg(M, truth["rotation_matrices"][i]) < 0.25, (name, i)
        if i == ref:  # the reference snapshot's attitude is the confirmed one itself
            assert np.abs(M - np.array(attitude["rotation_matrix"])).max() < 1e-9
        # The rate: the confirmed fit's, and (it is a true rate) close to the simulator's.
        assert np.allclose(row[5:8], attitude["rate_deg_s"], rtol=1e-9, atol=1e-12)
    sigma = np.array(attitude["candidate"]["sequence_fit"]["rate_sigma_deg_s"])
    assert np.all(np.abs(lines[0, 5:8] - np.degrees(truth["body_rate_rad_s"])) < 5 * sigma + 1e-6)

    (cov,) = data.cov
    assert (cov.cov_type, cov.cov_basis, str(cov.cov_ref_frame)) == ("ANGLE", "DETERMINED_GND", "SENSOR_1")
    (cov_line,) = cov.cov_lines
    assert t0 + timedelta(seconds=cov_line[0]) == epochs[ref]  # the covariance of the reference attitude
    cross = attitude["candidate"]["sigma_cross_boresight_arcsec"] / 3600.0
    roll = attitude["candidate"]["sigma_roll_arcsec"] / 3600.0
    assert np.allclose(cov_line[1:], [cross ** 2, cross ** 2, roll ** 2], rtol=1e-8)
    assert roll > cross  # a star camera knows its roll worst

    ad = data.ad
    assert ad.ad_id == att.att_basis_id and ad.ad_method == "BATCH" and ad.attitude_states == "QUATERNION"
    assert (str(ad.ref_frame_a), str(ad.ref_frame_b)) == ("ICRF", "SENSOR_1")
    assert ad.cov_type == "ANGLE" and ad.rate_states == "ANGVEL" and ad.number_states == 7
    (sensor,) = ad.sensors
    assert sensor.sensor_number == 1 and sensor.sensor_used == "STAR_TRACKER"
    assert sensor.sensor_noise_stddev == [pytest.approx(attitude["candidate"]["rms_arcsec"] / 3600.0, rel=1e-8)]
    steps = np.diff([t.timestamp() for t in truth_times])
    assert sensor.sensor_frequency == pytest.approx(1.0 / np.median(steps), rel=1e-6)
    assert max(len(line) for line in text.splitlines()) <= MAX_LINE_LENGTH


def test_a_confirmation_stored_before_acms_gets_the_same_acm_rendered_on_request(tmp_path, sky, sample_dir):
    """An archive confirmation without an ACM (made before migration 6): the ACM is rendered from the
    stored record, and is exactly what confirming renders (same inputs, same creation date)."""
    ctx = AppContext(storage=Storage.open(tmp_path / "old.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    try:
        data = (sample_dir / "01-clean.json").read_bytes()
        sid = client.post("/api/sequences", files={"file": ("01.json", data, "application/json")}).json()["id"]
        client.post(f"/api/sequences/{sid}/search", json={})
        new = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "ann", "comment": "ok"}).json()
        stored = ctx.storage.get_confirmation(new["id"])
        fields = {k: getattr(stored, k) for k in (
            "search_id", "rank", "operator", "quaternion", "rotation_matrix", "ra_deg", "dec_deg", "roll_deg",
            "deviation_arcsec", "false_match_probability", "pattern", "candidate", "apm_text", "aem_text",
            "comment", "confirmed_at", "epoch", "rate_deg_s")}
        old = ctx.storage.add_confirmation(sid, **fields, supersede=True)  # no acm_text, as before issue 14
        assert old.acm_text is None
        rendered = client.get(f"/api/attitudes/{old.id}/acm")
        assert rendered.status_code == 200
        assert rendered.text == stored.acm_text
        assert client.get(f"/api/attitudes/{old.id}/acm").text == rendered.text
    finally:
        ctx.close()


# -- the writer ----------------------------------------------------------------------------------------

def _quaternions(n: int) -> list[list[float]]:
    rotations = Rotation.from_rotvec([[0.01 * i, 0.2, -0.3] for i in range(n)])
    q = rotations.as_quat()
    return [list(v * np.sign(v[3])) for v in q]


def test_writer_without_rate_covariance_or_determination_is_a_plain_attitude_history():
    epochs = [T0 + timedelta(seconds=1.5 * i) for i in range(3)]
    text = acm_kvn(epochs=epochs, quaternions_xyzw=_quaternions(3), originator="me", object_name="sat",
                   creation_date=T0)
    assert text == acm_kvn(epochs=epochs, quaternions_xyzw=_quaternions(3), originator="me", object_name="sat",
                           creation_date=T0)  # deterministic
    assert "RATE_TYPE" not in text and "COV_START" not in text and "AD_START" not in text
    acm = ccsds_ndm.from_str(text)
    acm.validate()
    (att,) = acm.segment.data.att
    assert att.number_states == 4 and att.rate_type is None
    assert [line[0] for line in att.att_lines] == [0.0, 1.5, 3.0]
    assert acm.segment.metadata.acm_data_elements.split() == ["ATT"]
    # Quaternions are written as the standard's A -> B quaternion of the project's rotation.
    for q, line in zip(_quaternions(3), att.att_lines):
        assert np.allclose(_matrix(*line[1:5]), Rotation.from_quat(q).as_matrix(), atol=1e-14)


def test_writer_blocks_and_refusals():
    epochs = [T0, T0 + timedelta(seconds=2)]
    sensor = AcmSensor(number=1, used="star_tracker", noise_stddev_deg=(0.001,), frequency_hz=0.5)
    ad = AcmDetermination(ad_id="AD_1", method="BATCH", sensors=(sensor,), cov_type="ANGLE", rate_states="ANGVEL",
                          number_states=7)
    text = acm_kvn(epochs=epochs, quaternions_xyzw=_quaternions(2), originator="me", object_name="sat",
                   rate_deg_s=[0.1, -0.2, 0.0], covariance=(epochs[1], (1e-6, 1e-6, 4e-5)), determination=ad,
                   creation_date=T0)
    acm = ccsds_ndm.from_str(text)
    acm.validate()
    assert acm.segment.metadata.acm_data_elements.split() == ["ATT", "COV", "AD"]
    assert acm.segment.data.cov[0].cov_lines == [[2.0, 1e-6, 1e-6, 4e-5]]
    assert acm.segment.data.ad.sensors[0].sensor_used == "STAR_TRACKER"
    assert "-0 " not in text and "-0\n" not in text  # 6.8.5: no negative zero
    bad = [
        dict(epochs=[T0, T0], quaternions_xyzw=_quaternions(2)),  # not strictly increasing
        dict(epochs=[T0], quaternions_xyzw=_quaternions(2)),  # counts differ
        dict(epochs=[], quaternions_xyzw=[]),
        dict(epochs=epochs, quaternions_xyzw=_quaternions(2), rate_deg_s=[0.1, float("nan"), 0]),
        dict(epochs=epochs, quaternions_xyzw=_quaternions(2), covariance=(T0, (1.0, -1.0, 1.0))),
        dict(epochs=epochs, quaternions_xyzw=_quaternions(2),
             determination=AcmDetermination(ad_id="A", method="GUESS", sensors=())),
        dict(epochs=[T0.replace(tzinfo=None), T0.replace(tzinfo=None) + timedelta(1)], quaternions_xyzw=_quaternions(2)),
    ]
    for kwargs in bad:
        with pytest.raises(KvnError):
            acm_kvn(originator="me", object_name="sat", creation_date=T0, **kwargs)
