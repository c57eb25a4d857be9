"""The 3D view of an inspection: viser behind a websocket bridge on the app's own port.

Layout
------
Each inspection that a browser looks at gets its own :class:`viser.ViserServer`,
bound to loopback on an ephemeral port. FastAPI serves viser's bundled client
page at ``/viewer/{inspection_id}/`` and bridges the websocket the page opens
(``/viewer/{inspection_id}``) to that inspection's viser server. Which plate a
browser sees is therefore fixed by the bridge path, not by the page's query
string (which viser never receives, viser issue #365): every client of an
inspection's server is, by construction, a client of that inspection. No
private viser attribute is used.

Inside a server every browser gets its own scene and GUI (``on_client_connect``):
the measured surface coloured by signed deviation, the registered CAD target,
a layout toggle (side by side / overlaid with the target translucent) and a
colour legend in mm. A server with no client left is stopped after
``idle_s`` seconds, and at most ``max_servers`` run at once (an idle one makes
room; when all have browsers the page says so).

Room for the operator: a client without a valid dashboard session that is not on
loopback (anonymous; reads are open on the cell network) holds at most
``max_sockets_per_client`` viewer websockets per address, and starts a server only
while fewer than ``max_servers - reserved_servers`` servers have a browser. The
operator (a dashboard session, or the cell's own screen on loopback) may use every
server, so a few anonymous clients cannot take the 3D view from the cell.

Display frame: metres, origin at the centre of the measured surface's bounding
box, axes ``(x, -y, -z)`` of the left camera frame, so the side of the plate that
faces the cameras looks up (+z, viser's up direction).

Sharing is off: the share button is hidden and the server refuses share
requests (the cell network is closed).
"""

from __future__ import annotations

import asyncio
import html
import json
import logging
import threading
from collections.abc import Callable
from contextlib import asynccontextmanager, suppress
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import trimesh
import viser
import websockets
from fastapi import APIRouter, FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import HTMLResponse
from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection

from app.deps import client_address, has_dashboard_session, is_loopback
from app.security_headers import FRAMED_HEADERS, viewer_csp

logger = logging.getLogger(__name__)

#: The websocket subprotocol viser's bundled client offers (client and server versions must match).
VISER_SUBPROTOCOL = f"viser-v{viser.__version__}"
#: Vertex properties of surface.ply that may carry the signed deviation in mm, in order of preference.
DEVIATION_PROPERTIES = ("deviation_mm", "deviation", "quality")
#: The colour scale saturates at this multiple of the tolerance.
SCALE_TOLERANCES = 2.0
#: Close code sent to the browser when an inspection has nothing to show.
CLOSE_NOT_FOUND = 4404
#: Close code (RFC 6455 "try again later") when every allowed viewer server is busy.
CLOSE_TRY_AGAIN_LATER = 1013

# Display frame from the left camera frame: x, -y, -z (the cameras' side looks up).
_CAM_TO_DISPLAY = np.diag([1.0, -1.0, -1.0])
_TARGET_COLOUR = (176, 180, 188)
# Scene background: a vertical gradient from light grey-blue (top) to a darker one (bottom).
_BACKGROUND = (
    np.linspace((236, 240, 245), (196, 205, 216), 64)
    .round()
    .astype(np.uint8)[:, None, :]
    .repeat(4, axis=1)
)
_LAYOUTS = ("Side by side", "Overlaid")


# --------------------------------------------------------------------------- meshes


