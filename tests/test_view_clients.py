"""One 3D view per console session: which viser client draws which session, bounded, released when the client
or the session ends; the address that names the session; and the viewer admitting real connections by it
(viser's server replaced by stand-ins that record what each client was shown)."""

from __future__ import annotations

from types import SimpleNamespace
from unittest.mock import MagicMock
from urllib.parse import parse_qs, urlsplit

import numpy as np
import pytest

from app.workflow.view_state import (ViewerClients, ViewStateStore, address_for_session, session_in_address)


def test_clients_are_bounded_and_a_freed_place_admits_the_next():
    clients = ViewerClients(limit=2)
    assert clients.attach(1, "tab-a") and clients.attach(2, "tab-b")
    assert not clients.attach(3, "tab-c")  # past the bound
    assert len(clients) == 2 and clients.clients_of("tab-c") == []
    assert clients.attach(2, "tab-b")  # the same client asking again takes no second place
    assert len(clients) == 2
    assert clients.detach(1) and not clients.detach(1) and not clients.detach(3)  # 3 was never admitted
    assert clients.attach(3, "tab-c") and clients.session_of(3) == "tab-c"
    with pytest.raises(KeyError):
        clients.session_of(1)


def test_a_session_ending_releases_only_its_own_clients():
    clients = ViewerClients(limit=5)
    for client, session in [(1, "tab-a"), (2, "tab-b"), (3, "tab-a"), (4, None)]:
        assert clients.attach(client, session)
    assert clients.clients_of("tab-a") == [1, 3] and clients.clients_of(None) == [4]
    assert clients.end_session("tab-a") == [1, 3]
    assert clients.end_session("tab-a") == [] and len(clients) == 2
    assert clients.session_of(2) == "tab-b" and clients.session_of(4) is None


def test_malformed_sessions_and_bounds_are_refused():
    clients = ViewerClients(limit=1)
    for bad in ("", "a/b", "x" * 65, "tab a"):
        with pytest.raises(ValueError, match="session id"):
            clients.attach(1, bad)
    assert len(clients) == 0
    with pytest.raises(ValueError):
        ViewerClients(limit=0)


def test_the_address_carries_the_session_to_the_websocket():
    """viser's page connects to its ``websocket`` parameter: the session must come back out of the path the
    websocket handshake carries, read here as a browser would split the page's address."""
    base = "http://127.0.0.1:8123/"
    url = address_for_session(base, "3f2c-Tab_9")
    page = urlsplit(url)
    assert (page.scheme, page.netloc, page.path) == ("http", "127.0.0.1:8123", "/")
    (socket,) = parse_qs(page.query)["websocket"]
    assert socket == "ws://127.0.0.1:8123/?session=3f2c-Tab_9"
    handshake = urlsplit(socket)
    assert session_in_address(handshake.path + "?" + handshake.query) == "3f2c-Tab_9"
    assert address_for_session(base, None) == base and session_in_address("/") is None
    with pytest.raises(ValueError, match="session id"):
        session_in_address("/?session=..%2Fetc")
    with pytest.raises(ValueError, match="2 sessions"):
        session_in_address("/?session=a&session=b")
    with pytest.raises(ValueError):
        address_for_session(base, "a b")


def test_a_forgotten_session_is_announced_once_and_the_bare_addresss_session_is_kept():
    store = ViewStateStore(max_sessions=2)
    ended = []
    store.on_forget(ended.append)
    store.follow("s0")
    for k in range(4):
        store.update(session=f"s{k}", sequence=k + 1)
    assert ended == ["s1", "s2"] and store.get("s0").sequence == 1 and store.sessions() == 2


# --- the viewer's admission, with viser's server replaced by recording stand-ins -----------------------------

