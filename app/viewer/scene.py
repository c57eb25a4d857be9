"""One inspection's viser scene: the measured surface and the registered target, layout, legend.

Display frame: metres, origin at the centre of the measured surface's bounding box, axes
``(x, -y, -z)`` of the left camera frame, so the side of the plate that faces the cameras looks up
(+z, viser's up direction).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
import trimesh
import viser

from app.viewer.meshes import PlateMeshes, deviation_colours, legend_html

logger = logging.getLogger(__name__)


#: No share button (no outside host), no logo, a narrow panel (docked: :func:`_theme`).
_THEME: dict[str, Any] = {"show_share_button": False, "show_logo": False, "control_width": "small"}
_TARGET_COLOUR = (176, 180, 188)
#: The target's grid over the measured plate (overlaid layout): dark, to read on every band colour.
_TARGET_GRID_COLOUR = (40, 48, 58)
# Scene background: a vertical gradient from light grey-blue (top) to a darker one (bottom).
_BACKGROUND = (
    np.linspace((236, 240, 245), (196, 205, 216), 64)
    .round()
    .astype(np.uint8)[:, None, :]
    .repeat(4, axis=1)
)
_LAYOUTS = ("Side by side", "Overlaid")
#: Share of viser's default environment light (1.0) on the plates.
_ENVIRONMENT = 0.5


class _OfflineViserServer(viser.ViserServer):
    """A viser server that refuses share requests (the share tunnel reaches an outside host)."""

    def request_share_url(self, verbose: bool = True) -> None:
        logger.warning("viewer: a client asked for a share URL; refused, sharing is disabled")
        return


class InspectionView:
    """One inspection's viser server and the meshes it shows."""

    def __init__(self, inspection_id: int, meshes: PlateMeshes, *, host: str):
        self.inspection_id = inspection_id
        self.meshes = meshes
        self._glb = _measured_glb(meshes)
        self.server = _OfflineViserServer(
            host=host, port=0, label=f"Inspection {inspection_id}", verbose=False
        )
        _theme(self.server.gui)
        extent = max(meshes.extent_m, 0.1)
        # Both plates side by side are about 2.3 extents wide. The view spans the page's width
        # (viser's vertical field of view is 75 deg): at a distance of 1.25 extents they fit a
        # view 1.45 wide by 1 high (a 1366x768 screen, the panel docked), seen from the front,
        # above.
        self.server.initial_camera.position = (0.0, -0.97 * extent, 0.8 * extent)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
        self._client_nodes: dict[int, tuple[str, ...]] = {}
        self.server.on_client_connect(self._build_client_scene)
        self.server.on_client_disconnect(self._forget_client)

    def _forget_client(self, client: viser.ClientHandle) -> None:
        self._client_nodes.pop(client.client_id, None)

    @property
    def port(self) -> int:
        return self.server.get_port()

    def _build_client_scene(self, client: viser.ClientHandle) -> None:
        """Give one browser its own copy of the plate, layout toggle and legend."""
        meshes = self.meshes
        extent = max(meshes.extent_m, 0.1)
        half = np.array([0.575 * extent, 0.0, 0.0])
        _theme(client.gui)
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
        # Overlaid, a solid target on the measured plate would z-fight into speckle where they
        # meet (everywhere within tolerance): the target is then drawn as its grid instead.
        target_grid = client.scene.add_mesh_simple(
            "/plate/target-grid",
            meshes.target_vertices,
            meshes.target_faces,
            color=_TARGET_GRID_COLOUR,
            wireframe=True,
            opacity=0.45,
            visible=False,
        )
        # A tinted background and a floor grid (0.5 m cells): a plate within tolerance is
        # coloured near white, which must not vanish into a white page.
        client.scene.set_background_image(_BACKGROUND, format="png")
        # Less of the environment's even light, so the default lights' direction shades the
        # surface and a dent shows in it (at full intensity the plate looked flat and pale).
        client.scene.configure_environment_map("warehouse", environment_intensity=_ENVIRONMENT)
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

        labels = scene_labels(client.scene, meshes)
        self._client_nodes[client.client_id] = (
            measured.name,
            target.name,
            target_grid.name,
            *(label.name for label in labels),
        )

        @layout.on_update
        def _(_event: object) -> None:
            overlaid = layout.value == _LAYOUTS[1]
            measured.position = np.zeros(3) if overlaid else -half
            target.visible = not overlaid
            target_grid.visible = overlaid
            labels[1].visible = not overlaid  # "CAD target" would sit on the measured plate

    def client_count(self) -> int:
        return len(self.server.get_clients())

    def nodes_of(self, client_id: int) -> tuple[str, ...]:
        """Names of the plate's scene nodes built for a client."""
        return self._client_nodes.get(client_id, ())

    def stop(self) -> None:
        self.server.stop()


