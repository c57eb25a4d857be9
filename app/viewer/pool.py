"""The pool of viser servers: one per inspection a browser looks at, idle ones stopped, a cap on
how many run and room kept for the operator.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

from app.viewer.meshes import load_plate_meshes
from app.viewer.scene import InspectionView

logger = logging.getLogger(__name__)


class ViewerBusyError(RuntimeError):
    """Every allowed viser server is in use by a browser; the message says what to do."""


class PlateViewer:
    """The viser servers of the inspections that browsers are looking at.

    Parameters
    ----------
    artifacts_dir : callable ``(inspection_id: int) -> Path``, the folder holding an
        inspection's result.json, surface.ply and target.ply.
    host : str, interface the viser servers bind to; loopback, since browsers reach
        them only through the app's websocket bridge.
    idle_s : float, an inspection's server is stopped this long after its last
        browser left, s.
    max_servers : int, most servers running at once. Opening one more stops the
        longest-idle server without a browser; when every server has a browser,
        :class:`ViewerBusyError` says so.
    max_vertices : int, display meshes are decimated to about this many vertices.
    max_sockets_per_client : int or None, most bridges one anonymous client address
        holds at once (None: no limit).
    reserved_servers : int, servers only the operator may start: an anonymous client
        starts one only while fewer than ``max_servers - reserved_servers`` have a browser.
    """

    def __init__(
        self,
        artifacts_dir: Callable[[int], Path],
        *,
        host: str = "127.0.0.1",
        idle_s: float = 300.0,
        max_servers: int = 8,
        max_vertices: int = 150_000,
        max_sockets_per_client: int | None = None,
        reserved_servers: int = 0,
    ):
        if idle_s < 0:
            raise ValueError(f"idle_s: expected >= 0, got {idle_s}")
        if max_servers < 1:
            raise ValueError(f"max_servers: expected >= 1, got {max_servers}")
        if max_sockets_per_client is not None and max_sockets_per_client < 1:
            raise ValueError(
                f"max_sockets_per_client: expected >= 1 or None, got {max_sockets_per_client}"
            )
        if reserved_servers < 0:
            raise ValueError(f"reserved_servers: expected >= 0, got {reserved_servers}")
        self._artifacts_dir = artifacts_dir
        self._host = host
        self._idle_s = idle_s
        self._max_servers = max_servers
        self._max_vertices = max_vertices
        self._max_sockets_per_client = max_sockets_per_client
        self._reserved_servers = min(reserved_servers, max_servers)
        self._client_bridges: dict[str, int] = {}
        self._lock = threading.Lock()
        self._load_lock = threading.Lock()
        self._views: dict[int, InspectionView] = {}
        self._bridges: dict[int, int] = {}
        self._idle_timers: dict[int, threading.Timer] = {}

    def has_view(self, inspection_id: int) -> bool:
        """True if the inspection has the artifacts the 3D view needs."""
        folder = Path(self._artifacts_dir(inspection_id))
        return (folder / "result.json").is_file() and (folder / "surface.ply").is_file()

    def running(self) -> list[int]:
        """Inspections whose viser server is running."""
        with self._lock:
            return sorted(self._views)

    def check_capacity(self, inspection_id: int, *, privileged: bool = True) -> None:
        """Raise :class:`ViewerBusyError` if opening this inspection's view would exceed the cap.

        ``privileged``: the operator (may use every server); otherwise an anonymous client, which
        may not start a server once ``max_servers - reserved_servers`` have a browser.
        """
        with self._lock:
            if inspection_id in self._views:
                return
            busy = sum(1 for i in self._views if self._bridges.get(i, 0) > 0)
            room = len(self._views) < self._max_servers or busy < len(
                self._views
            )  # an idle server can make room
            if room and (privileged or busy < self._max_servers - self._reserved_servers):
                return
        if room:
            raise ViewerBusyError(
                f"3D view: {busy} inspections are being viewed and {self._reserved_servers} views are kept for the "
                "operator's dashboard; log in (or close another 3D view) and reload this page"
            )
        raise ViewerBusyError(
            f"3D view: {self._max_servers} inspections are already being viewed (the most this cell runs at once); "
            "close the 3D view of another inspection and reload this page"
        )

    def check_client(self, client: str | None) -> None:
        """Raise :class:`ViewerBusyError` if the anonymous ``client`` holds its most bridges (None: exempt)."""
        with self._lock:
            self._check_client_locked(client)

    def _check_client_locked(self, client: str | None) -> None:
        limit = self._max_sockets_per_client
        if client is None or limit is None or self._client_bridges.get(client, 0) < limit:
            return
        raise ViewerBusyError(
            f"3D view: this computer already has {limit} 3D views open (the most without an operator session); "
            "close one and reload this page"
        )

    def port_for(self, inspection_id: int, *, privileged: bool = True) -> int:
        """The loopback port of the inspection's viser server, started (and meshes loaded) if needed.

        Blocks while loading (one load at a time); call it from a worker thread in async code.

        Raises
        ------
        FileNotFoundError
            If the inspection has no result or meshes.
        ViewerBusyError
            If ``max_servers`` servers run and each has a browser, or (not ``privileged``)
            the servers not reserved for the operator all have one.
        """
        with self._lock:
            view = self._views.get(inspection_id)
        if view is not None:
            return view.port
        with self._load_lock:
            with self._lock:
                view = self._views.get(inspection_id)
            if view is not None:
                return view.port
            self.check_capacity(inspection_id, privileged=privileged)
            self._make_room()
            meshes = load_plate_meshes(
                Path(self._artifacts_dir(inspection_id)), max_vertices=self._max_vertices
            )
            view = InspectionView(inspection_id, meshes, host=self._host)
            with self._lock:
                self._views[inspection_id] = view
            logger.info("viewer: inspection %s on %s:%s", inspection_id, self._host, view.port)
        return view.port

    def _make_room(self) -> None:
        """At the cap, stop the server that has been idle longest (caller holds the load lock)."""
        with self._lock:
            if len(self._views) < self._max_servers:
                return
            # Longest idle first: timers are kept in the order they were armed.
            idle = [
                i
                for i in [*self._idle_timers, *self._views]
                if i in self._views and self._bridges.get(i, 0) == 0
            ]
            if not idle:
                return
            oldest = idle[0]
            view = self._views.pop(oldest)
            timer = self._idle_timers.pop(oldest, None)
            if timer is not None:
                timer.cancel()
        view.stop()
        logger.info("viewer: inspection %s stopped to make room", oldest)

    def client_count(self, inspection_id: int) -> int:
        """Browsers whose scene is built (viser clients) for an inspection."""
        with self._lock:
            view = self._views.get(inspection_id)
        return 0 if view is None else view.client_count()

    def scene_node_names(self, inspection_id: int) -> dict[int, tuple[str, ...]]:
        """Per connected client id, the names of the plate's scene nodes present (for checks)."""
        with self._lock:
            view = self._views.get(inspection_id)
        if view is None:
            return {}
        return {cid: tuple(view.nodes_of(cid)) for cid in view.server.get_clients()}

    def bridge_opened(self, inspection_id: int, client: str | None = None) -> None:
        """Count a browser connection (cancels a pending idle stop).

        ``client``: the anonymous client's address, counted against ``max_sockets_per_client``
        (None for the operator); give the same to :meth:`bridge_closed`.

        Raises
        ------
        ViewerBusyError
            If ``client`` holds its most bridges already (nothing is counted then).
        """
        with self._lock:
            self._check_client_locked(client)
            if client is not None:
                self._client_bridges[client] = self._client_bridges.get(client, 0) + 1
            self._bridges[inspection_id] = self._bridges.get(inspection_id, 0) + 1
            timer = self._idle_timers.pop(inspection_id, None)
        if timer is not None:
            timer.cancel()

    def bridge_closed(self, inspection_id: int, client: str | None = None) -> None:
        """Uncount a browser connection; the last one out arms the idle stop."""
        with self._lock:
            if client is not None:
                left_of_client = self._client_bridges.get(client, 1) - 1
                if left_of_client > 0:
                    self._client_bridges[client] = left_of_client
                else:
                    self._client_bridges.pop(client, None)
            left = max(self._bridges.get(inspection_id, 1) - 1, 0)
            self._bridges[inspection_id] = left
            if left == 0 and inspection_id in self._views:
                self._arm_idle_locked(inspection_id)

    def _arm_idle_locked(self, inspection_id: int) -> None:
        """(Re)start the idle timer of a view; the caller holds ``self._lock``."""
        old = self._idle_timers.pop(inspection_id, None)
        if old is not None:
            old.cancel()
        timer = threading.Timer(self._idle_s, self._stop_if_idle, args=(inspection_id,))
        timer.daemon = True
        self._idle_timers[inspection_id] = timer
        timer.start()

    def _stop_if_idle(self, inspection_id: int) -> None:
        with self._lock:
            if self._idle_timers.get(inspection_id) is not threading.current_thread():
                return  # re-armed or cancelled meanwhile: a newer timer decides
            if self._bridges.get(inspection_id, 0) > 0:
                return
            view = self._views.pop(inspection_id, None)
            self._idle_timers.pop(inspection_id, None)
            self._bridges.pop(inspection_id, None)
        if view is not None:
            view.stop()
            logger.info("viewer: inspection %s stopped (idle)", inspection_id)

    def close(self) -> None:
        """Stop every server (app shutdown)."""
        with self._lock:
            views = list(self._views.values())
            timers = list(self._idle_timers.values())
            self._views.clear()
            self._idle_timers.clear()
        for timer in timers:
            timer.cancel()
        for view in views:
            view.stop()
