"""The API's CCSDS APM and AEM read by an independent ADM parser (``ccsds-ndm-py``, test-only).

A sequence is uploaded, searched and confirmed through the API; its APM and
AEM are parsed by the ``ccsds_ndm`` package (a Rust implementation of CCSDS
502/504, nothing of ours), and their quaternions are turned back into
matrices without :mod:`app.ccsds`:

ADM 2.0 annex F2: the quaternion (Q1, Q2, Q3, QC) goes from REF_FRAME_A
(ICRF) to REF_FRAME_B (the camera) and transforms coordinates as
``X_B = M_BA X_A`` where ``M_BA`` is the *transpose* of the active rotation
matrix of the scalar-last quaternion (scipy's ``Rotation.from_quat``).  So
``M = from_quat([Q1, Q2, Q3, QC]).as_matrix().T`` must equal the candidate's
``rotation_matrix`` (ICRS -> camera) to the 15 decimals written, and must
match the simulator's true attitude of each snapshot to a small fraction of
a degree.  The opposite reading (no transpose) is checked to be far off, so
the test tells the two directions apart.
"""

from __future__ import annotations

import json
from datetime import datetime, timezone

import ccsds_ndm
import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from app.api import create_app
from app.workflow import AppContext
from app.storage import Storage

SAMPLES = ("01-clean.json", "09-wide-30deg.json")


