"""The surfaces the 3D view shows: the PLYs read (pipeline.artifacts.ply), decimation to display size, colours."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import overload

import numpy as np

from pipeline.artifacts.colours import (
    ABOVE_RGB,
    BELOW_RGB,
    IN_TOLERANCE_RGB,
    tolerance_band_colormap,
)
from pipeline.artifacts.ply import read_mesh_ply, read_surface_ply
from pipeline.judge.plate_map import to_target_frame

logger = logging.getLogger(__name__)


#: The colour scale saturates at this multiple of the tolerance.
SCALE_TOLERANCES = 2.0

# Display frame from the left camera frame: x, -y, -z (the cameras' side looks up).
_CAM_TO_DISPLAY = np.diag([1.0, -1.0, -1.0])

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
    defects : tuple of (int, (3,) float32), each defect's number (as on the result page) and its
        place on the measured surface (display frame, m).
    defect_xy_mm : tuple of (float, float), each defect's centroid in the target's frame (as on the
        result page's map and table), mm.
    edges : tuple of (str, (3,) float32), the plate's edges named as on the map ("A" where the
        target's y is smallest, then B, C, D counter-clockwise) and a point of the measured surface
        at the middle of each (display frame, m).
    """

    measured_vertices: np.ndarray
    measured_faces: np.ndarray
    deviation_mm: np.ndarray
    target_vertices: np.ndarray
    target_faces: np.ndarray
    tolerance_mm: float
    extent_m: float
    defects: tuple[tuple[int, np.ndarray], ...] = ()
    defect_xy_mm: tuple[tuple[float, float], ...] = ()
    edges: tuple[tuple[str, np.ndarray], ...] = ()

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


