"""The peer benchmark's parts that need no network: conventions at the boundary and the runner protocol.

The real peer (cedar-solve in its own virtual environment) is not used
here; tetra3's pinhole model and its attitude read-back are written out
below from its documented conventions, and fake peers (tiny scripts, and a
fake ``tetra3`` module under the real runner) stand in for the process.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import textwrap
from types import SimpleNamespace

import numpy as np
import pytest

from app.attitude import rotation_from_radec_roll
from app.bench import peer
from app.camera import CAMERAS
from app.simulate import random_rotation

CAMERA = CAMERAS["tubsat-752x582-20deg"]


# --- tetra3's conventions, written out independently ---------------------------------

def tetra3_rays(centroids_yx: np.ndarray, size: tuple[int, int], fov_rad: float) -> np.ndarray:
    """tetra3's pinhole: (y, x) from the top-left corner -> unit vectors (boresight, left, up).

    The optical centre is (height/2, width/2); ``fov_rad`` is the horizontal
    field of view, so one pixel is tan(fov/2) / (width/2) at the centre.
    """
    height, width = size
    scale = math.tan(fov_rad / 2) / (width / 2)
    y, x = centroids_yx[:, 0], centroids_yx[:, 1]
    v = np.column_stack([np.ones(len(y)), (width / 2 - x) * scale, (height / 2 - y) * scale])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def tetra3_angles(R_t3: np.ndarray) -> tuple[float, float, float]:
    """tetra3's read-back of (RA, Dec, Roll) in degrees from its ICRS -> camera matrix."""
    ra = math.degrees(math.atan2(R_t3[0, 1], R_t3[0, 0])) % 360
    dec = math.degrees(math.atan2(R_t3[0, 2], np.linalg.norm(R_t3[1:3, 2])))
    roll = math.degrees(math.atan2(R_t3[1, 2], R_t3[2, 2])) % 360
    return ra, dec, roll


#: Rows: our camera axes in tetra3's (+column = -left, +row = -up, boresight), so v_ours = M v_tetra3.
OURS_IN_TETRA3 = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], dtype=float)


# --- centroids -------------------------------------------------------------------------------

def test_pixel_centres_move_by_half_a_pixel_and_swap_to_row_column():
    xy = np.array([[0.0, 0.0], [751.0, 581.0], [375.5, 290.5], [10.0, 20.0]])
    got = peer.to_tetra3_centroids(xy, [4, 3, 2, 1], CAMERA)
    # (0, 0), the centre of our top-left pixel, is (0.5, 0.5) from tetra3's top-left corner,
    # the bottom-right pixel's centre is (581.5, 751.5), our principal point tetra3's (h/2, w/2).
    np.testing.assert_allclose(got, [[0.5, 0.5], [581.5, 751.5], [291.0, 376.0], [20.5, 10.5]], atol=1e-12)
    assert peer.tetra3_size(CAMERA) == (582, 752)


def test_centroids_are_sorted_brightest_first_keeping_ties_in_file_order():
    xy = np.array([[1.0, 1.0], [2.0, 2.0], [3.0, 3.0], [4.0, 4.0]])
    got = peer.to_tetra3_centroids(xy, [10.0, 255.0, 40.0, 255.0], CAMERA)
    np.testing.assert_allclose(got[:, 1], [2.5, 4.5, 3.5, 1.5])


@pytest.mark.parametrize("camera", [CAMERA, CAMERA.with_optics(cx=380.25, cy=285.0), CAMERAS["liebe-576x604-30deg"]])
def test_tetra3_sees_the_same_rays_as_our_camera(camera):
    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(-0.5, camera.width - 0.5, 40), rng.uniform(-0.5, camera.height - 0.5, 40)])
    brightness = rng.uniform(1, 255, 40)
    order = np.argsort(-brightness, kind="stable")
    ours = camera.pixels_to_vectors(xy[order]) @ OURS_IN_TETRA3  # rows: our rays in tetra3's axes
    theirs = tetra3_rays(peer.to_tetra3_centroids(xy, brightness, camera), peer.tetra3_size(camera),
                         math.radians(camera.fov_deg[0]))
    # 1e-3 px: a half-pixel slip would be 5e2 times larger
    assert np.max(np.linalg.norm(ours - theirs, axis=1)) * camera.focal_length_px < 1e-3