def _rotation_angle_deg(a, b) -> float:
    """Angle of the rotation a b^T: 0 when the matrices are the same attitude."""
    cos = (np.trace(np.asarray(a) @ np.asarray(b).T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _matrix_from_file_quaternion(q1, q2, q3, qc) -> np.ndarray:
    """Annex F2's M_BA for the quaternion A -> B: the transpose of the active matrix (scipy)."""
    return Rotation.from_quat([q1, q2, q3, qc]).as_matrix().T


def _utc(text: str) -> datetime:
    """A KVN or truth-file time (``...Z`` or none) as an aware UTC datetime."""
    return datetime.fromisoformat(text.rstrip("Z")).replace(tzinfo=timezone.utc)


@pytest.fixture(scope="module")
def confirmed(tmp_path_factory, sky, sample_dir):
    """For each sample: (search document, confirmation document, APM text, AEM text, truth)."""
    ctx = AppContext(storage=Storage.open(tmp_path_factory.mktemp("ccsds") / "c.sqlite3"), sky=sky)
    client = TestClient(create_app(ctx))
    out = {}
    try:
        for name in SAMPLES:
            data = (sample_dir / name).read_bytes()
            r = client.post("/api/sequences", files={"file": (name, data, "application/json")})
            assert r.status_code == 201, r.text
            sid = r.json()["id"]
            search = client.post(f"/api/sequences/{sid}/search", json={}).json()
            assert search["status"] == "identified", search
            r = client.post(f"/api/sequences/{sid}/confirm", json={"rank": 1, "operator": "Zoë Ünal"})
            assert r.status_code == 201, r.text
            attitude = r.json()
            apm = client.get(attitude["apm_url"])
            aem = client.get(attitude["aem_url"])
            assert apm.status_code == 200 and aem.status_code == 200
            truth = json.loads((sample_dir / name.replace(".json", ".truth.json")).read_text())
            out[name] = (search, attitude, apm.text, aem.text, truth)
    finally:
        ctx.close()
    return out


@pytest.mark.parametrize("name", SAMPLES)
def test_apm_parses_and_its_quaternion_is_the_candidate_rotation(confirmed, name):
    search, attitude, apm_text, _, truth = confirmed[name]
    apm = ccsds_ndm.from_str(apm_text)
    assert isinstance(apm, ccsds_ndm.Apm)
    apm.validate()  # raises on a violation of the standard
    assert str(apm.version) == "2.0"
    metadata, data = apm.segment.metadata, apm.segment.data
    assert str(metadata.time_system) == "UTC"
    # Text values are upper case (ADM 6.8.6): the spacecraft and the sequence's own id.
    assert (metadata.object_name, metadata.object_id) == (attitude["spacecraft"].upper(),
                                                          truth["sequence_id"].upper())
    ref = search["reference_snapshot"]
    assert _utc(data.epoch) == _utc(truth["times"][ref])
    (state,) = data.quaternion_state
    assert (str(state.ref_frame_a), str(state.ref_frame_b)) == ("ICRF", "SENSOR_1")
    q = np.array([state.q1, state.q2, state.q3, state.qc])
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12)

    M = _matrix_from_file_quaternion(*q)
    candidate = np.array(search["candidates"][0]["rotation_matrix"])
    assert np.abs(M - candidate).max() < 1e-9  # the JSON matrix has 10 decimals
    assert np.abs(M - np.array(attitude["rotation_matrix"])).max() < 1e-9  # the JSON matrix has 10 decimals
    # The identified attitude is the simulator's true one (the clean and wide samples solve to arcseconds).
    assert _rotation_angle_deg(M, truth["rotation_matrices"][ref]) < 0.05
    # The other direction of the quaternion would be a different attitude: the check above discriminates.
    assert _rotation_angle_deg(M.T, truth["rotation_matrices"][ref]) > 1.0
    # Its quality in the reader's terms: the matched stars and their RMS residual; the seed's deviation is named a
    # sum over the pattern's points (read alone, "deviation 1388 arcsec" looked like a pointing error).
    best = search["candidates"][0]
    comments = " ".join(line[len("COMMENT "):] for line in apm_text.splitlines() if line.startswith("COMMENT "))
    assert (f"{best['n_matched']} stars matched, residual {best['rms_arcsec']:.1f} arcsec RMS; deviation "
            f"{best['deviation_arcsec']} arcsec summed over the pattern's points") in comments


@pytest.mark.parametrize("name", SAMPLES)
def test_aem_parses_and_each_quaternion_is_the_snapshot_attitude(confirmed, name):
    search, attitude, _, aem_text, truth = confirmed[name]
    aem = ccsds_ndm.from_str(aem_text)
    assert isinstance(aem, ccsds_ndm.Aem)
    aem.validate()
    assert str(aem.version) == "2.0"
    (segment,) = aem.segments
    metadata = segment.metadata
    assert (str(metadata.ref_frame_a), str(metadata.ref_frame_b)) == ("ICRF", "SENSOR_1")
    assert str(metadata.attitude_type) == "QUATERNION" and str(metadata.time_system) == "UTC"

    epochs = [_utc(t) for t in segment.data.attitude_states_epochs]
    quaternions = np.asarray(segment.data.attitude_states_numpy, dtype=float)
    assert quaternions.shape == (len(epochs), 4)
    assert _utc(metadata.start_time) == epochs[0] and _utc(metadata.stop_time) == epochs[-1]
    truth_times = [_utc(t) for t in truth["times"]]
    assert len(epochs) >= 12  # nearly every snapshot of these samples is linked to the reference
    assert set(epochs) <= set(truth_times) and epochs == sorted(epochs)

    ref = search["reference_snapshot"]
    for epoch, q in zip(epochs, quaternions):
        i = truth_times.index(epoch)
        M = _matrix_from_file_quaternion(*q)
        # Other snapshots' attitudes come from the tracked motion, so their error grows towards the
        # ends of the sequence (up to ~0.15 deg of roll seen on the 30 deg camera); the boresight is tighter.
        true_matrix = np.array(truth["rotation_matrices"][i])
        assert _rotation_angle_deg(M, true_matrix) < 0.25, (name, i)
        assert np.degrees(np.arccos(np.clip(M[2] @ true_matrix[2], -1, 1))) < 0.1, (name, i)
        if i == ref:  # the reference snapshot's attitude is the confirmed one itself
            assert np.abs(M - np.array(attitude["rotation_matrix"])).max() < 1e-9  # the JSON matrix has 10 decimals
    assert truth_times[ref] in epochs
