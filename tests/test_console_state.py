"""Issue 13 below the API: console sessions in the view-state store, and schema migration 4 (verdicts) on
an archive written by the previous schema."""

from __future__ import annotations

import sqlite3
from datetime import datetime, timezone

import pytest

from app.storage import MIGRATIONS, Storage, VerdictExists
from app.workflow.view_state import DEFAULT_SESSION, ViewStateStore


def test_sessions_keep_their_own_state_and_the_3d_view_follows_one():
    store = ViewStateStore()
    store.update(session="tab-a", sequence=3, rank=2, updated_by="console")
    store.update(session="tab-b", sequence=7, updated_by="console")
    store.update(session="tab-b", mag=4.5, updated_by="console")
    a, b = store.get("tab-a"), store.get("tab-b")
    assert (a.sequence, a.rank, a.revision, a.session) == (3, 2, 1, "tab-a")
    assert (b.sequence, b.mag, b.revision) == (7, 4.5, 2)
    assert store.get("never-written").sequence is None and store.sessions() == 2  # reading stores nothing
    # No session named: the one the 3D view draws, the default one until a console asks for it.
    assert store.followed == DEFAULT_SESSION and store.get().sequence is None
    store.follow("tab-b")
    assert store.get().sequence == 7
    store.update(rank=3, updated_by="viewer")  # the 3D view's Next writes to the console it follows
    assert store.get("tab-b").rank == 3 and store.get("tab-a").rank == 2
    for bad in ("", "a/b", "x" * 65, None, 5):
        with pytest.raises(ValueError):
            store.follow(bad)
    with pytest.raises(ValueError):
        store.update(session="../x", rank=1)


def test_a_session_carries_its_operators_name_for_the_3d_view():
    """The console names its operator in its session; the 3D view drawing that session confirms under it.
    A blank name clears it; a name an operator field refuses is refused here too; the rest stays put."""
    store = ViewStateStore()
    store.update(session="tab-a", sequence=3, rank=2, updated_by="console")
    store.update(session="tab-a", operator="  Vera Rubin ", updated_by="console")
    state = store.get("tab-a")
    assert (state.operator, state.sequence, state.rank) == ("Vera Rubin", 3, 2)
    store.follow("tab-a")
    assert store.get().operator == "Vera Rubin" and store.get("tab-b").operator is None
    with pytest.raises(ValueError, match="U\\+001B"):
        store.update(session="tab-a", operator="eve\x1b[2J", updated_by="console")
    assert store.get("tab-a").operator == "Vera Rubin"
    store.update(session="tab-a", operator=" ", updated_by="console")
    assert store.get("tab-a").operator is None


def test_the_3d_views_operator_field_follows_the_console_until_someone_types_another():
    from types import SimpleNamespace

    from app.viewer.server import Panel as Viewer  # each 3D view's panel

    panel = SimpleNamespace(_operator=SimpleNamespace(value=""), _operator_from_console="")
    Viewer._follow_operator(panel, "Vera")
    assert panel._operator.value == "Vera"
    Viewer._follow_operator(panel, "Annie")  # the console's name changed: the field follows
    assert panel._operator.value == "Annie"
    panel._operator.value = "Henrietta"  # typed in the 3D view itself: kept
    Viewer._follow_operator(panel, "Vera")
    assert panel._operator.value == "Henrietta"
    Viewer._follow_operator(panel, None)
    assert panel._operator.value == "Henrietta"


def test_old_sessions_are_forgotten_but_never_the_3d_views():
    store = ViewStateStore(max_sessions=3)
    store.update(session="s0", sequence=1)
    store.follow("s0")
    for k in range(1, 6):
        store.update(session=f"s{k}", sequence=k + 1)
    assert store.sessions() == 3
    assert store.get("s0").sequence == 1  # the 3D view's session survives
    assert store.get("s5").sequence == 6 and store.get("s1").sequence is None


