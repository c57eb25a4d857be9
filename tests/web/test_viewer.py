"""The viser view: mesh preparation and the websocket bridge (no browser)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from app.viewer import (
    CLOSE_NOT_FOUND,
    VISER_SUBPROTOCOL,
    PlateViewer,
    decimate_mesh,
    deviation_colours,
    load_plate_meshes,
    read_surface_ply,
    router,
)
from pipeline.artifacts.colours import ABOVE_RGB, BELOW_RGB, IN_TOLERANCE_RGB
from tests.web.plates import cylinder_grid, write_artifacts


def test_decimate_keeps_a_cylinder_on_its_surface():
    # Cluster means of points on a cylinder lie inside it by at most the sagitta of a
    # cell: cell ~ sqrt(3000*2000/2000) ~ 55 mm -> sagitta 55^2/(8*5000) ~ 0.08 mm; allow 0.5 mm.
    v, f, _ = cylinder_grid(radius_mm=5000.0, size_mm=(3000.0, 2000.0), n=(121, 81))
    dv, df, _ = decimate_mesh(v, f, max_vertices=2000)
    assert len(dv) <= 2000 and len(dv) > 500
    radial = np.hypot(dv[:, 0], dv[:, 2] - 3000.0 - 5000.0)
    assert np.abs(radial - 5000.0).max() < 0.5
    assert df.max() < len(dv) and len(np.unique(np.sort(df, axis=1), axis=0)) == len(df)
    assert np.all((df[:, 0] != df[:, 1]) & (df[:, 1] != df[:, 2]) & (df[:, 0] != df[:, 2]))


def test_decimate_averages_values_and_leaves_small_meshes_alone():
    v, f, _ = cylinder_grid(radius_mm=5000.0, size_mm=(1000.0, 1000.0), n=(41, 41))
    values = (
        0.01 * v[:, 0]
    )  # linear in x: cluster means of a linear field are the field at the cluster mean
    dv, _, dval = decimate_mesh(v, f, values, max_vertices=300)
    np.testing.assert_allclose(dval, 0.01 * dv[:, 0], atol=1e-9)
    same_v, same_f, _same_val = decimate_mesh(v, f, values, max_vertices=len(v))
    np.testing.assert_array_equal(same_v, v)
    np.testing.assert_array_equal(same_f, f)


def test_decimate_refuses_bad_input():
    v, f, _ = cylinder_grid(radius_mm=5000.0, size_mm=(100.0, 100.0), n=(3, 3))
    with pytest.raises(ValueError, match=r"vertices: expected shape \(V, 3\)"):
        decimate_mesh(v[:, :2], f, max_vertices=2)
    with pytest.raises(ValueError, match=r"faces: expected indices in \[0, 8\]"):
        decimate_mesh(v, f + 5, max_vertices=2)
    with pytest.raises(ValueError, match=r"values: expected shape \(9,\)"):
        decimate_mesh(v, f, np.zeros(4), max_vertices=2)
    with pytest.raises(ValueError, match="max_vertices: expected >= 1"):
        decimate_mesh(v, f, max_vertices=0)


def test_deviation_colours_are_tolerance_bands_and_saturate():
    rgb = deviation_colours(np.array([-9.0, -4.0, 0.0, 1.9, 4.0, 9.0, np.nan]), 4.0, 2.0)
    assert tuple(rgb[0]) == tuple(rgb[1]) == BELOW_RGB[1]  # saturated blue at and beyond -scale
    assert tuple(rgb[4]) == tuple(rgb[5]) == ABOVE_RGB[1]
    assert tuple(rgb[2]) == tuple(rgb[3]) == IN_TOLERANCE_RGB  # one calm band within tolerance
    assert tuple(rgb[6]) == (128, 128, 128)
    with pytest.raises(ValueError, match="limit_mm: expected a finite number above tolerance_mm"):
        deviation_colours(np.zeros(3), 2.0, 2.0)


def test_load_plate_meshes_in_display_frame(tmp_path):
    write_artifacts(tmp_path, size_mm=(3000.0, 2000.0), n=(31, 21))
    meshes = load_plate_meshes(tmp_path, max_vertices=10_000)
    # Display frame: metres, centred; the apex (nearest the cameras) is the highest point.
    assert meshes.extent_m == pytest.approx(3.0)
    apex = meshes.measured_vertices[
        np.argmin(np.abs(meshes.measured_vertices[:, 0]) + np.abs(meshes.measured_vertices[:, 1]))
    ]
    assert apex[2] == pytest.approx(meshes.measured_vertices[:, 2].max(), abs=1e-6)
    tri = meshes.measured_vertices[meshes.measured_faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(normals[:, 2] > 0)  # wound to face up (the cameras' side)
    assert meshes.tolerance_mm == 2.0 and meshes.scale_mm == 4.0
    _, _, dev = read_surface_ply(tmp_path / "surface.ply")
    np.testing.assert_allclose(meshes.deviation_mm, dev, atol=1e-6)


def test_read_surface_ply_needs_a_deviation(tmp_path):
    import trimesh

    v, f, _ = cylinder_grid(radius_mm=5000.0, size_mm=(100.0, 100.0), n=(3, 3))
    (tmp_path / "s.ply").write_bytes(
        trimesh.exchange.ply.export_ply(trimesh.Trimesh(v, f, process=False))
    )
    with pytest.raises(
        ValueError, match=r"s.ply: vertex: expected a property among \('deviation_mm'"
    ):
        read_surface_ply(tmp_path / "s.ply")


@pytest.fixture
def viewer_app(tmp_path):
    write_artifacts(tmp_path / "7", n=(31, 21))
    app = FastAPI()
    app.include_router(router)
    app.state.viewer = PlateViewer(lambda i: tmp_path / str(i), idle_s=0.0)
    yield app
    app.state.viewer.close()


def test_viewer_page_serves_the_bundled_client(viewer_app):
    with TestClient(viewer_app) as client:
        page = client.get("/viewer/7/")
        assert page.status_code == 200 and "<html" in page.text.lower()
        assert "https://" not in page.text  # offline: nothing fetched from outside
        assert client.get("/viewer/8/").status_code == 404


def test_bridge_reaches_the_inspection_server(viewer_app):
    viewer: PlateViewer = viewer_app.state.viewer
    with TestClient(viewer_app) as client:
        with client.websocket_connect("/viewer/7", subprotocols=[VISER_SUBPROTOCOL]) as ws:
            first = ws.receive_bytes()  # viser's first message batch, relayed from loopback
            assert len(first) > 0
            assert viewer.port_for(7) > 0
        with (
            pytest.raises(WebSocketDisconnect) as closed,
            client.websocket_connect("/viewer/8", subprotocols=[VISER_SUBPROTOCOL]) as ws,
        ):
            ws.receive_bytes()
        assert closed.value.code == CLOSE_NOT_FOUND
        with (
            pytest.raises(WebSocketDisconnect) as refused,
            client.websocket_connect("/viewer/7", subprotocols=["viser-v0.0.1"]) as ws,
        ):
            ws.receive_bytes()
        assert refused.value.code == 1002


def test_bridge_accepts_the_browser_before_the_server_starts(viewer_app, monkeypatch):
    """Issue 26: viser's client closes a socket not open within 5 s (the browser saw 1006, the
    log "bridge ... ended" with no reason) and a large plate loads longer than that on a busy
    machine: the bridge accepts first, then starts the inspection's server."""
    viewer: PlateViewer = viewer_app.state.viewer
    load = viewer.port_for
    started: list[float] = []

    def slow_port_for(inspection_id: int, **kwargs) -> int:
        time.sleep(1.0)  # a slow mesh load
        started.append(time.monotonic())
        return load(inspection_id, **kwargs)

    monkeypatch.setattr(viewer, "port_for", slow_port_for)
    with TestClient(viewer_app) as client:
        with client.websocket_connect("/viewer/7", subprotocols=[VISER_SUBPROTOCOL]) as ws:
            accepted = time.monotonic()
            assert not started, "the browser's socket waited for the server to start"
            assert len(ws.receive_bytes()) > 0
        assert started and accepted < started[0]