class FakeServer:
    """What :class:`app.viewer.server.Viewer` uses of a viser server: callbacks, a shared scene and GUI, and the
    handshake path of each live connection."""

    def __init__(self) -> None:
        self.scene, self.gui = MagicMock(), MagicMock()
        self.connect, self.disconnect = [], []
        self._websock_server = SimpleNamespace(_live_connections={})

    def on_client_connect(self, callback):
        self.connect.append(callback)

    def on_client_disconnect(self, callback):
        self.disconnect.append(callback)

    def open(self, client_id: int, path: str):
        """A browser connecting at ``path``: its client handle, whose GUI records the Markdown it was shown."""
        self._websock_server._live_connections[client_id] = SimpleNamespace(request=SimpleNamespace(path=path))
        client = SimpleNamespace(client_id=client_id, gui=MagicMock(), scene=MagicMock(), camera=MagicMock())
        for callback in self.connect:
            callback(client)
        return client

    def close(self, client) -> None:
        self._websock_server._live_connections.pop(client.client_id)
        for callback in self.disconnect:
            callback(client)

    def get_port(self) -> int:
        return 8123

    def stop(self) -> None:
        pass


def shown(client) -> list[str]:
    """The Markdown texts a client's GUI was given, in order."""
    return [call.args[0] for call in client.gui.add_markdown.call_args_list]


@pytest.fixture
def viewer():
    from app.viewer.server import SkyModel, Viewer

    sky = SkyModel(vectors=np.eye(3), mag=np.array([1.0, 3.0, 6.5]), hip=np.array([1, 2, 3]), anchors=[])
    ctx = SimpleNamespace(view=ViewStateStore(max_sessions=3), storage=None)
    server = FakeServer()
    running = Viewer(ctx, server, sky, max_views=2)
    yield running, server, ctx
    running.stop()


def test_the_viewer_admits_each_address_to_its_own_session_and_refuses_past_the_bound(viewer):
    from app.viewer.server import refusal_text

    running, server, ctx = viewer
    a = server.open(0, "/?session=tab-a")
    bare = server.open(1, "/")
    assert running.clients.session_of(0) == "tab-a" and running.clients.session_of(1) is None
    described = running.describe("tab-a")
    assert (described.views, described.max_views, described.session) == (2, 2, "tab-a")
    assert described.url == "http://127.0.0.1:8123/?websocket=ws%3A%2F%2F127.0.0.1%3A8123%2F%3Fsession%3Dtab-a"
    assert shown(a)[0] == shown(bare)[0] == "No sequence selected yet: open one in the console."  # its own panel
    third = server.open(2, "/?session=tab-c")
    assert shown(third) == [refusal_text(2)] and "at most 2 3D views" in refusal_text(2)
    bad = server.open(3, "/?session=..")
    assert "not one a console opens" in shown(bad)[0] and len(running.clients) == 2
    server.close(bare)  # a tab closed: its place is free again
    again = server.open(4, "/?session=tab-c")
    assert running.clients.session_of(4) == "tab-c" and len(running.clients) == 2
    assert shown(again)[0].startswith("No sequence selected")
    assert a.gui.add_button.call_count == 3 and third.gui.add_button.call_count == 0  # Prev, Next, Confirm


def test_a_view_whose_session_ends_is_released_and_says_so(viewer):
    from app.viewer.server import SESSION_ENDED_TEXT

    running, server, ctx = viewer
    ctx.view.update(session="tab-a", sequence=1)
    a = server.open(0, "/?session=tab-a")
    b = server.open(1, "/?session=tab-b")
    for k in range(3):  # three newer sessions push tab-a out of a store of three (tab-b is written later)
        ctx.view.update(session=f"other-{k}", sequence=2)
    assert running.clients.clients_of("tab-a") == [] and running.clients.session_of(1) == "tab-b"
    assert shown(a)[-1] == SESSION_ENDED_TEXT and SESSION_ENDED_TEXT not in shown(b)
    assert server.open(2, "/?session=tab-c") is not None and running.clients.session_of(2) == "tab-c"
