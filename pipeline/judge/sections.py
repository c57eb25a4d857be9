"""Virtual templates: sections of the measured plate and its CAD target along frame lines.

A wooden forming template is cut to the hull's section at one frame; laid on the
plate it shows, by the gap under it, how far the plate is from its target there.
Here the same sections are cut from the inspection's meshes (``surface.ply`` and
the registered ``target.ply``, both in the left camera frame, mm).

Plate frame (computed from the target mesh)
------------------------------------------
origin: the target's centroid; ``normal``: the direction of least spread of the
target's vertices, oriented towards the cameras; ``across``: the direction the frame
line runs along; ``along``: ``normal x across``, the direction in which frames are
stacked (the cylinder axis for a cylinder target). Sections are the planes
``along = t`` at a chosen spacing.

``across`` follows the target's own axes when they are known (the registration's
``T_cam_target``, as for every inspection): of the target's ``x`` and ``y`` (its first
and second side), the one the target bends more along, projected on the plate; ``x``
when they bend alike (a sphere, a symmetric saddle), so that frames run square to the
plate's edges as a yard's frame lines do, never diagonally. Without the axes it is
the in-plane direction of strongest curvature of the target.

The gap at a point of a section is ``h_measured - h_target`` along ``normal``: the
same sign as the result's deviation (positive: the plate stands proud of its
target, towards the cameras). Measured along the plate's normal rather than along
the local surface normal, it differs from the normal distance by a factor
``cos(slope)`` (under 1 % for slopes below 8 degrees).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from trimesh.intersections import mesh_plane

from pipeline.artifacts.ply import read_mesh_ply
from pipeline.judge.plate_map import to_camera_frame

#: Samples along each section.
SAMPLES = 241


@dataclass(frozen=True)
class PlateFrame:
    """Orthonormal plate axes in the left camera frame (see the module docstring).

    Attributes
    ----------
    origin_mm : (3,) float, mm.  across, along, normal : (3,) float unit vectors.
    along_range_mm : (2,) float, extent of the target along ``along``, mm from ``origin``.
    across_range_mm : (2,) float, extent of the target along ``across``, mm from ``origin``.
    """

    origin_mm: np.ndarray
    across: np.ndarray
    along: np.ndarray
    normal: np.ndarray
    along_range_mm: tuple[float, float]
    across_range_mm: tuple[float, float]

    def line_mm(self, position_mm: float) -> np.ndarray:
        """(2, 3) ends of the frame line at ``position_mm`` (from the first edge), camera frame, mm."""
        centre = self.origin_mm + (self.along_range_mm[0] + position_mm) * self.along
        a0, a1 = self.across_range_mm
        return np.stack([centre + a0 * self.across, centre + a1 * self.across])


@dataclass(frozen=True)
class Section:
    """One virtual template: the target and the plate cut by the plane ``along = position``.

    Attributes
    ----------
    position_mm : float, distance of the section from the target's first edge along ``along``, mm.
    u_mm : (N,) float, distance along ``across`` from the target's first edge, mm.
    target_h_mm, measured_h_mm : (N,) float, height along ``normal`` (towards the cameras), mm;
        NaN where the mesh does not reach.
    gap_mm : (N,) float, ``measured_h_mm - target_h_mm`` (deviation sign), mm; NaN where either is.
    defect : int or None, the defect (its number) this frame was placed through, if any.
    chosen : bool, the frame was placed through a point the operator chose.
    """

    position_mm: float
    u_mm: np.ndarray
    target_h_mm: np.ndarray
    measured_h_mm: np.ndarray
    gap_mm: np.ndarray
    defect: int | None = None
    chosen: bool = False


def plate_frame(
    target_vertices_mm: np.ndarray, target_axes: np.ndarray | None = None
) -> PlateFrame:
    """The plate axes of a target surface (module docstring).

    Parameters
    ----------
    target_vertices_mm : (V, 3) float, the registered target's vertices, left camera frame, mm.
    target_axes : (3, 3) float or None, the target frame's rotation into the camera frame
        (``T_cam_target[:3, :3]``: columns are its x, y and z axes); frames then run along
        the target's x or y (module docstring).

    Raises
    ------
    ValueError
        Fewer than 6 vertices, or not an (V, 3) array of finite numbers.
    """
    v = np.asarray(target_vertices_mm, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 6:
        raise ValueError(f"target_vertices_mm: expected shape (V, 3) with V >= 6, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("target_vertices_mm: expected finite coordinates, got NaN or inf")
    origin = v.mean(axis=0)
    _, _, vt = np.linalg.svd(v - origin, full_matrices=False)
    e1, e2, normal = vt
    if normal @ origin > 0:  # the cameras are at the origin of the camera frame
        normal = -normal
    e2 = np.cross(normal, e1)
    d = v - origin
    x, y, h = d @ e1, d @ e2, d @ normal
    scale = max(np.abs(x).max(), np.abs(y).max())
    xs, ys = x / scale, y / scale
    design = np.stack([xs**2, xs * ys, ys**2, xs, ys, np.ones_like(xs)], axis=1)
    a, b, c = np.linalg.lstsq(design, h, rcond=None)[0][:3]
    hessian = np.array([[2 * a, b], [b, 2 * c]]) / scale**2
    eigvals, eigvecs = np.linalg.eigh(hessian)
    if target_axes is not None:
        k = _frame_line_direction(np.asarray(target_axes, dtype=np.float64), e1, e2, hessian)
    elif np.abs(eigvals).max() * scale < 1e-9:  # flat: frames across the longer side
        k = np.array([1.0, 0.0])
    else:
        k = eigvecs[:, np.argmax(np.abs(eigvals))]
    across = k[0] * e1 + k[1] * e2
    across /= np.linalg.norm(across)
    along = np.cross(normal, across)
    pa, pb = d @ across, d @ along
    return PlateFrame(
        origin_mm=origin,
        across=across,
        along=along,
        normal=normal,
        along_range_mm=(float(pb.min()), float(pb.max())),
        across_range_mm=(float(pa.min()), float(pa.max())),
    )


#: The target bends "alike" along x and y when their curvatures' magnitudes differ by less than this
#: fraction of the larger: frames then run along x.
_ALIKE = 0.15


def _frame_line_direction(
    axes: np.ndarray, e1: np.ndarray, e2: np.ndarray, hessian: np.ndarray
) -> np.ndarray:
    """The frame line's direction in the plate's (e1, e2) plane: the target's x or y axis (module
    docstring), whichever it bends more along; x when they bend alike or the plate is flat."""
    if axes.shape != (3, 3) or not np.all(np.isfinite(axes)):
        raise ValueError(f"target_axes: expected a finite (3, 3) rotation, got shape {axes.shape}")
    candidates = []
    for column in (0, 1):
        d = np.array([axes[:, column] @ e1, axes[:, column] @ e2])
        norm = float(np.linalg.norm(d))
        if norm < 1e-6:  # this axis stands on the plate: the other one is the choice
            continue
        d /= norm
        candidates.append((abs(float(d @ hessian @ d)), d))
    if not candidates:
        return np.array([1.0, 0.0])
    if len(candidates) == 2 and candidates[1][0] * (1 - _ALIKE) > candidates[0][0]:
        return candidates[1][1]
    return candidates[0][1]


def section_positions(frame: PlateFrame, spacing_mm: float) -> np.ndarray:
    """Frame positions at ``spacing_mm``, centred on the plate, mm from its first edge along ``along``.

    Raises
    ------
    ValueError
        ``spacing_mm`` not positive, or so small it would give more than 200 sections.
    """
    if not (np.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm: expected a positive number, got {spacing_mm}")
    lo, hi = frame.along_range_mm
    length = hi - lo
    if length / spacing_mm > 200:
        raise ValueError(
            f"spacing_mm: expected at most 200 sections over {length:.0f} mm, got spacing {spacing_mm}"
        )
    # Keep sections off the very edges (a plane through the boundary cuts a ragged line).
    margin = 0.02 * length
    n_half = int(np.floor((length / 2 - margin) / spacing_mm))
    offsets = spacing_mm * np.arange(-n_half, n_half + 1)
    return length / 2 + offsets


def cut_sections(
    surface_vertices_mm: np.ndarray,
    surface_faces: np.ndarray,
    target_vertices_mm: np.ndarray,
    target_faces: np.ndarray,
    *,
    spacing_mm: float,
    samples: int = SAMPLES,
    through_mm: Sequence[tuple[int, np.ndarray]] = (),
    chosen_mm: Sequence[np.ndarray] = (),
    target_axes: np.ndarray | None = None,
) -> tuple[PlateFrame, list[Section]]:
    """Cut the measured and the target surfaces along frame lines.

    Parameters
    ----------
    surface_vertices_mm : (V, 3) float, measured surface, left camera frame, mm.
    surface_faces : (F, 3) int.
    target_vertices_mm : (W, 3) float, registered target surface, same frame, mm.
    target_faces : (G, 3) int.
    spacing_mm : float > 0, distance between frames, mm.
    samples : int >= 2, points per section.
    through_mm : sequence of (number, (3,) point), one more frame through each point (left camera
        frame, mm; a defect's centroid), labelled with its number; points off the plate are skipped.
    chosen_mm : sequence of (3,) points, one more frame through each (a point the operator chose on
        the map; left camera frame, mm), marked ``chosen``; points off the plate are skipped.
    target_axes : (3, 3) float or None, see :func:`plate_frame`.

    Returns
    -------
    frame : PlateFrame
    sections : list of Section, in order along ``frame.along``.
    """
    if samples < 2:
        raise ValueError(f"samples: expected >= 2, got {samples}")
    frame = plate_frame(target_vertices_mm, target_axes)
    lo, hi = frame.along_range_mm
    placed: list[tuple[float, int | None, bool]] = [
        (float(p), None, False) for p in section_positions(frame, spacing_mm)
    ]
    marked: list[tuple[int | None, np.ndarray, bool]]
    marked = [(number, point, False) for number, point in through_mm]
    marked += [(None, point, True) for point in chosen_mm]
    for number, point, chosen in marked:
        pos = float((np.asarray(point, dtype=np.float64) - frame.origin_mm) @ frame.along) - lo
        if 0.0 < pos < hi - lo:
            placed.append((pos, number, chosen))
    placed.sort(key=lambda item: item[0])
    surface = trimesh.Trimesh(surface_vertices_mm, surface_faces, process=False)
    target = trimesh.Trimesh(target_vertices_mm, target_faces, process=False)
    a0, a1 = frame.across_range_mm
    u = np.linspace(a0, a1, samples)
    sections = []
    for pos, defect, chosen in placed:
        origin = frame.origin_mm + (frame.along_range_mm[0] + pos) * frame.along
        h_target = _profile(target, origin, frame, u)
        h_measured = _profile(surface, origin, frame, u)
        sections.append(
            Section(
                position_mm=float(pos),
                u_mm=u - a0,
                target_h_mm=h_target,
                measured_h_mm=h_measured,
                gap_mm=h_measured - h_target,
                defect=defect,
                chosen=chosen,
            )
        )
    return frame, sections


def _profile(
    mesh: trimesh.Trimesh, origin: np.ndarray, frame: PlateFrame, u: np.ndarray
) -> np.ndarray:
    """Height along ``frame.normal`` of the mesh's cut by the plane through ``origin`` normal to ``along``.

    NaN where the cut has no segment within one sample step of ``u``.
    """
    segments = mesh_plane(  # type: ignore[no-untyped-call]  # trimesh's own annotations stop here
        mesh, plane_normal=frame.along, plane_origin=origin
    )
    out = np.full(u.shape, np.nan)
    if len(segments) == 0:
        return out
    d = segments - frame.origin_mm  # (n, 2, 3)
    su, sh = d @ frame.across, d @ frame.normal  # (n, 2)
    lo, hi = np.minimum(su[:, 0], su[:, 1]), np.maximum(su[:, 0], su[:, 1])
    # Each segment covers [lo, hi]: interpolate inside it (a height field has one segment per u).
    order = np.argsort(lo)
    lo, hi, su, sh = lo[order], hi[order], su[order], sh[order]
    idx = np.searchsorted(lo, u, side="right") - 1
    inside = (idx >= 0) & (u <= hi[np.clip(idx, 0, None)] + 1e-9)
    k = idx[inside]
    span = su[k, 1] - su[k, 0]
    t = np.divide(u[inside] - su[k, 0], span, out=np.zeros_like(span), where=np.abs(span) > 1e-12)
    out[inside] = sh[k, 0] + t * (sh[k, 1] - sh[k, 0])
    return out


def load_sections(
    artifact_dir: Path, *, spacing_mm: float, chosen_xy_mm: Sequence[tuple[float, float]] = ()
) -> tuple[PlateFrame, list[Section], float]:
    """Sections of an inspection from its artifact folder (surface.ply, target.ply, result.json,
    details.json): frames at ``spacing_mm``, one through each defect and one through each chosen
    point (``(x, y)`` in the target's frame, mm: where the operator clicked the plate map).

    Returns
    -------
    frame, sections, tolerance_mm
    """
    artifact_dir = Path(artifact_dir)
    document = json.loads((artifact_dir / "result.json").read_text())
    names = document.get("artifacts", {})
    surface = read_mesh_ply(artifact_dir / names.get("surface", "surface.ply"))
    target = read_mesh_ply(artifact_dir / names.get("target_surface", "target.ply"))
    T, defects = _registration_and_defects(artifact_dir)
    chosen = [to_camera_frame([x, y, 0.0], T)[0] for x, y in chosen_xy_mm] if T is not None else []
    frame, sections = cut_sections(
        *surface,
        *target,
        spacing_mm=spacing_mm,
        through_mm=defects,
        chosen_mm=chosen,
        target_axes=None if T is None else T[:3, :3],
    )
    return frame, sections, float(document["tolerance_mm"])


def _registration_and_defects(
    artifact_dir: Path,
) -> tuple[np.ndarray | None, list[tuple[int, np.ndarray]]]:
    """details.json's ``T_cam_target`` and the defects' centroids (numbered as there, 1 first) in
    the left camera frame, mm (their target-frame positions moved by the registration); ``None``
    and no defects without details.json."""
    path = artifact_dir / "details.json"
    if not path.is_file():
        return None, []
    details = json.loads(path.read_text())
    T = np.asarray(details.get("T_cam_target", np.eye(4)), dtype=np.float64)
    out = []
    for k, d in enumerate(details.get("defects", []), start=1):
        if d.get("centroid_mm") is not None:
            x, y = d["centroid_mm"]
            out.append((k, to_camera_frame([x, y, 0.0], T)[0]))
    return T, out
