"""The studio's open tabs: one `ClientView` each (its camera and its render thread), the
input views they stood at, and the renders shown so far."""

from __future__ import annotations

import time
from typing import Any

import viser

from pipeline.studio.view import ClientView, Host


class Tabs:
    """Every tab of the page, by viser client id."""

    def __init__(self, host: Host):
        self.host = host
        self.clients: dict[int, ClientView] = {}
        self.views_seen: set[int] = set()  # input views a tab stood at (saved with the spec)
        self.renders = 0  # renders shown so far (the page numbers them)

    def connect(self, client: viser.ClientHandle) -> None:
        self.clients[client.client_id] = ClientView(self.host, client)

    def disconnect(self, client: viser.ClientHandle) -> None:
        cv = self.clients.pop(client.client_id, None)
        if cv is not None:
            cv.alive = False

    def of(self, ev: Any) -> list[ClientView]:
        """The tab an event came from, or every tab when it came from none."""
        if ev.client is None:
            return list(self.clients.values())
        cv = self.clients.get(ev.client.client_id)
        return [] if cv is None else [cv]

    def redraw(self) -> None:
        """Every tab renders again: a preview first, then the full view."""
        for cv in list(self.clients.values()):
            cv.moved = time.perf_counter()