@dataclass(frozen=True)
class PlateMeshes:
    """Display-ready meshes of one inspection (display frame, metres).

    Attributes
    ----------
    measured_vertices : (V, 3) float32, m
    measured_faces : (F, 3) int32
    deviation_mm : (V,) float32, signed deviation per measured vertex, mm (positive:
        the measured surface lies on the cameras' side of the target).
    target_vertices : (W, 3) float32, m
    target_faces : (G, 3) int32
    tolerance_mm : float
    extent_m : float, largest side of the measured or the target surface's bounding box, m.
    """

    measured_vertices: np.ndarray
    measured_faces: np.ndarray
    deviation_mm: np.ndarray
    target_vertices: np.ndarray
    target_faces: np.ndarray
    tolerance_mm: float
    extent_m: float

    @property
    def floor_z_m(self) -> float:
        """Height of a floor just below both meshes (display frame), m."""
        low = min(
            float(self.measured_vertices[:, 2].min()), float(self.target_vertices[:, 2].min())
        )
        return low - 0.02 * self.extent_m

    @property
    def scale_mm(self) -> float:
        """Deviation at which the colour scale saturates, mm."""
        return SCALE_TOLERANCES * self.tolerance_mm


def decimate_mesh(
    vertices: np.ndarray, faces: np.ndarray, values: np.ndarray | None = None, *, max_vertices: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Reduce a mesh to at most about ``max_vertices`` vertices by vertex clustering.

    Vertices are binned into cubic cells; each cell becomes one vertex at the mean
    of its members (the per-vertex ``values`` are averaged the same way), faces are
    re-indexed and those that collapse are dropped. Meant for display only.

    Parameters
    ----------
    vertices : (V, 3) float array, any length unit.
    faces : (F, 3) int array of vertex indices.
    values : (V,) float array or None, a per-vertex quantity to carry along.
    max_vertices : int, > 0.

    Returns
    -------
    vertices : (V', 3) float64, faces : (F', 3) int32, values : (V',) float64 or None
        Unchanged (as copies) when the mesh already has at most ``max_vertices`` vertices.

    Raises
    ------
    ValueError
        On shapes that do not match, face indices out of range or ``max_vertices < 1``.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(
            f"faces: expected an integer array of shape (F, 3), got {faces.dtype} {faces.shape}"
        )
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(
            f"faces: expected indices in [0, {len(vertices) - 1}], got [{faces.min()}, {faces.max()}]"
        )
    if values is not None:
        values = np.asarray(values, dtype=np.float64)
        if values.shape != (len(vertices),):
            raise ValueError(f"values: expected shape ({len(vertices)},), got {values.shape}")
    if max_vertices < 1:
        raise ValueError(f"max_vertices: expected >= 1, got {max_vertices}")
    if len(vertices) <= max_vertices:
        return vertices.copy(), faces.astype(np.int32), None if values is None else values.copy()

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    span = np.maximum(hi - lo, 1e-12)
    # Start from the cell size that would give max_vertices on a surface filling
    # its bounding box's two largest sides, grow until the count fits.
    a, b = np.sort(span)[-2:]
    cell = float(np.sqrt(a * b / max_vertices))
    for _ in range(40):
        keys = np.floor((vertices - lo) / cell).astype(np.int64)
        dims = keys.max(axis=0) + 1
        flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
        cells, inverse = np.unique(flat, return_inverse=True)
        if len(cells) <= max_vertices:
            break
        cell *= 1.15
    counts = np.bincount(inverse, minlength=len(cells)).astype(np.float64)
    out_vertices = np.stack(
        [np.bincount(inverse, vertices[:, k], len(cells)) for k in range(3)], axis=1
    )
    out_vertices /= counts[:, None]
    out_values = None if values is None else np.bincount(inverse, values, len(cells)) / counts
    out_faces = inverse[faces]
    keep = (
        (out_faces[:, 0] != out_faces[:, 1])
        & (out_faces[:, 1] != out_faces[:, 2])
        & (out_faces[:, 0] != out_faces[:, 2])
    )
    out_faces = out_faces[keep]
    # Faces that collapsed onto the same three cells: keep the first (with its winding).
    _, first = np.unique(np.sort(out_faces, axis=1), axis=0, return_index=True)
    out_faces = out_faces[np.sort(first)]
    return out_vertices, out_faces.astype(np.int32), out_values


def deviation_colours(deviation_mm: np.ndarray, scale_mm: float) -> np.ndarray:
    """Colour signed deviations on a diverging blue - white - red scale.

    Parameters
    ----------
    deviation_mm : (V,) float array, mm. NaN is drawn grey.
    scale_mm : float > 0, deviation drawn in full colour; larger magnitudes saturate
        (the legend says so).

    Returns
    -------
    (V, 3) uint8 RGB: blue below the target (away from the cameras), red above it.
    """
    deviation_mm = np.asarray(deviation_mm, dtype=np.float64)
    if deviation_mm.ndim != 1:
        raise ValueError(f"deviation_mm: expected shape (V,), got {deviation_mm.shape}")
    if not (np.isfinite(scale_mm) and scale_mm > 0):
        raise ValueError(f"scale_mm: expected a positive number, got {scale_mm}")
    t = np.clip(deviation_mm / scale_mm, -1.0, 1.0)
    stops_t = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
    stops = np.array(_COLOUR_STOPS, dtype=np.float64)
    rgb = np.stack([np.interp(t, stops_t, stops[:, k]) for k in range(3)], axis=1)
    rgb[~np.isfinite(deviation_mm)] = (128, 128, 128)
    return np.round(rgb).astype(np.uint8)


# Diverging scale (blue, light blue, near white, orange, red) at -1, -1/2, 0, 1/2, 1.
_COLOUR_STOPS = ((33, 102, 172), (146, 197, 222), (247, 247, 247), (244, 165, 130), (178, 24, 43))


def legend_html(scale_mm: float, tolerance_mm: float) -> str:
    """HTML of the colour legend shown in the viewer's panel (ticks in mm)."""
    stops = ", ".join(f"rgb{c}" for c in _COLOUR_STOPS)
    ticks = "".join(
        f'<span style="position:absolute;left:{100 * (v + scale_mm) / (2 * scale_mm):.1f}%;'
        f'transform:translateX(-50%)">{v:+.1f}</span>'
        for v in (-scale_mm, -tolerance_mm, 0.0, tolerance_mm, scale_mm)
    )
    return (
        '<div style="font:12px sans-serif;padding:4px 14px 4px 14px">'
        "<div>Deviation from target, mm</div>"
        f'<div style="height:14px;margin-top:4px;background:linear-gradient(to right, {stops})"></div>'
        f'<div style="position:relative;height:14px">{ticks}</div>'
        f'<div style="margin-top:6px;color:#555">red: proud of target (cameras\' side); '
        f"tolerance ±{tolerance_mm:g} mm; colours saturate beyond ±{scale_mm:g} mm</div></div>"
    )


def read_surface_ply(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read the measured surface written by the pipeline.

    Returns
    -------
    vertices : (V, 3) float64, mm, left camera frame; faces : (F, 3) int64;
    deviation_mm : (V,) float64, the vertex property named in :data:`DEVIATION_PROPERTIES`.

    Raises
    ------
    ValueError
        If the file has no faces or no deviation property.
    """
    mesh = trimesh.load(path, process=False, force="mesh")
    raw = mesh.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    names = () if raw is None or raw.dtype.names is None else raw.dtype.names
    found = next((n for n in DEVIATION_PROPERTIES if n in names), None)
    if found is None:
        raise ValueError(
            f"{path.name}: vertex: expected a property among {DEVIATION_PROPERTIES}, got {names}"
        )
    if len(mesh.faces) == 0:
        raise ValueError(f"{path.name}: face: expected a triangle mesh, got no faces")
    return (
        np.asarray(mesh.vertices, dtype=np.float64),
        np.asarray(mesh.faces),
        np.asarray(raw[found], dtype=np.float64),
    )


def load_plate_meshes(artifact_dir: Path, *, max_vertices: int = 150_000) -> PlateMeshes:
    """Load surface.ply, target.ply and result.json of an inspection, ready for display.

    Parameters
    ----------
    artifact_dir : Path, the inspection's artifact folder (holds result.json and the
        files its ``artifacts`` names: ``surface`` and ``target_surface``).
    max_vertices : int, each mesh is decimated to about this many vertices.

    Raises
    ------
    FileNotFoundError
        If result.json or a mesh is missing.
    ValueError
        If a mesh lacks what the view needs.
    """
    artifact_dir = Path(artifact_dir)
    document = json.loads((artifact_dir / "result.json").read_text())
    names = document.get("artifacts", {})
    surface_path = artifact_dir / names.get("surface", "surface.ply")
    target_path = artifact_dir / names.get("target_surface", "target.ply")
    vertices, faces, deviation = read_surface_ply(surface_path)
    target = trimesh.load(target_path, process=False, force="mesh")

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = (lo + hi) / 2.0

    def to_display(v_mm: np.ndarray) -> np.ndarray:
        return ((v_mm - centre) @ _CAM_TO_DISPLAY.T / 1000.0).astype(np.float32)

    mv, mf, md = decimate_mesh(vertices, faces, deviation, max_vertices=max_vertices)
    tv, tf, _ = decimate_mesh(
        np.asarray(target.vertices), np.asarray(target.faces), max_vertices=max_vertices
    )
    mv, tv = to_display(mv), to_display(tv)
    return PlateMeshes(
        measured_vertices=mv,
        measured_faces=_facing_up(mv, mf),
        deviation_mm=md.astype(np.float32),
        target_vertices=tv,
        target_faces=_facing_up(tv, tf),
        tolerance_mm=float(document["tolerance_mm"]),
        extent_m=float(max(np.ptp(mv, axis=0).max(), np.ptp(tv, axis=0).max())),
    )


def _facing_up(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Wind the faces so that their normals point up (+z, the cameras' side) on average."""
    tri = vertices[faces].astype(np.float64)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return faces[:, ::-1].copy() if normals[:, 2].sum() < 0 else faces


# --------------------------------------------------------------------------- servers


class _OfflineViserServer(viser.ViserServer):
    """A viser server that refuses share requests (the share tunnel reaches an outside host)."""

    def request_share_url(self, verbose: bool = True) -> None:
        logger.warning("viewer: a client asked for a share URL; refused, sharing is disabled")
        return


class _InspectionView:
    """One inspection's viser server and the meshes it shows."""

    def __init__(self, inspection_id: int, meshes: PlateMeshes, *, host: str):
        self.inspection_id = inspection_id
        self.meshes = meshes
        self._glb = _measured_glb(meshes)
        self.server = _OfflineViserServer(
            host=host, port=0, label=f"Inspection {inspection_id}", verbose=False
        )
        self.server.gui.configure_theme(
            show_share_button=False, show_logo=False, control_width="medium"
        )
        extent = max(meshes.extent_m, 0.1)
        # Far enough back that both plates side by side (about 2.2 extents wide) fit a
        # landscape panel (viser's vertical field of view is 75 deg), seen from the front, above.
        self.server.initial_camera.position = (0.0, -1.25 * extent, 1.0 * extent)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
        self._client_nodes: dict[int, tuple[str, ...]] = {}
        self.server.on_client_connect(self._build_client_scene)
        self.server.on_client_disconnect(
            lambda client: self._client_nodes.pop(client.client_id, None)
        )

    @property
    def port(self) -> int:
        return self.server.get_port()

    def _build_client_scene(self, client: viser.ClientHandle) -> None:
        """Give one browser its own copy of the plate, layout toggle and legend."""
        meshes = self.meshes
        extent = max(meshes.extent_m, 0.1)
        half = np.array([0.575 * extent, 0.0, 0.0])
        client.gui.configure_theme(show_share_button=False, show_logo=False, control_width="medium")
        measured = client.scene.add_glb("/plate/measured", self._glb, position=-half)
        target = client.scene.add_mesh_simple(
            "/plate/target",
            meshes.target_vertices,
            meshes.target_faces,
            color=_TARGET_COLOUR,
            opacity=1.0,
            side="double",
            position=half,
        )
        # A tinted background and a floor grid (0.5 m cells): a plate within tolerance is
        # coloured near white, which must not vanish into a white page.
        client.scene.set_background_image(_BACKGROUND, format="png")
        client.scene.add_grid(
            "/floor",
            width=2.6 * extent,
            height=1.6 * extent,
            cell_size=0.5,
            section_size=1.0,
            cell_color=(170, 178, 188),
            section_color=(120, 130, 142),
            position=(0.0, 0.0, meshes.floor_z_m),
        )
        layout = client.gui.add_dropdown("Layout", _LAYOUTS, initial_value=_LAYOUTS[0])
        client.gui.add_html(legend_html(meshes.scale_mm, meshes.tolerance_mm))

        self._client_nodes[client.client_id] = (measured.name, target.name)

        @layout.on_update
        def _(_event) -> None:
            overlaid = layout.value == _LAYOUTS[1]
            measured.position = np.zeros(3) if overlaid else -half
            target.position = np.zeros(3) if overlaid else half
            target.opacity = 0.35 if overlaid else 1.0

    def client_count(self) -> int:
        return len(self.server.get_clients())

    def nodes_of(self, client_id: int) -> tuple[str, ...]:
        """Names of the plate's scene nodes built for a client."""
        return self._client_nodes.get(client_id, ())

    def stop(self) -> None:
        self.server.stop()


def _measured_glb(meshes: PlateMeshes) -> bytes:
    mesh = trimesh.Trimesh(meshes.measured_vertices, meshes.measured_faces, process=False)
    mesh.visual = trimesh.visual.ColorVisuals(
        mesh, vertex_colors=deviation_colours(meshes.deviation_mm, meshes.scale_mm)
    )
    return mesh.export(file_type="glb")


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
        self._views: dict[int, _InspectionView] = {}
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
            view = _InspectionView(inspection_id, meshes, host=self._host)
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


# --------------------------------------------------------------------------- FastAPI side


@cache
def _client_page() -> bytes:
    return (Path(viser.__file__).parent / "client" / "build" / "index.html").read_bytes()


router = APIRouter(tags=["viewer"])


def _viewer(app: FastAPI) -> PlateViewer | None:
    return getattr(app.state, "viewer", None)


@cache
def _client_page_csp() -> str:
    return viewer_csp(_client_page())


def _operator(conn: HTTPConnection) -> bool:
    """True for the operator: a client on loopback (the cell's screen) or with a valid dashboard session."""
    return is_loopback(conn) or has_dashboard_session(conn)


@router.get("/viewer/{inspection_id}/", response_class=HTMLResponse, include_in_schema=False)
def viewer_page(inspection_id: int, request: Request) -> HTMLResponse:
    """viser's bundled client page; its websocket goes to ``/viewer/{inspection_id}`` (the bridge).

    Every answer may be framed by the dashboard (same origin only); the client page gets the
    policy of :func:`app.security_headers.viewer_csp`.
    """
    viewer = _viewer(request.app)
    if viewer is None:
        return HTMLResponse(
            "<p>The 3D view is not running on this server.</p>",
            status_code=503,
            headers=FRAMED_HEADERS,
        )
    if not viewer.has_view(inspection_id):
        return HTMLResponse(
            f"<p>Inspection {inspection_id} has no surface to show.</p>",
            status_code=404,
            headers=FRAMED_HEADERS,
        )
    operator = _operator(request)
    try:
        viewer.check_capacity(inspection_id, privileged=operator)
        viewer.check_client(None if operator else client_address(request))
    except ViewerBusyError as err:
        return HTMLResponse(
            f"<p>{html.escape(str(err))}.</p>", status_code=503, headers=FRAMED_HEADERS
        )
    return HTMLResponse(
        _client_page(), headers={**FRAMED_HEADERS, "Content-Security-Policy": _client_page_csp()}
    )


@router.websocket("/viewer/{inspection_id}")
async def viewer_bridge(websocket: WebSocket, inspection_id: int) -> None:
    """Forward a browser's viser websocket to the inspection's viser server on loopback."""
    viewer = _viewer(websocket.app)
    if viewer is None or not viewer.has_view(inspection_id):
        await websocket.close(code=CLOSE_NOT_FOUND)
        return
    if VISER_SUBPROTOCOL not in websocket.scope.get("subprotocols", []):
        offered = websocket.scope.get("subprotocols", [])
        await websocket.close(
            code=1002, reason=f"expected subprotocol {VISER_SUBPROTOCOL}, got {offered}"
        )
        return
    operator = is_loopback(websocket) or await run_in_threadpool(has_dashboard_session, websocket)
    client = None if operator else client_address(websocket)
    # Counted before the server starts, so that it is stopped when idle however this ends.
    try:
        viewer.bridge_opened(inspection_id, client)
    except ViewerBusyError as err:
        logger.warning("viewer: inspection %s refused to %s: %s", inspection_id, client, err)
        await websocket.close(code=CLOSE_TRY_AGAIN_LATER, reason=str(err)[:120])
        return
    try:
        try:
            port = await run_in_threadpool(viewer.port_for, inspection_id, privileged=operator)
        except ViewerBusyError as err:
            logger.warning("viewer: inspection %s refused: %s", inspection_id, err)
            await websocket.close(code=CLOSE_TRY_AGAIN_LATER, reason=str(err)[:120])
            return
        except (OSError, ValueError) as err:
            logger.error("viewer: inspection %s cannot be shown: %s", inspection_id, err)
            await websocket.close(code=CLOSE_NOT_FOUND)
            return
        await websocket.accept(subprotocol=VISER_SUBPROTOCOL)
        async with websockets.connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[VISER_SUBPROTOCOL],
            max_size=None,
            compression=None,
            open_timeout=10,
        ) as upstream:
            await _pump(websocket, upstream)
    except (OSError, websockets.exceptions.WebSocketException) as err:
        logger.warning("viewer: bridge for inspection %s ended: %s", inspection_id, err)
    finally:
        viewer.bridge_closed(inspection_id, client)
        with suppress(RuntimeError, WebSocketDisconnect):  # the browser side is closed already
            await websocket.close()


async def _pump(browser: WebSocket, upstream) -> None:
    """Copy messages both ways until either side closes."""

    async def browser_to_viser() -> None:
        while True:
            message = await browser.receive()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            await upstream.send(data if data is not None else message.get("text", ""))

    async def viser_to_browser() -> None:
        async for data in upstream:
            if isinstance(data, bytes):
                await browser.send_bytes(data)
            else:
                await browser.send_text(data)

    tasks = [asyncio.create_task(browser_to_viser()), asyncio.create_task(viser_to_browser())]
    try:
        done, _pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    for task in done:
        err = task.exception()
        if err is not None and not isinstance(
            err, (WebSocketDisconnect, websockets.exceptions.ConnectionClosed)
        ):
            raise err


def attach(app: FastAPI, settings):
    """Create the app's 3D viewer as ``app.state.viewer``; called in the app's lifespan.

    Servers start on demand (the first browser to open an inspection's view), bound to
    loopback; ``settings.viewer_idle_s`` and ``settings.viewer_max_servers`` bound them,
    ``settings.viewer_max_sockets_per_client`` and ``settings.viewer_reserved_servers`` keep
    room for the operator. The routes (:data:`router`) are included by :mod:`web.routes`.

    Parameters
    ----------
    app : FastAPI
    settings : app.settings.Settings, its ``data_dir`` locates the artifacts.

    Returns
    -------
    An async context manager that stops every viewer server on exit (app shutdown).
    """
    from app.storage import Storage

    storage = Storage(settings.data_dir)
    viewer = PlateViewer(
        storage.artifacts_dir,
        idle_s=settings.viewer_idle_s,
        max_servers=settings.viewer_max_servers,
        max_sockets_per_client=settings.viewer_max_sockets_per_client,
        reserved_servers=settings.viewer_reserved_servers,
    )
    app.state.viewer = viewer

    @asynccontextmanager
    async def running():
        try:
            yield viewer
        finally:
            viewer.close()

    return running()