def _xyz(point: np.ndarray) -> tuple[float, float, float]:
    """A scene position as three floats."""
    x, y, z = (float(v) for v in point)
    return x, y, z


def _outward_anchor(outward: np.ndarray) -> Any:
    """A label's anchor that makes it read away from the plate: to the left of a left edge, to the
    right of a right one (display x), centred on the near and far edges."""
    if abs(outward[0]) <= abs(outward[1]):
        return "center-center"
    return "center-right" if outward[0] < 0 else "center-left"


def _theme(gui: viser.GuiApi) -> None:
    """The panel's theme, docked to the right of the view rather than floating over it (on a
    1366x768 screen a floating panel covered the target plate)."""
    gui.configure_theme(**_THEME)
    gui.main_panel.dock_right()


def _measured_glb(meshes: PlateMeshes) -> bytes:
    """The measured plate as GLB: smooth vertex normals (a dent shows in its shading), the
    band colours as glTF's linear ``COLOR_0`` (written as sRGB they were drawn washed out)
    and a matte, non-metallic material (glTF's default is fully metallic, which reflected the
    light background and left the plate very pale)."""
    mesh = trimesh.Trimesh(meshes.measured_vertices, meshes.measured_faces, process=False)
    srgb = deviation_colours(meshes.deviation_mm, meshes.scale_mm, meshes.tolerance_mm)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=srgb_to_linear_u8(srgb))
    glb = mesh.export(file_type="glb", include_normals=True, tree_postprocessor=_matte)
    if not isinstance(glb, bytes):  # trimesh answers GLB as bytes
        raise TypeError(f"trimesh: expected GLB bytes, got {type(glb).__name__}")
    return glb


def srgb_to_linear_u8(rgb: np.ndarray) -> np.ndarray:
    """(V, 3) uint8 sRGB colours as (V, 3) uint8 linear ones (IEC 61966-2-1)."""
    c = np.asarray(rgb, dtype=np.float64) / 255.0
    linear = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return np.round(linear * 255.0).astype(np.uint8)


def _matte(tree: dict[str, Any]) -> None:
    """glTF tree post-processor: every primitive gets one matte, double-sided material."""
    tree["materials"] = [
        {
            "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 0.75},
            "doubleSided": True,
        }
    ]
    for mesh in tree.get("meshes", []):
        for primitive in mesh["primitives"]:
            primitive["material"] = 0


def scene_labels(scene: viser.SceneApi, meshes: PlateMeshes) -> list[viser.LabelHandle]:
    """Labels in the scene: "Measured" and "CAD target" above their plates, each defect's number and
    its place in the target's frame at its place, and the plate's edges named as on the map
    (children of the plates' nodes: they follow the layout)."""
    extent = max(meshes.extent_m, 0.1)
    above = 0.18 * extent  # clear of the edge labels
    top_m = float(meshes.measured_vertices[:, 2].max()) + above
    top_t = float(meshes.target_vertices[:, 2].max()) + above
    back = 0.5 * extent
    labels = [
        scene.add_label("/plate/measured/label", "Measured", position=(0.0, back, top_m)),
        scene.add_label("/plate/target/label", "CAD target", position=(0.0, back, top_t)),
    ]
    xy_mm: Sequence[tuple[float, float] | tuple[None, None]] = meshes.defect_xy_mm or tuple(
        (None, None) for _ in meshes.defects
    )
    for (number, place), (x, y) in zip(meshes.defects, xy_mm, strict=True):
        text = f"defect {number}" if x is None else f"defect {number}: x {x:.0f}, y {y:.0f} mm"
        labels.append(
            scene.add_label(
                f"/plate/measured/defect-{number}",
                text.replace("-", "\u2212"),
                position=_xyz(place),
                anchor="bottom-left",  # reads away from the edge labels on the left
            )
        )
    for name, place in meshes.edges:  # the target frame's edges, named as on the map
        outward = np.array([place[0], place[1], 0.0])  # from the display origin, the plate's centre
        outward *= 0.06 * extent / max(float(np.linalg.norm(outward)), 1e-9)
        labels.append(
            scene.add_label(
                f"/plate/measured/edge-{name}",
                f"edge {name}",
                position=_xyz(np.asarray(place) + outward),
                anchor=_outward_anchor(outward),
            )
        )
    return labels
