"""surface.ply (the measured surface, per-vertex deviation and colour) and target.ply (the registered target), binary PLY:
written here, and read back (any PLY triangle mesh with a deviation property) with plyfile."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np
import numpy.typing as npt
from plyfile import PlyData, PlyElementParseError, PlyHeaderParseError

from .checks import check_mask, check_positive
from .colours import default_limit_mm, deviation_colormap

#: Vertex properties of a surface PLY that may carry the signed deviation in mm, in order of
#: preference (ours first; ``quality`` is CloudCompare's and MeshLab's scalar field).
DEVIATION_PROPERTIES = ("deviation_mm", "deviation", "quality")


def write_surface_ply(
    path: str | os.PathLike[str],
    points_mm: npt.ArrayLike,
    mask: npt.ArrayLike,
    deviation_mm: npt.ArrayLike,
    *,
    max_vertices: int = 250_000,
    tolerance_mm: float | None = None,
    limit_mm: float | None = None,
) -> None:
    """Write the measured surface as a binary PLY triangle mesh with per-vertex deviation.

    The grid is subsampled by the smallest integer stride ``s`` (rows and
    columns ``0, s, 2s, ...``), searched upwards from ``sqrt(mask pixels /
    max_vertices)``, that keeps the vertex count at or under ``max_vertices``; every 2x2 cell of the subsampled grid whose four corners
    are valid gives two triangles; only vertices used by a triangle are written.

    Parameters
    ----------
    path : str or Path
    points_mm : (H, W, 3) float
        Surface points, mm, left camera frame.
    mask : (H, W) bool
        True = measured. Pixels with non-finite points are treated as not measured.
    deviation_mm : (H, W) float
        Signed deviation from the target, mm, positive towards the cameras; NaN
        allowed (no target there): stored as NaN and drawn grey.
    max_vertices : int
        Vertex budget (>= 3).
    tolerance_mm, limit_mm : float, optional
        The colour scale: ``limit_mm`` if given, else ``2 * tolerance_mm``
        (as :func:`write_deviation_png`), else the largest ``|deviation|``.

    Notes
    -----
    PLY layout (binary little endian): ``vertex`` with float32 ``x y z`` (mm,
    left camera frame), uchar ``red green blue`` (:func:`deviation_colormap`)
    and float32 ``deviation_mm``; ``face`` with ``vertex_indices`` (uchar count,
    int32 indices). Faces are wound so that their normals point towards the
    cameras (-z side), like the surface normals of the pipeline. The colour
    scale is written in a header comment.

    Raises
    ------
    ValueError
        Wrong shapes or dtypes, a bad budget or scale, or no 2x2 cell with
        four valid corners at the chosen stride.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points_mm: expected shape (H, W, 3), got {pts.shape}")
    h, w = pts.shape[:2]
    mask = check_mask(mask, (h, w))
    dev = np.asarray(deviation_mm, dtype=np.float64)
    if dev.shape != (h, w):
        raise ValueError(
            f"deviation_mm: expected shape {(h, w)} to match points_mm, got {dev.shape}"
        )
    if not (isinstance(max_vertices, (int, np.integer)) and max_vertices >= 3):
        raise ValueError(f"max_vertices: expected an integer >= 3, got {max_vertices!r}")
    if limit_mm is None:
        if tolerance_mm is not None:
            check_positive("tolerance_mm", tolerance_mm)
            limit_mm = default_limit_mm(tolerance_mm)
        else:
            finite = np.abs(dev[mask & np.isfinite(dev) & np.isfinite(pts).all(axis=-1)])
            limit_mm = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    check_positive("limit_mm", limit_mm)

    valid = np.empty((h, w), bool)  # in the mask and finite
    _valid_points(pts, mask, valid)
    stride = max(1, int(math.sqrt(np.count_nonzero(mask) / max_vertices)))
    while True:
        sub = valid[::stride, ::stride]
        cell = sub[:-1, :-1] & sub[:-1, 1:] & sub[1:, :-1] & sub[1:, 1:]
        used = np.zeros_like(sub)
        used[:-1, :-1] |= cell
        used[:-1, 1:] |= cell
        used[1:, :-1] |= cell
        used[1:, 1:] |= cell
        if np.count_nonzero(used) <= max_vertices:
            break
        stride += 1
    if not cell.any():
        raise ValueError(
            f"mask: no 2x2 cell with four valid corners at stride {stride} "
            f"({np.count_nonzero(sub)} valid points of {sub.shape[1]}x{sub.shape[0]} at that stride): nothing to mesh"
        )

    vertices = np.empty((np.count_nonzero(used), 3), np.float32)
    vdev = np.empty(len(vertices), np.float64)
    faces = np.empty((2 * np.count_nonzero(cell), 3), np.int32)
    _mesh(pts[::stride, ::stride], dev[::stride, ::stride], used, cell, vertices, vdev, faces)
    colours = deviation_colormap(vdev, limit_mm=limit_mm)
    comments = [
        "plate-inspect measured surface: mm, left camera frame (x right, y down, z forward)",
        f"grid stride {stride} px; deviation_mm signed, positive towards the cameras",
        f"vertex colour: blue-white-red saturated at +/- {limit_mm:g} mm, grey = no deviation",
    ]
    _write_ply(path, vertices, faces, comments=comments, colours=colours, deviation=vdev)


