"""CCSDS ADM 2.0 APM/AEM writers and the KVN reader, checked against the standard's own examples."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from app.attitude import quaternion_from_rotation, rotation_from_radec_roll
from app.ccsds import (
    CAMERA_FRAME,
    KvnError,
    aem_kvn,
    apm_kvn,
    ccsds_quaternion_from_rotation,
    comment_lines,
    rotation_from_ccsds_quaternion,
)
from kvn_reader import parse_epoch, parse_kvn

EPOCH = datetime(2024, 3, 1, 12, 0, 0, 250000, tzinfo=timezone.utc)
CREATED = datetime(2024, 3, 2, 8, 30, 0, tzinfo=timezone.utc)


def _apm(R, **overrides):
    kwargs = dict(epoch=EPOCH, quaternion_xyzw=quaternion_from_rotation(R), originator="TUB",
                  object_name="TUBSAT-N", object_id="1998-042B", creation_date=CREATED)
    kwargs.update(overrides)
    return apm_kvn(**kwargs)


def _file_quaternion(block_or_line) -> np.ndarray:
    if isinstance(block_or_line, dict):
        return np.array([block_or_line[k] for k in ("Q1", "Q2", "Q3", "QC")])
    return np.array(block_or_line[1:5])


def _random_rotations(n, seed):
    return Rotation.random(n, random_state=seed).as_matrix()


# -- direction and order of the quaternion, against the standard's annex F2 ----------

def test_annex_f2_example_90_degrees_about_z():
    # Annex F2.2: frame B = frame A turned +90 deg about Z (B's X axis is A's Y axis)
    # has the quaternion A->B  Q1 = Q2 = 0, Q3 = QC = 0.7071, and M_BA = [[0,1,0],[-1,0,0],[0,0,1]].
    m_ba = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(ccsds_quaternion_from_rotation(m_ba), [0, 0, np.sqrt(0.5), np.sqrt(0.5)],
                               atol=1e-15)
    np.testing.assert_allclose(rotation_from_ccsds_quaternion(0, 0, np.sqrt(0.5), np.sqrt(0.5)), m_ba,
                               atol=1e-15)
    # Our R (ICRS -> camera, rows = camera axes in ICRS) for a camera whose x axis is ICRS +y
    # is the same matrix, so the APM must hold the same quaternion.
    block = parse_kvn(_apm(m_ba))["data"]["blocks"][0]
    np.testing.assert_allclose(_file_quaternion(block), [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)
    assert (block["REF_FRAME_A"], block["REF_FRAME_B"]) == ("ICRF", CAMERA_FRAME)


def test_apm_quaternion_maps_the_boresight_direction_onto_camera_z():
    # Physical check: the star at the boresight's RA/Dec must land on the camera +z axis.
    ra, dec = np.radians([201.3, -11.2])
    R = rotation_from_radec_roll(201.3, -11.2, 75.0)
    q = _file_quaternion(parse_kvn(_apm(R))["data"]["blocks"][0])
    boresight_icrs = np.array([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)])
    np.testing.assert_allclose(rotation_from_ccsds_quaternion(*q) @ boresight_icrs, [0, 0, 1], atol=1e-12)


def test_apm_round_trip_many_attitudes():
    for R in _random_rotations(40, seed=1):
        q_project = quaternion_from_rotation(R)
        q_file = _file_quaternion(parse_kvn(_apm(R))["data"]["blocks"][0])
        np.testing.assert_allclose(rotation_from_ccsds_quaternion(*q_file), R, atol=1e-12)
        # The file holds the conjugate of the project's scalar-last quaternion.
        back = np.array([-q_file[0], -q_file[1], -q_file[2], q_file[3]])
        np.testing.assert_allclose(back, q_project, atol=1e-9)
        assert q_file[3] >= 0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_any_unit_quaternion_round_trips(values):
    q = np.array(values) / np.linalg.norm(values)
    R = Rotation.from_quat(q).as_matrix()
    q_file = _file_quaternion(parse_kvn(_apm(R, quaternion_xyzw=q))["data"]["blocks"][0])
    np.testing.assert_allclose(rotation_from_ccsds_quaternion(*q_file), R, atol=1e-12)


def test_rotation_to_ccsds_quaternion_is_the_inverse_of_the_annex_formula():
    for R in _random_rotations(25, seed=2):
        q = ccsds_quaternion_from_rotation(R)
        np.testing.assert_allclose(rotation_from_ccsds_quaternion(*q), R, atol=1e-13)


# -- layout: keywords, order, blocks -----------------------------------------------

def test_apm_keywords_follow_tables_3_1_to_3_3():
    text = _apm(np.eye(3), message_id="att-7", header_comments=["made by tests"],
                comments=["deviation 3.2 arcsec"], quaternion_comments=["ICRF to camera"])
    doc = parse_kvn(text)
    assert doc["type"] == "APM" and doc["version"] == "2.0"
    assert doc["keywords"] == [
        "CCSDS_APM_VERS", "COMMENT", "CREATION_DATE", "ORIGINATOR", "MESSAGE_ID",
        "OBJECT_NAME", "OBJECT_ID", "CENTER_NAME", "TIME_SYSTEM",
        "COMMENT", "EPOCH",
        "QUAT_START", "COMMENT", "REF_FRAME_A", "REF_FRAME_B", "Q1", "Q2", "Q3", "QC", "QUAT_STOP",
    ]
    assert text.splitlines()[0] == "CCSDS_APM_VERS = 2.0"
    assert doc["header"]["COMMENT"] == ["made by tests"]
    assert doc["data"]["COMMENT"] == ["deviation 3.2 arcsec"]
    assert doc["data"]["blocks"][0]["COMMENT"] == ["ICRF to camera"]
    assert doc["metadata"]["TIME_SYSTEM"] == "UTC"
    assert parse_epoch(doc["data"]["EPOCH"]) == EPOCH
    assert parse_epoch(doc["header"]["CREATION_DATE"]) == CREATED
    # Version-1.0-only keywords and an APM metadata block delimiter must not appear.
    for old in ("Q_DIR", "ATTITUDE_DIR", "QUATERNION_TYPE", "META_START", "CCSDS_APM_VERS = 1.0"):
        assert old not in text


def test_aem_keywords_follow_tables_4_2_to_4_4():
    epochs = [EPOCH + timedelta(seconds=2 * i) for i in range(16)]
    rotations = _random_rotations(16, seed=3)
    text = aem_kvn(epochs=epochs, quaternions_xyzw=[quaternion_from_rotation(R) for R in rotations],
                   originator="TUB", object_name="TUBSAT-N", object_id="1998-042B",
                   comments=["sequence 12"], data_comments=["one line per snapshot"],
                   creation_date=CREATED)
    doc = parse_kvn(text)
    assert doc["type"] == "AEM" and doc["version"] == "2.0"
    assert doc["keywords"] == [
        "CCSDS_AEM_VERS", "CREATION_DATE", "ORIGINATOR",
        "META_START", "COMMENT", "OBJECT_NAME", "OBJECT_ID", "CENTER_NAME", "REF_FRAME_A",
        "REF_FRAME_B", "TIME_SYSTEM", "START_TIME", "STOP_TIME", "ATTITUDE_TYPE", "META_STOP",
        "DATA_START", "COMMENT", *["<DATA>"] * 16, "DATA_STOP",
    ]
    (segment,) = doc["segments"]
    meta = segment["metadata"]
    assert (meta["REF_FRAME_A"], meta["REF_FRAME_B"], meta["ATTITUDE_TYPE"]) == ("ICRF", CAMERA_FRAME, "QUATERNION")
    assert parse_epoch(meta["START_TIME"]) == epochs[0]
    assert parse_epoch(meta["STOP_TIME"]) == epochs[-1]
    for line, t, R in zip(segment["data"]["lines"], epochs, rotations):
        assert parse_epoch(line[0]) == t
        np.testing.assert_allclose(rotation_from_ccsds_quaternion(*_file_quaternion(line)), R, atol=1e-12)
    for old in ("ATTITUDE_DIR", "QUATERNION_TYPE", "Q_DIR"):
        assert old not in text


def test_output_is_deterministic_and_creation_date_is_an_input():
    R = rotation_from_radec_roll(10.0, 20.0, 30.0)
    assert _apm(R) == _apm(R)
    later = _apm(R, creation_date=CREATED + timedelta(hours=1))
    differing = [(a, b) for a, b in zip(_apm(R).splitlines(), later.splitlines()) if a != b]
    assert [a.split(" = ")[0] for a, _ in differing] == ["CREATION_DATE"]
    kwargs = dict(epochs=[EPOCH, EPOCH + timedelta(seconds=1)], quaternions_xyzw=[[0, 0, 0, 1]] * 2,
                  originator="TUB", object_name="A", object_id="B", creation_date=CREATED)
    assert aem_kvn(**kwargs) == aem_kvn(**kwargs)


def test_lines_are_printable_ascii_within_254_characters():
    text = _apm(np.eye(3), comments=["Operator Jürgen Müller: ok ✓", "x" * 600], object_name="tübsat n")
    lines = text.splitlines()
    assert all(len(line) <= 254 and all(32 <= ord(c) < 127 for c in line) for line in lines)
    doc = parse_kvn(text)
    assert doc["data"]["COMMENT"][0] == "Operator Jurgen Muller: ok \\u2713"
    assert "".join(doc["data"]["COMMENT"][1:]) == "x" * 600
    assert doc["metadata"]["OBJECT_NAME"] == "TUBSAT N"  # 6.8.6: all upper case


def test_names_and_comments_in_any_script_keep_who_and_what_in_ascii():
    """Two operators named in Chinese both read "Confirmed by ??" and a Russian comment was all question marks:
    a comment's non-Latin characters are escaped as Python does (readable back with unicode_escape), accents
    dropped as before, and control or bidirectional characters still say nothing ('?')."""
    import codecs

    said = ["Confirmed by 张伟", "Confirmed by 李娜", "Комментарий: звезда не та 😀", "Jürgen \u202e"]
    lines = comment_lines(said)
    assert lines[0] != lines[1] and all(line.isascii() for line in lines)
    back = [codecs.decode(line.removeprefix("COMMENT "), "unicode_escape") for line in lines]
    assert back == said[:3] + ["Jurgen ?"]


def test_a_long_comment_is_wrapped_between_words():
    """An operator's long override reason reads whole: each COMMENT line ends at a word (it once cut
    "supersede" into "supers" / "ede"), and the words joined again are the text."""
    words = [f"word{k}" if k % 7 else "supersede" for k in range(120)]
    lines = comment_lines([" ".join(words)])
    assert len(lines) > 2 and all(len(line) <= 254 and line.startswith("COMMENT ") for line in lines)
    assert [w for line in lines for w in line[len("COMMENT "):].split(" ")] == words


def test_negative_zero_is_never_written():
    text = _apm(np.eye(3), quaternion_xyzw=[-0.0, 1e-18, -1e-18, 1.0])
    values = dict(line.split(" = ") for line in text.splitlines() if line[:3] in ("Q1 ", "Q2 ", "Q3 ", "QC "))
    assert values == {"Q1": "0.000000000000000", "Q2": "0.000000000000000",
                      "Q3": "0.000000000000000", "QC": "1.000000000000000"}


# -- bad input ------------------------------------------------------------------------

@pytest.mark.parametrize("overrides, message", [
    ({"epoch": datetime(2024, 3, 1, 12, 0)}, "timezone-aware"),
    ({"quaternion_xyzw": [0, 0, 0, 2]}, "unit norm"),
    ({"quaternion_xyzw": [0, 0, 1]}, "four finite"),
    ({"quaternion_xyzw": [0, 0, float("nan"), 1]}, "four finite"),
    ({"object_name": "   "}, "non-empty"),
])
def test_apm_rejects_bad_input(overrides, message):
    with pytest.raises(KvnError, match=message):
        _apm(np.eye(3), **overrides)


def test_aem_rejects_bad_epochs():
    base = dict(originator="TUB", object_name="A", object_id="B", creation_date=CREATED)
    with pytest.raises(KvnError, match="strictly increasing"):
        aem_kvn(epochs=[EPOCH, EPOCH], quaternions_xyzw=[[0, 0, 0, 1]] * 2, **base)
    with pytest.raises(KvnError, match="2 epochs but 1"):
        aem_kvn(epochs=[EPOCH, EPOCH + timedelta(seconds=1)], quaternions_xyzw=[[0, 0, 0, 1]], **base)
    with pytest.raises(KvnError, match="at least one"):
        aem_kvn(epochs=[], quaternions_xyzw=[], **base)


# -- the reader, on the standard's examples and on broken texts ------------------------

FIGURE_G1 = """CCSDS_APM_VERS = 2.0
CREATION_DATE = 2003-09-30T19:23:57
ORIGINATOR    = GSFC
MESSAGE_ID    = A701521

