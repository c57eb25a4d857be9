"""Virtual templates: sections of the measured plate and its CAD target along frame lines.

A wooden forming template is cut to the hull's section at one frame; laid on the
plate it shows, by the gap under it, how far the plate is from its target there.
Here the same sections are cut from the inspection's meshes (``surface.ply`` and
the registered ``target.ply``, both in the left camera frame, mm).

Plate frame (computed from the target mesh)
------------------------------------------
origin: the target's centroid; ``normal``: the direction of least spread of the
target's vertices, oriented towards the cameras; ``across``: the in-plane
direction of strongest curvature of the target (the frame line runs along it);
``along``: ``normal x across``, the direction in which frames are stacked (the
cylinder axis for a cylinder target). Sections are the planes ``along = t`` at a
chosen spacing.

The gap at a point of a section is ``h_measured - h_target`` along ``normal``: the
same sign as the result's deviation (positive: the plate stands proud of its
target, towards the cameras). Measured along the plate's normal rather than along
the local surface normal, it differs from the normal distance by a factor
``cos(slope)`` (under 1 % for slopes below 8 degrees).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from trimesh.intersections import mesh_plane

from .artifacts.ply import read_mesh_ply

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
    """

    position_mm: float
    u_mm: np.ndarray
    target_h_mm: np.ndarray
    measured_h_mm: np.ndarray
    gap_mm: np.ndarray
    defect: int | None = None


def plate_frame(target_vertices_mm: np.ndarray) -> PlateFrame:
    """The plate axes of a target surface (module docstring).

    Parameters
    ----------
    target_vertices_mm : (V, 3) float, the registered target's vertices, left camera frame, mm.

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
    if np.abs(eigvals).max() * scale < 1e-9:  # flat: frames across the longer side
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

    Returns
    -------
    frame : PlateFrame
    sections : list of Section, in order along ``frame.along``.
    """
    if samples < 2:
        raise ValueError(f"samples: expected >= 2, got {samples}")
    frame = plate_frame(target_vertices_mm)
    lo, hi = frame.along_range_mm
    placed: list[tuple[float, int | None]] = [
        (float(p), None) for p in section_positions(frame, spacing_mm)
    ]
    for number, point in through_mm:
        pos = float((np.asarray(point, dtype=np.float64) - frame.origin_mm) @ frame.along) - lo
        if 0.0 < pos < hi - lo:
            placed.append((pos, number))
    placed.sort(key=lambda item: item[0])
    surface = trimesh.Trimesh(surface_vertices_mm, surface_faces, process=False)
    target = trimesh.Trimesh(target_vertices_mm, target_faces, process=False)
    a0, a1 = frame.across_range_mm
    u = np.linspace(a0, a1, samples)
    sections = []
    for pos, defect in placed:
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
    artifact_dir: Path, *, spacing_mm: float
) -> tuple[PlateFrame, list[Section], float]:
    """Sections of an inspection from its artifact folder (surface.ply, target.ply, result.json).

    Returns
    -------
    frame, sections, tolerance_mm
    """
    import json

    artifact_dir = Path(artifact_dir)
    document = json.loads((artifact_dir / "result.json").read_text())
    names = document.get("artifacts", {})
    surface = read_mesh_ply(artifact_dir / names.get("surface", "surface.ply"))
    target = read_mesh_ply(artifact_dir / names.get("target_surface", "target.ply"))
    frame, sections = cut_sections(
        *surface, *target, spacing_mm=spacing_mm, through_mm=_defect_points(artifact_dir)
    )
    return frame, sections, float(document["tolerance_mm"])


def _defect_points(artifact_dir: Path) -> list[tuple[int, np.ndarray]]:
    """The defects' centroids (numbered as in details.json, 1 first) in the left camera frame, mm:
    their target-frame positions moved by the registration; none without details.json."""
    import json

    path = artifact_dir / "details.json"
    if not path.is_file():
        return []
    details = json.loads(path.read_text())
    T = np.asarray(details.get("T_cam_target", np.eye(4)), dtype=np.float64)
    out = []
    for k, d in enumerate(details.get("defects", []), start=1):
        if d.get("centroid_mm") is not None:
            x, y = d["centroid_mm"]
            out.append((k, T[:3, :3] @ np.array([x, y, 0.0]) + T[:3, 3]))
    return out