def test_request_carries_fov_estimate_and_error_in_degrees():
    snapshot = SimpleNamespace(xy=np.array([[0.0, 0.0], [5.0, 6.0]]), brightness=np.array([1.0, 2.0]))
    req = peer.peer_request(snapshot, CAMERA, 0.05, solve_timeout_ms=123)
    assert req["size"] == [582, 752]
    assert req["fov_estimate"] == pytest.approx(20.0, abs=1e-3)
    assert req["fov_max_error"] == pytest.approx(1.0, abs=1e-4)
    assert req["centroids"] == [[6.5, 5.5], [0.5, 0.5]]
    assert req["solve_timeout_ms"] == 123
    json.dumps(req)  # what goes down the pipe


# --- attitudes --------------------------------------------------------------------------------

def test_tetra3_angles_read_back_from_the_rotation_they_build():
    rng = np.random.default_rng(5)
    for _ in range(50):
        angles = (rng.uniform(0, 360), rng.uniform(-89, 89), rng.uniform(0, 360))
        R = peer.tetra3_rotation(*angles)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        got = tetra3_angles(R)
        assert got[0] == pytest.approx(angles[0], abs=1e-9)
        assert got[1] == pytest.approx(angles[1], abs=1e-9)
        assert (got[2] - angles[2] + 180) % 360 - 180 == pytest.approx(0, abs=1e-9)


def test_our_attitude_survives_the_round_trip_through_tetra3s_angles():
    rng = np.random.default_rng(7)
    for _ in range(50):
        R_ours = random_rotation(rng)
        R_t3 = OURS_IN_TETRA3.T @ R_ours  # rows: tetra3's axes in ICRS
        np.testing.assert_allclose(peer.rotation_from_tetra3(*tetra3_angles(R_t3)), R_ours, atol=1e-9)


def test_tetra3_roll_is_our_roll_with_the_sign_flipped():
    # tetra3: positive roll turns north counter-clockwise from image up; ours is the position angle of up.
    for ra, dec, roll in [(10.0, 20.0, 0.0), (200.0, -45.0, 30.0), (83.0, 5.0, 271.0)]:
        np.testing.assert_allclose(peer.rotation_from_tetra3(ra, dec, roll), rotation_from_radec_roll(ra, dec, -roll),
                                   atol=1e-12)


def test_a_star_lands_where_both_models_put_it():
    """A peer's attitude and centroid agree with ours about where a sky direction is imaged."""
    rng = np.random.default_rng(11)
    R_ours = random_rotation(rng)
    xy = np.array([[100.0, 50.0], [600.0, 400.0], [375.5, 290.5]])
    sky = CAMERA.pixels_to_vectors(xy) @ R_ours  # ICRS directions of the three pixels
    R_peer = peer.tetra3_rotation(*tetra3_angles(OURS_IN_TETRA3.T @ R_ours))
    in_peer_camera = sky @ R_peer.T
    expected = tetra3_rays(peer.to_tetra3_centroids(xy, [3, 2, 1], CAMERA), (582, 752),
                           math.radians(CAMERA.fov_deg[0]))
    np.testing.assert_allclose(in_peer_camera, expected, atol=1e-9)


# --- the runner protocol with fake peers ---------------------------------------------------------

FAKE_ECHO = textwrap.dedent("""
    import json, sys
    ra, dec, roll = (float(a) for a in sys.argv[1:4])
    print(json.dumps({"ready": True, "import_s": 0.0, "load_s": 0.0}), flush=True)
    for line in sys.stdin:
        req = json.loads(line)
        if req.get("cmd") == "quit":
            sys.exit(0)
        print(json.dumps({"id": req["id"], "status": "MATCH_FOUND", "ra_deg": ra, "dec_deg": dec,
                          "roll_deg": roll, "solve_ms": 1.5, "n": len(req["centroids"]),
                          "size": req["size"]}), flush=True)
    sys.exit(0)
""")


def _script(tmp_path, name: str, text: str) -> list[str]:
    path = tmp_path / name
    path.write_text(text)
    return [sys.executable, "-I", str(path)]