def test_idle_servers_stop_and_at_most_max_servers_run(tmp_path):
    from app.viewer import ViewerBusyError

    for i in (1, 2, 3):
        write_artifacts(tmp_path / str(i), n=(11, 9))
    viewer = PlateViewer(lambda i: tmp_path / str(i), idle_s=0.5, max_servers=2)
    try:
        viewer.port_for(1)
        viewer.bridge_opened(1)
        viewer.port_for(2)
        viewer.bridge_opened(2)
        assert viewer.running() == [1, 2]
        # Both servers have a browser: a third view is refused with a message that says why.
        with pytest.raises(ViewerBusyError, match="2 inspections are already being viewed"):
            viewer.port_for(3)
        viewer.bridge_closed(1)
        viewer.bridge_opened(3)  # the bridge counts the browser, then asks for the port
        viewer.port_for(3)  # the idle server of inspection 1 makes room
        assert viewer.running() == [2, 3]
        viewer.bridge_closed(2)
        viewer.bridge_closed(3)
        # No browser left: both stop after idle_s.
        deadline = time.monotonic() + 10.0
        while viewer.running() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert viewer.running() == []
    finally:
        viewer.close()


def test_servers_bind_loopback_only_and_refuse_sharing(viewer_app):
    viewer: PlateViewer = viewer_app.state.viewer
    port = viewer.port_for(7)
    view = viewer._views[7]
    assert view.server.get_host() == "127.0.0.1" and port == view.server.get_port()
    assert view.server.request_share_url() is None  # no tunnel to an outside host