@numba.njit(nogil=True, cache=True)
def _valid_points(
    pts: npt.NDArray[np.float64], mask: npt.NDArray[np.bool_], out: npt.NDArray[np.bool_]
) -> None:  # pragma: no cover - compiled
    """``out`` (H, W) = the points (H, W, 3) in ``mask`` whose three coordinates are finite."""
    h, w = mask.shape
    for i in range(h):
        for j in range(w):
            out[i, j] = (
                mask[i, j]
                and np.isfinite(pts[i, j, 0])
                and np.isfinite(pts[i, j, 1])
                and np.isfinite(pts[i, j, 2])
            )


@numba.njit(nogil=True, cache=True)
def _mesh(
    pts: npt.NDArray[np.float64],
    dev: npt.NDArray[np.float64],
    used: npt.NDArray[np.bool_],
    cell: npt.NDArray[np.bool_],
    vertices: npt.NDArray[np.float32],
    vdev: npt.NDArray[np.float64],
    faces: npt.NDArray[np.int32],
) -> None:  # pragma: no cover - compiled
    """The mesh of the subsampled grid ``pts`` (h, w, 3) (``dev`` (h, w) its deviations): the ``used``
    points in row-major order into ``vertices`` (float32) and ``vdev``, and two faces per ``cell``
    (h - 1, w - 1), row-major, into ``faces``: corners a b / c d give (a, c, b) and (b, c, d), whose
    normal is -z (towards the cameras) with x along columns and y along rows."""
    h, w = used.shape
    index = np.empty((h, w), np.int64)
    n = 0
    for i in range(h):
        for j in range(w):
            if used[i, j]:
                index[i, j] = n
                vertices[n, 0] = pts[i, j, 0]
                vertices[n, 1] = pts[i, j, 1]
                vertices[n, 2] = pts[i, j, 2]
                vdev[n] = dev[i, j]
                n += 1
    f = 0
    for i in range(h - 1):
        for j in range(w - 1):
            if cell[i, j]:
                a, b, c, d = index[i, j], index[i, j + 1], index[i + 1, j], index[i + 1, j + 1]
                faces[f, 0], faces[f, 1], faces[f, 2] = a, c, b
                faces[f + 1, 0], faces[f + 1, 1], faces[f + 1, 2] = b, c, d
                f += 2