def test_fake_peer_answers_each_request_in_order_and_quits_cleanly(tmp_path):
    argv = _script(tmp_path, "echo.py", FAKE_ECHO) + ["10", "20", "30"]
    with peer.PeerProcess(argv, ready_timeout=30, answer_timeout=30) as p:
        assert p.ready["ready"] is True
        answers = [p.solve({"centroids": [[1.0, 2.0]] * k, "size": [582, 752]}) for k in (1, 2, 3)]
        proc = p.proc
    assert [a["n"] for a in answers] == [1, 2, 3]
    assert [a["id"] for a in answers] == [1, 2, 3]
    assert proc.returncode == 0  # it quit on request, was not killed


def test_peer_answer_is_judged_against_the_truth(tmp_path):
    argv = _script(tmp_path, "echo.py", FAKE_ECHO) + ["10", "20", "30"]
    R_claimed = peer.rotation_from_tetra3(10, 20, 30)
    snapshot = SimpleNamespace(xy=np.array([[1.0, 2.0]] * 4), brightness=np.ones(4))
    p = peer.RestartingPeer(argv, ready_timeout=30, answer_timeout=30)
    try:
        right = peer._theirs(p, snapshot, CAMERA, R_claimed, peer.FOV_MAX_ERROR)
        wrong = peer._theirs(p, snapshot, CAMERA, rotation_from_radec_roll(10, 20.5, -30), peer.FOV_MAX_ERROR)
    finally:
        p.close()
    assert right.claimed and right.correct and right.ms == 1.5
    assert wrong.claimed and not wrong.correct


def test_a_peer_that_never_answers_is_timed_out_and_killed(tmp_path):
    silent = 'import json, sys\nprint(json.dumps({"ready": True}), flush=True)\nsys.stdin.readline()\nsys.stdin.read()\n'
    p = peer.PeerProcess(_script(tmp_path, "silent.py", silent), ready_timeout=30, answer_timeout=0.5)
    p.start()
    with pytest.raises(peer.PeerTimeout, match="within 0.5 s"):
        p.solve({"centroids": [], "size": [1, 1]})
    assert p.proc.poll() is not None  # killed, not left behind
    p.close()


def test_a_peer_that_dies_before_it_is_ready_says_why(tmp_path):
    dying = 'import sys\nsys.stderr.write("no module named tetra3\\n")\nsys.exit(1)\n'
    p = peer.PeerProcess(_script(tmp_path, "dying.py", dying), ready_timeout=30)
    with pytest.raises(peer.PeerError, match="no module named tetra3"):
        p.start()
    assert p.proc.poll() == 1


@pytest.mark.parametrize("reply, message", [
    ('"not an object"', "not an object"),
    ("this is not json", "not a JSON line"),
    ('{"id": 99, "status": "MATCH_FOUND"}', "expected 1"),
])
def test_a_peer_that_breaks_the_protocol_is_an_error(tmp_path, reply, message):
    text = ('import json, sys\nprint(json.dumps({"ready": True}), flush=True)\nsys.stdin.readline()\n'
            f'print({reply!r}, flush=True)\nsys.stdin.read()\n')
    p = peer.PeerProcess(_script(tmp_path, "bad.py", text), ready_timeout=30, answer_timeout=30)
    p.start()
    with pytest.raises(peer.PeerError, match=message):
        p.solve({"centroids": [], "size": [1, 1]})
    p.close()
    assert p.proc.poll() is not None


def test_a_peer_that_hangs_once_is_restarted(tmp_path):
    # The first process to start hangs on its first request; the ones after it answer.
    flag = tmp_path / "started-once"
    text = textwrap.dedent(f"""
        import json, pathlib, sys
        flag = pathlib.Path({str(flag)!r})
        first = not flag.exists()
        flag.write_text("x")
        print(json.dumps({{"ready": True}}), flush=True)
        for line in sys.stdin:
            req = json.loads(line)
            if req.get("cmd") == "quit":
                break
            if first:
                sys.stdin.read()
            print(json.dumps({{"id": req["id"], "status": "NO_MATCH", "solve_ms": 2.0}}), flush=True)
    """)
    p = peer.RestartingPeer(_script(tmp_path, "flaky.py", text), ready_timeout=30, answer_timeout=0.5)
    try:
        first = p.solve({"centroids": [], "size": [1, 1]})
        second = p.solve({"centroids": [], "size": [1, 1]})
    finally:
        p.close()
    assert first["status"] == "TIMEOUT_KILLED"
    assert second == {"id": 1, "status": "NO_MATCH", "solve_ms": 2.0}
    assert p.restarts == 1