def _version_3_archive(path) -> None:
    """An archive as schema version 3 left it, with a searched and confirmed sequence."""
    conn = sqlite3.connect(path)
    conn.execute("PRAGMA foreign_keys=ON")
    conn.execute("CREATE TABLE schema_version (version INTEGER PRIMARY KEY, applied_at TEXT NOT NULL)")
    for version, statements in enumerate(MIGRATIONS[:3], start=1):
        for statement in statements:
            conn.execute(statement)
        conn.execute("INSERT INTO schema_version VALUES (?, '2026-01-01T00:00:00.000000+00:00')", (version,))
    conn.execute("INSERT INTO sequences (id, content_sha256, sequence_id, spacecraft, raw_text, uploaded_at, status, "
                 "camera_calibration) VALUES (1, 'abc', 'A-1', 'SAT', 'raw', '2026-01-01T00:00:00.000000+00:00', "
                 "'confirmed', NULL)")
    conn.execute("INSERT INTO searches (id, seq_id, pattern_version, method, options_json, result_json, status, "
                 "created_at) VALUES (1, 1, 1, 'bright_pair', '{}', '{}', 'identified', 't')")
    conn.execute("INSERT INTO confirmations (id, seq_id, search_id, rank, operator, confirmed_at, quaternion_json, "
                 "rotation_matrix_json, ra_deg, dec_deg, roll_deg, pattern_json, candidate_json, apm_text) VALUES "
                 "(1, 1, 1, 1, 'ann', '2026-01-01T00:00:00.000000+00:00', '[0,0,0,1]', '[[1,0,0],[0,1,0],[0,0,1]]', "
                 "1, 2, 3, '{}', '{}', 'APM')")
    conn.commit()
    conn.close()


def test_migration_4_keeps_the_archive_and_its_guards(tmp_path):
    path = tmp_path / "v3.sqlite3"
    _version_3_archive(path)
    with Storage.open(path) as store:
        assert store.health()["schema_version"] == len(MIGRATIONS)
        row = store.get_sequence(1)
        assert (row.sequence_id, row.status, row.raw_text) == ("A-1", "confirmed", "raw")
        before = store.current_confirmation(1)
        assert before.id == 1 and before.is_current and before.override_reason is None
        # The new verdict: withdraws the confirmation, and the status CHECK accepts it.
        with pytest.raises(VerdictExists):
            store.add_rejection(1, operator="bob", reason="ghosts")
        rejection = store.add_rejection(1, operator="bob", reason="ghosts", supersede=True,
                                        rejected_at=datetime(2026, 2, 1, tzinfo=timezone.utc))
        assert rejection.replaces_confirmation == 1 and rejection.is_current
        assert store.get_sequence(1).status == "rejected" and store.current_confirmation(1) is None
        assert store.get_confirmation(1).withdrawn_by == rejection.id
    raw = sqlite3.connect(path)
    raw.execute("PRAGMA foreign_keys=ON")
    for sql in ("UPDATE sequences SET raw_text = 'changed'", "DELETE FROM sequences",
                "UPDATE rejections SET reason = 'x'", "DELETE FROM rejections",
                "UPDATE confirmations SET operator = 'x'",
                "INSERT INTO searches (seq_id, method, options_json, result_json, status, created_at) "
                "VALUES (99, 'm', '{}', '{}', 's', 't')",
                "UPDATE sequences SET status = 'done'"):
        with pytest.raises(sqlite3.DatabaseError):
            raw.execute(sql)
    names = {r[0] for r in raw.execute("SELECT name FROM sqlite_master WHERE type IN ('index', 'trigger')")}
    assert {"sequences_spacecraft", "sequences_status", "sequences_keep_content", "sequences_no_delete",
            "confirmations_only_supersede", "rejections_no_update", "rejections_no_delete"} <= names
    assert raw.execute("PRAGMA foreign_key_check").fetchall() == []
    raw.close()