COMMENT GEOCENTRIC, CARTESIAN, EARTH FIXED
OBJECT_NAME = TRMM
OBJECT_ID   = 1997-074A
CENTER_NAME = EARTH
TIME_SYSTEM = UTC

COMMENT Current attitude for orbit 335
EPOCH = 2003-09-30T14:28:15.1172

QUAT_START
REF_FRAME_A = SC_BODY_1
REF_FRAME_B = ITRF1997
Q1 = 0.00005
Q2 = 0.87543
Q3 = 0.40949
QC = 0.25678
QUAT_STOP
"""


def test_reader_reads_the_standards_apm_example():
    doc = parse_kvn(FIGURE_G1)
    assert doc["metadata"]["COMMENT"] == ["GEOCENTRIC, CARTESIAN, EARTH FIXED"]
    assert doc["metadata"]["OBJECT_NAME"] == "TRMM"
    assert doc["data"]["COMMENT"] == ["Current attitude for orbit 335"]
    block = doc["data"]["blocks"][0]
    assert _file_quaternion(block).tolist() == [0.00005, 0.87543, 0.40949, 0.25678]
    assert parse_epoch(doc["data"]["EPOCH"]) == datetime(2003, 9, 30, 14, 28, 15, 117200, tzinfo=timezone.utc)


def test_reader_accepts_day_of_year_epochs_and_units():
    assert parse_epoch("2008-071T17:09:49") == datetime(2008, 3, 11, 17, 9, 49, tzinfo=timezone.utc)
    text = FIGURE_G1.replace("QUAT_START", "EULER_START\nREF_FRAME_A = A\nREF_FRAME_B = B\n"
                             "EULER_ROT_SEQ = YXY\nANGLE_1 = -26.78 [deg]\nANGLE_2 = 46.26 [deg]\n"
                             "ANGLE_3 = 144.10 [deg]\nEULER_STOP\nQUAT_START")
    blocks = parse_kvn(text)["data"]["blocks"]
    assert [b["block"] for b in blocks] == ["EULER", "QUAT"]
    assert blocks[0]["ANGLE_1"] == -26.78


@pytest.mark.parametrize("mutate, message", [
    (lambda t: t.replace("QUAT_STOP\n", ""), "without QUAT_STOP"),
    (lambda t: t.replace("ORIGINATOR    = GSFC\n", ""), "ORIGINATOR"),
    (lambda t: t.replace("OBJECT_ID   = 1997-074A\n", "").replace("CENTER_NAME = EARTH",
                                                                  "CENTER_NAME = EARTH\nOBJECT_ID = X"),
     "out of order"),
    (lambda t: t.replace("Q2 = 0.87543", "q2 = 0.87543"), "upper case"),
    (lambda t: t.replace("Q2 = 0.87543", "Q2 = 0,87543"), "not a number"),
    (lambda t: t.replace("Q3 = 0.40949", "COMMENT late\nQ3 = 0.40949"), "comments only at its start"),
    (lambda t: t.replace("CCSDS_APM_VERS", "CCSDS_OPM_VERS"), "first line"),
    (lambda t: t.replace("Q1 = 0.00005\nQ2 = 0.87543", "Q2 = 0.87543\nQ1 = 0.00005"), "not in the order"),
    (lambda t: t + "COMMENT " + "y" * 260 + "\n", "longer than 254"),
])
def test_reader_rejects_broken_apms(mutate, message):
    with pytest.raises(KvnError, match=message):
        parse_kvn(mutate(FIGURE_G1))


def test_reader_rejects_broken_aems():
    good = aem_kvn(epochs=[EPOCH, EPOCH + timedelta(seconds=1)], quaternions_xyzw=[[0, 0, 0, 1]] * 2,
                   originator="TUB", object_name="A", object_id="B", creation_date=CREATED)
    assert len(parse_kvn(good)["segments"][0]["data"]["lines"]) == 2
    with pytest.raises(KvnError, match="4 expected"):
        parse_kvn(good.replace(" 1.000000000000000\n", "\n", 1))
    with pytest.raises(KvnError, match="DATA_STOP"):
        parse_kvn(good.replace("DATA_STOP\n", ""))
    with pytest.raises(KvnError, match="META_START"):
        parse_kvn(good.replace("META_START\n", ""))
    with pytest.raises(KvnError, match="not a CCSDS epoch"):
        parse_kvn(good.replace("2024-03-01T12:00:01.250000 ", "2024/03/01 "))