def test_restarts_are_bounded(tmp_path):
    silent = 'import json, sys\nprint(json.dumps({"ready": True}), flush=True)\nsys.stdin.read()\n'
    p = peer.RestartingPeer(_script(tmp_path, "silent.py", silent), max_restarts=1, ready_timeout=30,
                            answer_timeout=0.3)
    try:
        assert p.solve({"centroids": [], "size": [1, 1]})["status"] == "TIMEOUT_KILLED"
        with pytest.raises(peer.PeerError, match="failed 2 times"):
            p.solve({"centroids": [], "size": [1, 1]})
    finally:
        p.close()


# --- the real runner over a fake tetra3 --------------------------------------------------------------

FAKE_TETRA3 = textwrap.dedent("""
    MATCH_FOUND = 1

    class Tetra3:
        def __init__(self):
            self.calls = 0

        def solve_from_centroids(self, centroids, size, fov_estimate=None, fov_max_error=None, solve_timeout=None):
            if len(centroids) == 0:
                raise ValueError("no centroids")
            self.calls += 1
            return {"RA": float(centroids[0][1]), "Dec": float(centroids[0][0]), "Roll": float(size[1]),
                    "FOV": (fov_estimate or 0) + (fov_max_error or 0), "Matches": len(centroids), "Prob": float("nan"),
                    "T_solve": float(solve_timeout), "status": 1 if self.calls == 1 else 2}
""")


def _runner_argv(tmp_path, tetra3_source: str) -> list[str]:
    (tmp_path / "tetra3").mkdir()
    (tmp_path / "tetra3" / "__init__.py").write_text(tetra3_source)
    boot = (f"import runpy, sys; sys.path.insert(0, {str(tmp_path)!r}); "
            f"runpy.run_path({str(peer.RUNNER)!r}, run_name='__main__')")
    return [sys.executable, "-I", "-c", boot]


def test_runner_translates_tetra3s_answers_and_survives_a_bad_request(tmp_path):
    with peer.PeerProcess(_runner_argv(tmp_path, FAKE_TETRA3), ready_timeout=60, answer_timeout=60) as p:
        assert p.ready["ready"] is True and p.ready["load_s"] >= 0
        first = p.solve({"centroids": [[3.5, 7.5], [1.0, 1.0]], "size": [582, 752], "fov_estimate": 20.0,
                         "fov_max_error": 0.5, "solve_timeout_ms": 250})
        with pytest.raises(peer.PeerError, match="no centroids"):
            p.solve({"centroids": [], "size": [582, 752]})
        second = p.solve({"centroids": [[0.5, 0.5]], "size": [582, 752]})
        proc = p.proc
    assert first["status"] == "MATCH_FOUND"
    assert (first["ra_deg"], first["dec_deg"], first["roll_deg"]) == (7.5, 3.5, 752.0)
    assert first["fov_deg"] == 20.5 and first["matches"] == 2 and first["t_solve_ms"] == 250.0
    assert first["prob"] is None  # NaN is not JSON
    assert first["solve_ms"] >= 0 and first["cpu_ms"] >= 0
    assert second["status"] == "NO_MATCH" and second["t_solve_ms"] == 5000.0  # the runner's default time-out
    assert proc.returncode == 0


def test_runner_reports_a_tetra3_that_cannot_load(tmp_path):
    broken = "class Tetra3:\n    def __init__(self):\n        raise OSError('default_database.npz missing')\n"
    p = peer.PeerProcess(_runner_argv(tmp_path, broken), ready_timeout=60)
    with pytest.raises(peer.PeerError, match="default_database.npz missing"):
        p.start()
    assert p.proc.poll() == 1


# --- the environment and the skip -----------------------------------------------------------------------