@overload
def decimate_mesh(
    vertices: np.ndarray, faces: np.ndarray, values: np.ndarray, *, max_vertices: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@overload
def decimate_mesh(
    vertices: np.ndarray, faces: np.ndarray, values: None = None, *, max_vertices: int
) -> tuple[np.ndarray, np.ndarray, None]: ...


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
    out_vertices = (
        np.stack([np.bincount(inverse, vertices[:, k], len(cells)) for k in range(3)], axis=1)
        / counts[:, None]
    )
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


def deviation_colours(deviation_mm: np.ndarray, scale_mm: float, tolerance_mm: float) -> np.ndarray:
    """Colour signed deviations by tolerance band, as the result page's map does.

    Parameters
    ----------
    deviation_mm : (V,) float array, mm. NaN is drawn grey.
    scale_mm : float > tolerance_mm, deviation drawn in the deepest colour; larger magnitudes
        saturate (the legend says so).
    tolerance_mm : float > 0, within it one calm green.

    Returns
    -------
    (V, 3) uint8 RGB (:func:`pipeline.artifacts.colours.tolerance_band_colormap`): green within
    tolerance, orange to dark red above the target (towards the cameras), light to dark blue below.
    """
    deviation_mm = np.asarray(deviation_mm, dtype=np.float64)
    if deviation_mm.ndim != 1:
        raise ValueError(f"deviation_mm: expected shape (V,), got {deviation_mm.shape}")
    return tolerance_band_colormap(deviation_mm, tolerance_mm=tolerance_mm, limit_mm=scale_mm)


def legend_html(scale_mm: float, tolerance_mm: float) -> str:
    """HTML of the viewer panel's legend: which surface is which, and the colour bands in mm."""

    def swatch(rgb: tuple[int, int, int]) -> str:
        return (
            f'<span style="display:inline-block;width:14px;height:10px;margin:0 3px 0 8px;'
            f'vertical-align:middle;border:1px solid #999;background:rgb{rgb}"></span>'
        )

    return (
        '<div style="font:12px sans-serif;padding:4px 14px 4px 14px;line-height:1.6">'
        '<div id="viewer-surfaces"><b>Side by side:</b> left the measured plate (coloured), right the '
        "CAD target (grey). <b>Overlaid:</b> the target is drawn as a grid over the measured plate.</div>"
        '<div style="margin-top:6px">Deviation from target, mm</div>'
        f"<div>{swatch(BELOW_RGB[1])}below −{scale_mm:g}{swatch(BELOW_RGB[0])}below −{tolerance_mm:g}</div>"
        f"<div>{swatch(IN_TOLERANCE_RGB)}within ±{tolerance_mm:g} (tolerance)</div>"
        f"<div>{swatch(ABOVE_RGB[0])}above +{tolerance_mm:g}{swatch(ABOVE_RGB[1])}above +{scale_mm:g}</div>"
        '<div style="margin-top:4px;color:#555">above: proud of the target (cameras\' side)</div></div>'
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
    target_vertices, target_faces = read_mesh_ply(target_path)

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = (lo + hi) / 2.0

    def to_display(v_mm: np.ndarray) -> np.ndarray:
        return np.asarray((v_mm - centre) @ _CAM_TO_DISPLAY.T / 1000.0, dtype=np.float32)

    mv, mf, md = decimate_mesh(vertices, faces, deviation, max_vertices=max_vertices)
    tv, tf, _ = decimate_mesh(target_vertices, target_faces, max_vertices=max_vertices)
    in_target = _in_target_xy(artifact_dir, vertices)
    places = _defect_places(artifact_dir, vertices, in_target)
    mv, tv = to_display(mv), to_display(tv)
    return PlateMeshes(
        measured_vertices=mv,
        measured_faces=_facing_up(mv, mf),
        deviation_mm=md.astype(np.float32),
        target_vertices=tv,
        target_faces=_facing_up(tv, tf),
        tolerance_mm=float(document["tolerance_mm"]),
        extent_m=float(max(np.ptp(mv, axis=0).max(), np.ptp(tv, axis=0).max())),
        defects=tuple((k, to_display(p[None])[0]) for k, p, _ in places),
        defect_xy_mm=tuple(xy for _, _, xy in places),
        edges=tuple(
            (name, to_display(p[None])[0]) for name, p in _edge_places(in_target, vertices)
        ),
    )


def _in_target_xy(artifact_dir: Path, vertices_mm: np.ndarray) -> np.ndarray | None:
    """(V, 2) the vertices' x, y in the target's frame, mm; None without a registration."""
    try:
        details = json.loads((artifact_dir / "details.json").read_text())
        return to_target_frame(vertices_mm, details["T_cam_target"])[:, :2]
    except (OSError, ValueError, KeyError):
        return None


def _defect_places(
    artifact_dir: Path, vertices_mm: np.ndarray, in_target: np.ndarray | None
) -> list[tuple[int, np.ndarray, tuple[float, float]]]:
    """Each defect of details.json (numbered from 1): its number, the measured vertex nearest its
    centroid in the target's x, y (camera frame, mm) and that centroid (target frame, mm); none
    without details.json or a registration."""
    if in_target is None:
        return []
    details = json.loads((artifact_dir / "details.json").read_text())
    places = []
    for k, d in enumerate(details.get("defects", []), start=1):
        if d.get("centroid_mm") is not None:
            xy = np.asarray(d["centroid_mm"], dtype=np.float64)
            nearest = int(np.argmin(((in_target - xy) ** 2).sum(axis=1)))
            places.append((k, vertices_mm[nearest], (float(xy[0]), float(xy[1]))))
    return places


def _edge_places(
    in_target: np.ndarray | None, vertices_mm: np.ndarray
) -> list[tuple[str, np.ndarray]]:
    """The measured vertex at the middle of each edge of the plate, named as on the map (A: least
    target y, B: most x, C: most y, D: least x); none without a registration."""
    if in_target is None or len(in_target) == 0:
        return []
    lo, hi = in_target.min(axis=0), in_target.max(axis=0)
    mid = 0.5 * (lo + hi)
    aims = {"A": (mid[0], lo[1]), "B": (hi[0], mid[1]), "C": (mid[0], hi[1]), "D": (lo[0], mid[1])}
    return [
        (name, vertices_mm[int(np.argmin(((in_target - aim) ** 2).sum(axis=1)))])
        for name, aim in aims.items()
    ]


def _facing_up(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Wind the faces so that their normals point up (+z, the cameras' side) on average."""
    tri = vertices[faces].astype(np.float64)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return faces[:, ::-1].copy() if normals[:, 2].sum() < 0 else faces