def write_target_ply(
    path: str | os.PathLike[str],
    vertices_mm: npt.ArrayLike,
    faces: npt.ArrayLike,
    T_cam_target: npt.ArrayLike,
) -> None:
    """Write the CAD target, moved into the left camera frame, as a binary PLY mesh.

    Parameters
    ----------
    path : str or Path
    vertices_mm : (V, 3) float
        Target vertices in the target's own frame, mm.
    faces : (F, 3) int
        Triangles, indices into ``vertices_mm``.
    T_cam_target : (4, 4) float
        Rigid transform mapping target-frame points into the left camera frame:
        ``X_cam = T[:3, :3] @ X_target + T[:3, 3]`` (mm).

    Raises
    ------
    ValueError
        Wrong shapes, non-finite values, out-of-range face indices, or a
        transform that is not rigid (rotation + translation).
    """
    verts = np.asarray(vertices_mm, dtype=np.float64)
    if verts.ndim != 2 or verts.shape[1] != 3 or verts.shape[0] == 0:
        raise ValueError(f"vertices_mm: expected shape (V, 3) with V > 0, got {verts.shape}")
    if not np.all(np.isfinite(verts)):
        raise ValueError("vertices_mm: expected finite coordinates")
    faces = np.asarray(faces)
    if (
        faces.ndim != 2
        or faces.shape[1] != 3
        or faces.shape[0] == 0
        or not np.issubdtype(faces.dtype, np.integer)
    ):
        raise ValueError(
            f"faces: expected an integer array of shape (F, 3) with F > 0, got {faces.dtype} {faces.shape}"
        )
    if faces.min() < 0 or faces.max() >= verts.shape[0]:
        raise ValueError(
            f"faces: expected indices in [0, {verts.shape[0] - 1}], got [{faces.min()}, {faces.max()}]"
        )
    T = np.asarray(T_cam_target, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_cam_target: expected a finite (4, 4) matrix, got shape {T.shape}")
    R = T[:3, :3]
    if (
        not np.allclose(T[3], [0, 0, 0, 1])
        or not np.allclose(R @ R.T, np.eye(3), atol=1e-6)
        or np.linalg.det(R) <= 0
    ):
        raise ValueError(
            "T_cam_target: expected a rigid transform [[R, t], [0, 0, 0, 1]] with R a rotation"
        )
    cam = verts @ R.T + T[:3, 3]
    comments = ["plate-inspect CAD target registered to the measurement: mm, left camera frame"]
    _write_ply(path, cam, faces, comments=comments)


def _write_ply(
    path: str | os.PathLike[str],
    vertices: npt.NDArray[np.floating[Any]],
    faces: npt.NDArray[Any],
    *,
    comments: Sequence[str],
    colours: npt.NDArray[np.uint8] | None = None,
    deviation: npt.NDArray[np.float64] | None = None,
) -> None:
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    props = ["property float x", "property float y", "property float z"]
    if colours is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    if deviation is not None:
        fields += [("deviation_mm", "<f4")]
        props += ["property float deviation_mm"]
    vdata = np.empty(len(vertices), dtype=fields)
    vdata["x"], vdata["y"], vdata["z"] = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    if colours is not None:
        vdata["red"], vdata["green"], vdata["blue"] = colours[:, 0], colours[:, 1], colours[:, 2]
    if deviation is not None:
        vdata["deviation_mm"] = deviation
    fdata = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    fdata["n"] = 3
    fdata["v"] = faces
    header = "\n".join(
        [
            "ply",
            "format binary_little_endian 1.0",
            *(f"comment {c}" for c in comments),
            f"element vertex {len(vertices)}",
            *props,
            f"element face {len(faces)}",
            "property list uchar int vertex_indices",
            "end_header",
        ]
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii") + b"\n")
        fh.write(vdata.data)  # the arrays' own buffers (contiguous): no copy into bytes
        fh.write(fdata.data)


def read_mesh_ply(
    path: str | os.PathLike[str],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """Read a PLY triangle mesh (surface.ply, target.ply): vertices (V, 3) float64 mm, faces (F, 3) int64.

    Raises
    ------
    ValueError
        Not a PLY, no vertex or face element, or faces that are not triangles (naming the file).
    """
    _, vertices, faces = _read_ply(path)
    return vertices, faces


def read_surface_ply(
    path: str | os.PathLike[str],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Read a surface PLY: the pipeline's surface.ply, or any triangle mesh with a deviation property.

    Returns
    -------
    vertices : (V, 3) float64, mm; faces : (F, 3) int64; deviation_mm : (V,) float64, the vertex
    property named first among :data:`DEVIATION_PROPERTIES`.

    Raises
    ------
    ValueError
        As :func:`read_mesh_ply`, and a mesh without a deviation property.
    """
    vertex, vertices, faces = _read_ply(path)
    names = vertex.dtype.names or ()
    found = next((n for n in DEVIATION_PROPERTIES if n in names), None)
    if found is None:
        name = os.path.basename(os.fspath(path))
        raise ValueError(
            f"{name}: vertex: expected a property among {DEVIATION_PROPERTIES}, got {names}"
        )
    return vertices, faces, np.asarray(vertex[found], dtype=np.float64)


def _read_ply(
    path: str | os.PathLike[str],
) -> tuple[npt.NDArray[Any], npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """The vertex element's records, the vertices and the triangles of a PLY (plyfile).

    A binary PLY whose faces are all triangles (every PLY the pipeline writes) is read as one
    array (plyfile's ``known_list_len``, which checks every face's length); any other falls back
    to plyfile's face-by-face read (about 10 s per million faces).
    """
    name = os.path.basename(os.fspath(path))
    try:
        try:
            ply = PlyData.read(os.fspath(path), known_list_len=_TRIANGLES)
        except PlyElementParseError:
            ply = PlyData.read(os.fspath(path))
    except (PlyHeaderParseError, PlyElementParseError) as err:
        raise ValueError(f"{name}: not a readable PLY: {err}") from err
    elements = {e.name: e for e in ply.elements}
    if "vertex" not in elements:
        raise ValueError(f"{name}: vertex: expected a vertex element, got none")
    vertex: npt.NDArray[Any] = np.array(elements["vertex"].data)  # a copy: no mmap kept open
    face = elements.get("face")
    if face is None or len(face.data) == 0:
        raise ValueError(f"{name}: face: expected a triangle mesh, got no faces")
    lists = face.data[face.data.dtype.names[0]]
    if lists.dtype != object:  # read as one (F, 3) array: lengths checked by plyfile
        triangles = np.array(lists, dtype=np.int64)
    elif any(len(f) != 3 for f in lists):
        raise ValueError(f"{name}: face: expected triangles only")
    else:
        triangles = np.vstack(lists).astype(np.int64)
    vertices = np.column_stack([vertex["x"], vertex["y"], vertex["z"]]).astype(np.float64)
    return vertex, vertices, triangles


#: plyfile's ``known_list_len`` for a face element of triangles (either usual property name).
_TRIANGLES = {"face": {"vertex_indices": 3, "vertex_index": 3}}