def test_a_failed_setup_step_names_the_step_and_its_output(tmp_path):
    import io

    log = io.StringIO()
    with pytest.raises(peer.PeerUnavailable, match=r"pip install cedar-solve failed \(exit 3\): .*no route to PyPI"):
        peer._run_step([sys.executable, "-c", "print('ERROR: no route to PyPI'); raise SystemExit(3)"],
                       "pip install cedar-solve", 60, log)
    assert "no route to PyPI" in log.getvalue()


def test_an_environment_that_cannot_import_tetra3_is_not_used(tmp_path):
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "python").symlink_to(sys.executable)  # this interpreter has no tetra3
    assert peer._check_env(tmp_path) is None
    assert peer._check_env(tmp_path / "missing") is None


def test_someone_elses_folder_is_never_deleted(tmp_path):
    precious = tmp_path / "mine" / "notes.txt"
    precious.parent.mkdir()
    precious.write_text("keep me")
    with pytest.raises(peer.PeerUnavailable, match="left alone"):
        peer.ensure_peer_env(tmp_path / "mine", log=lambda message: None)
    assert precious.read_text() == "keep me"


def test_venv_location_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("STARID_PEER_VENV", str(tmp_path / "pv"))
    assert peer.peer_venv_dir() == tmp_path / "pv"
    monkeypatch.delenv("STARID_PEER_VENV")
    monkeypatch.setenv("STARID_CACHE_DIR", str(tmp_path / "cache"))
    assert peer.peer_venv_dir() == tmp_path / "cache" / "peer-venv"


def test_suite_without_its_environment_is_skipped_with_the_reason(monkeypatch, capsys):
    from app.cli import bench

    def unavailable(*args, **kwargs):
        raise peer.PeerUnavailable("pip install cedar-solve failed (exit 1): network unreachable")

    monkeypatch.setattr(peer, "ensure_peer_env", unavailable)
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    assert bench.run(parser.parse_args(["--suite", "peer", "--n", "3", "--json"])) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["peer"]["skipped"].endswith("network unreachable")
    assert peer.format_table(out["peer"]).startswith("skipped: cedar-solve environment unavailable")


def test_bench_cli_lists_the_peer_suite():
    done = subprocess.run([sys.executable, "-m", "app", "bench", "--help"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "peer" in done.stdout


# --- frames in which no star is seen ------------------------------------------------------------

@pytest.mark.parametrize("kind", ["noise", "earth"])
def test_a_no_star_frame_is_one_snapshot_of_sources_that_are_not_stars(kind):
    """Random points on the sensor, or the Earth's blobs (at least 3 sources, else both tools answer at once);
    and any claim on such a frame is wrong."""
    from app.identification import Sky, solve_sequence

    rng = np.random.default_rng(4)
    sky = Sky()
    for _ in range(3):
        sequence = peer._no_match_frame(rng, CAMERA, kind)
        (snapshot,) = sequence.snapshots
        assert snapshot.index == 0 and snapshot.n_sources >= 3
        assert CAMERA.on_sensor(snapshot.xy).all()
        if kind == "noise":
            assert snapshot.n_sources == 10
        ours = peer._ours(sky, sequence, None)
        assert not ours.claimed and not ours.correct
    assert peer._verdict(np.eye(3), None) == (False, None, None)


def test_a_middle_snapshot_is_one_snapshot_with_its_own_truth():
    """The few-star row's frame: the sequence's middle snapshot, renumbered 0, with the truth of that
    snapshot (its attitude, its sources' labels, its time), not the first one's."""
    from app.simulate import simulate_sequence

    sequence, truth = simulate_sequence(np.random.default_rng(9), CAMERA, "sparse")
    middle = len(sequence.snapshots) // 2
    one, one_truth = peer.middle_snapshot(sequence, truth)
    (snapshot,) = one.snapshots
    assert snapshot.index == 0 and snapshot.time == sequence.snapshots[middle].time
    np.testing.assert_array_equal(snapshot.xy, sequence.snapshots[middle].xy)
    assert one_truth["rotation_matrices"] == [truth["rotation_matrices"][middle]]
    assert one_truth["sources"] == [truth["sources"][middle]] and one_truth["times"] == [truth["times"][middle]]
    assert len(one_truth["sources"][0]) == snapshot.n_sources