def test_viewer_page_says_when_every_server_is_busy(tmp_path):
    for i in (1, 2):
        write_artifacts(tmp_path / str(i), n=(11, 9))
    app = FastAPI()
    app.include_router(router)
    app.state.viewer = PlateViewer(lambda i: tmp_path / str(i), idle_s=60.0, max_servers=1)
    try:
        app.state.viewer.port_for(1)
        app.state.viewer.bridge_opened(1)
        with TestClient(app) as client:
            page = client.get("/viewer/2/")
            assert page.status_code == 503 and "1 inspections are already being viewed" in page.text
            assert client.get("/viewer/1/").status_code == 200
    finally:
        app.state.viewer.close()


def test_the_scene_labels_the_plates_and_numbers_the_defects(tmp_path):
    """The scene's labels: "Measured" and "CAD target" above their plates, and one per defect, on the
    measured surface at the defect's centroid (children of the plates' nodes; a real viser server)."""
    import json

    from app.viewer.meshes import load_plate_meshes

    folder = write_artifacts(tmp_path / "7", n=(31, 21))
    T = np.diag([1.0, -1.0, -1.0, 1.0])  # target frame (z towards the cameras) -> camera frame
    T[2, 3] = 3000.0
    details = {"T_cam_target": T.tolist(), "defects": [{"centroid_mm": [600.0, -300.0]}]}
    (folder / "details.json").write_text(json.dumps(details))
    meshes = load_plate_meshes(folder)
    [(number, place)] = meshes.defects
    # the vertex nearest (600, -300) of the target frame: camera (600, 300), display (x, -y) from
    # the measured surface's centre (the origin here), in metres
    assert number == 1 and place[:2] == pytest.approx([0.6, -0.3], abs=0.06)

    import viser

    from app.viewer.scene import scene_labels

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        labels = scene_labels(server.scene, meshes)
    finally:
        server.stop()
    assert [(label.name, label.text) for label in labels] == [
        ("/plate/measured/label", "Measured"),
        ("/plate/target/label", "CAD target"),
        # in the target's frame, as the map and the defect table give it (issue 26)
        ("/plate/measured/defect-1", "defect 1: x 600, y \u2212300 mm"),
        ("/plate/measured/edge-A", "edge A"),
        ("/plate/measured/edge-B", "edge B"),
        ("/plate/measured/edge-C", "edge C"),
        ("/plate/measured/edge-D", "edge D"),
    ]
    # edge A where the target's y is smallest: camera y largest, display y (-camera y) smallest
    edges = dict(meshes.edges)
    assert edges["A"][1] < edges["C"][1] and edges["D"][0] < edges["B"][0]
    assert np.allclose(labels[2].position, place)  # on the measured surface, in its node's frame
    top = float(meshes.measured_vertices[:, 2].max())
    assert labels[0].position[2] > top  # above the plate


def test_measured_plate_is_shaded_matte_and_in_its_band_colours(tmp_path):
    """Issue 26 (a dent barely visible, the plate very pale): the GLB carries vertex normals (the
    shading shows the dent), a non-metallic material (glTF's default is fully metallic) and the
    band colours linearised, as glTF's COLOR_0 is linear (sRGB 255 stays 255, mid grey 128 -> 55)."""
    import json
    import struct

    from app.viewer.scene import _measured_glb, srgb_to_linear_u8

    write_artifacts(tmp_path / "7", n=(31, 21))
    glb = _measured_glb(load_plate_meshes(tmp_path / "7"))
    (length,) = struct.unpack("<I", glb[12:16])
    tree = json.loads(glb[20 : 20 + length])
    primitive = tree["meshes"][0]["primitives"][0]
    assert {"POSITION", "NORMAL", "COLOR_0"} <= set(primitive["attributes"])
    material = tree["materials"][primitive["material"]]
    assert material["pbrMetallicRoughness"]["metallicFactor"] == 0.0
    assert srgb_to_linear_u8(np.array([[255, 128, 0]])).tolist() == [[255, 55, 0]]
