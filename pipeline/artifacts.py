"""Result artifacts of an inspection: the measured surface mesh, the deviation map, normals, depth; their file names.

All coordinates are millimetres in the left camera frame (OpenCV: x right,
y down, z forward into the scene). Deviation is signed: positive where the
measured surface lies on the cameras' side of the target ("above", red),
negative where it lies away from the cameras ("below", blue).

One colour map serves the PNG, the PLY vertex colours and the 3D viewer
(``app/viewer.py`` uses the same stops): a diverging blue - white - red scale
saturated at ``+/- limit_mm``. With the default ``limit_mm = 2 * tolerance_mm``
the light blue and orange stops sit exactly at ``-/+ tolerance_mm``, so
everything out of tolerance is drawn in the darker half of the scale.
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np

#: File names of an inspection's artifacts in its output folder, keyed as ``plate-result/1``'s ``artifacts``.
ARTIFACT_FILES = {
    "surface": "surface.ply",
    "target_surface": "target.ply",
    "deviation_map": "deviation.png",
    "normals": "normals.png",
    "depth": "depth.npy",
    "details": "details.json",
}
#: File name of the ``plate-result/1`` document beside them.
RESULT_FILE = "result.json"

#: Colour stops (RGB) at t = -1, -1/2, 0, 1/2, 1 of ``deviation / limit_mm``; the viewer uses the same.
COLOUR_STOPS = ((33, 102, 172), (146, 197, 222), (247, 247, 247), (244, 165, 130), (178, 24, 43))
_STOP_T = (-1.0, -0.5, 0.0, 0.5, 1.0)
#: RGB of pixels/vertices without a deviation (NaN or outside the mask).
NO_DATA_RGB = (128, 128, 128)
#: Minimum height in pixels of the deviation PNG (small maps are enlarged by an integer factor).
MIN_PNG_HEIGHT = 540
#: Tallest map drawn (px); a taller one is sampled down by a whole stride.
MAX_PNG_HEIGHT = 1080

#: Widest enlargement of a small map (px), so thin maps are not blown up without bound.
MAX_PNG_WIDTH = 4000


# =========================================================================== colour map


def deviation_colormap(deviation_mm, *, limit_mm: float) -> np.ndarray:
    """Colour signed deviations on a diverging blue - white - red scale.

    Parameters
    ----------
    deviation_mm : (H, W) float array (any shape works), mm, positive towards the cameras.
    limit_mm : float > 0
        Deviation drawn in full colour; larger magnitudes saturate at the end colours.

    Returns
    -------
    (H, W, 3) uint8 RGB
        ``(33, 102, 172)`` dark blue at ``-limit_mm`` (below the target, away from
        the cameras), ``(247, 247, 247)`` near white at 0, ``(178, 24, 43)`` dark
        red at ``+limit_mm``; linear in RGB between the stops of
        :data:`COLOUR_STOPS`. NaN -> neutral grey ``(128, 128, 128)``.

    Raises
    ------
    ValueError
        ``limit_mm`` not a positive finite number; infinite deviations.
    """
    dev = np.asarray(deviation_mm, dtype=np.float64)
    if not (isinstance(limit_mm, (int, float, np.floating, np.integer)) and math.isfinite(limit_mm) and limit_mm > 0):
        raise ValueError(f"limit_mm: expected a positive finite number of mm, got {limit_mm!r}")
    if np.isinf(dev).any():
        raise ValueError(f"deviation_mm: expected finite values or NaN, got {int(np.isinf(dev).sum())} infinite")
    # a lookup table of _LUT_SIZE steps over [-limit, +limit] (finer than 8-bit colour can show), last entry = no data
    index = np.rint((dev / float(limit_mm) + 1.0) * (0.5 * (_LUT_SIZE - 1)))
    np.clip(index, 0, _LUT_SIZE - 1, out=index)
    index[np.isnan(dev)] = _LUT_SIZE
    return _COLOUR_LUT[index.astype(np.intp)]


def _colour_lut(size: int) -> np.ndarray:
    t = np.linspace(-1.0, 1.0, size)
    stops = np.asarray(COLOUR_STOPS, dtype=np.float64)
    rgb = np.stack([np.interp(t, _STOP_T, stops[:, k]) for k in range(3)], axis=-1)
    return np.rint(np.vstack([rgb, NO_DATA_RGB])).astype(np.uint8)


_LUT_SIZE = 2049
_COLOUR_LUT = _colour_lut(_LUT_SIZE)


def default_limit_mm(tolerance_mm: float) -> float:
    """The colour scale of a plate judged against ``tolerance_mm``: ``2 * tolerance_mm``."""
    return 2.0 * float(tolerance_mm)


# =========================================================================== surface mesh


def write_surface_ply(
    path,
    points_mm,
    mask,
    deviation_mm,
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
    mask = _check_mask(mask, (h, w))
    dev = np.asarray(deviation_mm, dtype=np.float64)
    if dev.shape != (h, w):
        raise ValueError(f"deviation_mm: expected shape {(h, w)} to match points_mm, got {dev.shape}")
    if not (isinstance(max_vertices, (int, np.integer)) and max_vertices >= 3):
        raise ValueError(f"max_vertices: expected an integer >= 3, got {max_vertices!r}")
    if limit_mm is None:
        if tolerance_mm is not None:
            _check_positive("tolerance_mm", tolerance_mm)
            limit_mm = default_limit_mm(tolerance_mm)
        else:
            finite = np.abs(dev[mask & np.isfinite(dev) & np.isfinite(pts).all(axis=-1)])
            limit_mm = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    _check_positive("limit_mm", limit_mm)

    def valid_at(stride: int) -> np.ndarray:
        """The grid points at this stride that are in the mask and finite (checked on those only)."""
        return mask[::stride, ::stride] & np.isfinite(pts[::stride, ::stride]).all(axis=-1)

    stride = max(1, int(math.sqrt(np.count_nonzero(mask) / max_vertices)))
    while True:
        sub = valid_at(stride)
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

    index = np.full(sub.shape, -1, dtype=np.int64)
    index[used] = np.arange(np.count_nonzero(used))
    a, b = index[:-1, :-1][cell], index[:-1, 1:][cell]
    c, d = index[1:, :-1][cell], index[1:, 1:][cell]
    # (a, c, b) and (b, c, d): with x along columns and y along rows, the normal is -z (towards the cameras).
    faces = np.stack([np.stack([a, c, b], axis=1), np.stack([b, c, d], axis=1)], axis=1).reshape(-1, 3)

    vertices = pts[::stride, ::stride][used]
    vdev = dev[::stride, ::stride][used]
    colours = deviation_colormap(vdev, limit_mm=limit_mm)
    comments = [
        "plate-inspect measured surface: mm, left camera frame (x right, y down, z forward)",
        f"grid stride {stride} px; deviation_mm signed, positive towards the cameras",
        f"vertex colour: blue-white-red saturated at +/- {limit_mm:g} mm, grey = no deviation",
    ]
    _write_ply(path, vertices, faces, comments=comments, colours=colours, deviation=vdev)


def write_target_ply(path, vertices_mm, faces, T_cam_target) -> None:
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
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(
            f"faces: expected an integer array of shape (F, 3) with F > 0, got {faces.dtype} {faces.shape}"
        )
    if faces.min() < 0 or faces.max() >= verts.shape[0]:
        raise ValueError(f"faces: expected indices in [0, {verts.shape[0] - 1}], got [{faces.min()}, {faces.max()}]")
    T = np.asarray(T_cam_target, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_cam_target: expected a finite (4, 4) matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise ValueError("T_cam_target: expected a rigid transform [[R, t], [0, 0, 0, 1]] with R a rotation")
    cam = verts @ R.T + T[:3, 3]
    comments = ["plate-inspect CAD target registered to the measurement: mm, left camera frame"]
    _write_ply(path, cam, faces, comments=comments)


def _write_ply(path, vertices, faces, *, comments, colours=None, deviation=None) -> None:
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
        ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments)]
        + [f"element vertex {len(vertices)}", *props]
        + [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii") + b"\n")
        fh.write(vdata.tobytes())
        fh.write(fdata.tobytes())


# =========================================================================== deviation map


def write_deviation_png(path, deviation_mm, mask, *, tolerance_mm: float, limit_mm: float | None = None) -> None:
    """Write the deviation map as an RGB PNG with a scale bar in mm and the tolerance marked.

    Parameters
    ----------
    path : str or Path
    deviation_mm : (H, W) float
        Signed deviation, mm, positive towards the cameras (red), negative away (blue).
    mask : (H, W) bool
        True = measured; outside it (and at NaN) the map is grey ``(128, 128, 128)``.
    tolerance_mm : float > 0
        Marked on the scale bar with heavy lines and "tol" labels.
    limit_mm : float > 0, optional
        Colour saturation, default ``2 * tolerance_mm`` (then ``+/- tolerance``
        falls on the light blue / orange stops).

    Notes
    -----
    A map taller than ``MAX_PNG_HEIGHT`` (1080) px is first sampled down by the
    smallest whole stride that fits (every ``s``-th row and column: the figure is for
    the screen; the full-resolution deviation is in ``surface.ply`` and can be
    recomputed from ``depth.npy``).

    Layout: the map at the top left, enlarged by the integer factor
    ``k = max(1, min(ceil(540 / H), floor(4000 / W)))`` (nearest neighbour,
    so map pixel ``[r, c]`` covers ``[r*k:(r+1)*k, c*k:(c+1)*k]``); a white
    panel on its right with the vertical colour bar (``+limit`` at the top),
    tick labels in mm, the tolerance marks and a legend. Canvas height is
    ``max(k * H, 540)``; text is about 1/40 of it high (>= 14 px), so the
    figure stays readable when shown scaled to 1920x1080.

    Raises
    ------
    ValueError
        Wrong shapes, non-positive or non-finite tolerance or limit.
    OSError
        The file cannot be written.
    """
    dev = np.asarray(deviation_mm, dtype=np.float64)
    if dev.ndim != 2:
        raise ValueError(f"deviation_mm: expected shape (H, W), got {dev.shape}")
    mask = _check_mask(mask, dev.shape)
    _check_positive("tolerance_mm", tolerance_mm)
    limit = default_limit_mm(tolerance_mm) if limit_mm is None else limit_mm
    _check_positive("limit_mm", limit)
    # a map taller than a screen is shown reduced anyway: sample it down by a whole stride
    stride = math.ceil(dev.shape[0] / MAX_PNG_HEIGHT)
    if stride > 1:
        dev, mask = dev[::stride, ::stride], mask[::stride, ::stride]
    h, w = dev.shape

    rgb = deviation_colormap(np.where(mask, dev, np.nan), limit_mm=limit)
    k = max(1, min(math.ceil(MIN_PNG_HEIGHT / h), MAX_PNG_WIDTH // w))
    if k > 1:
        rgb = np.repeat(np.repeat(rgb, k, axis=0), k, axis=1)
    height = max(rgb.shape[0], MIN_PNG_HEIGHT)
    panel = _scale_panel(height, limit_mm=float(limit), tolerance_mm=float(tolerance_mm))
    canvas = np.full((height, rgb.shape[1] + panel.shape[1], 3), 255, dtype=np.uint8)
    canvas[: rgb.shape[0], : rgb.shape[1]] = rgb
    canvas[:, rgb.shape[1] :] = panel
    _imwrite(path, canvas)


def _scale_panel(height: int, *, limit_mm: float, tolerance_mm: float) -> np.ndarray:
    """(height, width, 3) uint8 RGB: colour bar, ticks in mm, tolerance marks, legend."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    text_px = max(14, round(height / 40))
    scale = text_px / 22.0  # FONT_HERSHEY_SIMPLEX capitals are ~22 px high at scale 1
    thick = max(1, round(scale * 1.3))
    margin = text_px
    bar_w = 2 * text_px
    top, bottom = 3 * text_px, height - 7 * text_px
    decimals = 2 if limit_mm < 1 else 1

    ticks = {0.0: "0", limit_mm: f"{limit_mm:+.{decimals}f}", -limit_mm: f"{-limit_mm:+.{decimals}f}"}
    if abs(limit_mm / 2 - tolerance_mm) > 0.1 * limit_mm:
        ticks[limit_mm / 2] = f"{limit_mm / 2:+.{decimals}f}"
        ticks[-limit_mm / 2] = f"{-limit_mm / 2:+.{decimals}f}"
    tol_in = tolerance_mm <= limit_mm
    if tol_in:
        ticks[tolerance_mm] = f"{tolerance_mm:+.{decimals}f} tol"
        ticks[-tolerance_mm] = f"{-tolerance_mm:+.{decimals}f} tol"
    legend = [
        "red: above target",
        "blue: below target",
        f"tol +/-{tolerance_mm:g} mm" + ("" if tol_in else " (off scale)"),
        f"saturates at +/-{limit_mm:g} mm",
    ]
    title = "deviation, mm"

    def width_of(text: str) -> int:
        return cv2.getTextSize(text, font, scale, thick)[0][0]

    label_x = margin + bar_w + text_px // 2
    width = max(
        label_x + max(width_of(t) for t in ticks.values()) + margin,
        margin + width_of(title) + margin,
        margin + max(width_of(t) for t in legend) + margin,
    )
    panel = np.full((height, width, 3), 255, dtype=np.uint8)

    rows = np.arange(top, bottom + 1)
    values = limit_mm * (1 - 2 * (rows - top) / (bottom - top))  # +limit at the top
    panel[top : bottom + 1, margin : margin + bar_w] = deviation_colormap(values, limit_mm=limit_mm)[:, None, :]
    black = (0, 0, 0)
    cv2.rectangle(panel, (margin, top), (margin + bar_w - 1, bottom), black, 1)

    def row_of(value: float) -> int:
        return round(top + (limit_mm - value) / (2 * limit_mm) * (bottom - top))

    for value, text in sorted(ticks.items()):
        y = row_of(value)
        is_tol = text.endswith("tol")
        if is_tol:
            cv2.line(panel, (margin - text_px // 3, y), (margin + bar_w + text_px // 3, y), black, max(2, thick + 1))
        else:
            cv2.line(panel, (margin + bar_w - text_px // 2, y), (margin + bar_w + text_px // 4, y), black, 1)
        cv2.putText(panel, text, (label_x, y + text_px // 2), font, scale, black, thick, cv2.LINE_AA)
    cv2.putText(panel, title, (margin, top - text_px), font, scale, black, thick, cv2.LINE_AA)
    for i, text in enumerate(legend):
        y = bottom + round((i + 1.5) * 1.5 * text_px)
        cv2.putText(panel, text, (margin, y), font, scale, black, thick, cv2.LINE_AA)
    return panel


# =========================================================================== normals, depth


def write_normals_png(path, normals, mask) -> None:
    """Write a normal field as the usual RGB normal map.

    Parameters
    ----------
    path : str or Path
    normals : (H, W, 3) float
        Unit normals in the left camera frame, pointing towards the cameras (n_z < 0).
    mask : (H, W) bool
        True = valid; outside it the pixel is black ``(0, 0, 0)``.

    Notes
    -----
    The mapping is the OpenGL-style one of a viewer-facing frame (x right, y up,
    z towards the viewer), i.e. ``(n_x, -n_y, -n_z)`` mapped from [-1, 1] to
    [0, 255]: ``R = 255 (1 + n_x) / 2``, ``G = 255 (1 - n_y) / 2``,
    ``B = 255 (1 - n_z) / 2``, rounded. A patch facing the cameras is
    ``(128, 128, 255)``; one tilted to the right (+x) is redder, one tilted
    up (-y, image top) is greener.

    Raises
    ------
    ValueError
        Wrong shapes; non-finite or non-unit (beyond 1e-3) normals inside the mask.
    OSError
        The file cannot be written.
    """
    n = np.ascontiguousarray(normals, dtype=np.float32)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals: expected shape (H, W, 3), got {n.shape}")
    mask = np.ascontiguousarray(_check_mask(mask, n.shape[:2]))
    bgr = np.empty(n.shape, np.uint8)
    n_bad, worst = _encode_normals(n, mask, bgr)
    if n_bad:
        raise ValueError(f"normals: expected finite values inside the mask, got {n_bad} non-finite")
    if worst > 1e-3:
        raise ValueError(f"normals: expected unit vectors inside the mask, got a length off by {worst:.3g}")
    if not cv2.imwrite(str(path), bgr):
        raise OSError(f"{path}: cannot write the image (is the suffix .png and the folder writable?)")


@numba.njit(cache=True)
def _encode_normals(n, mask, bgr):
    """The normal map of :func:`write_normals_png` into ``bgr`` (H, W, 3) uint8, in OpenCV's channel order.

    Returns (the number of non-finite normals inside the mask, the largest | |n| - 1 | there).
    Single-threaded: the pipeline writes it from a worker thread, and numba's parallel kernels
    must not run from two threads at once.
    """
    h, w = mask.shape
    bad_rows = np.zeros(h, np.int64)
    worst_rows = np.zeros(h)
    for i in range(h):
        for j in range(w):
            if not mask[i, j]:
                bgr[i, j, 0] = bgr[i, j, 1] = bgr[i, j, 2] = 0
                continue
            x, y, z = n[i, j, 0], n[i, j, 1], n[i, j, 2]
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                bad_rows[i] += 1
                bgr[i, j, 0] = bgr[i, j, 1] = bgr[i, j, 2] = 0
                continue
            worst_rows[i] = max(worst_rows[i], abs(np.sqrt(x * x + y * y + z * z) - 1.0))
            # (R, G, B) = 127.5 (1 + x, 1 - y, 1 - z), rounded half to even like np.rint, clipped
            bgr[i, j, 0] = min(max(np.rint(127.5 - 127.5 * z), 0.0), 255.0)
            bgr[i, j, 1] = min(max(np.rint(127.5 - 127.5 * y), 0.0), 255.0)
            bgr[i, j, 2] = min(max(np.rint(127.5 + 127.5 * x), 0.0), 255.0)
    return int(bad_rows.sum()), float(worst_rows.max()) if h else 0.0


def save_depth(path, depth_mm) -> None:
    """Save a depth map as ``.npy`` float32, NaN where there is no depth.

    Parameters
    ----------
    path : str or Path
        Written as given (no suffix is appended).
    depth_mm : (H, W) float
        Depth along the left camera's z axis, mm; NaN outside the measured area.

    Raises
    ------
    ValueError
        Not 2-D, or holding infinite values.
    """
    depth = np.asarray(depth_mm)
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(f"depth_mm: expected a float array of shape (H, W), got {depth.dtype} {depth.shape}")
    if np.isinf(depth).any():
        raise ValueError(f"depth_mm: expected finite values or NaN, got {int(np.isinf(depth).sum())} infinite")
    with open(path, "wb") as fh:
        np.save(fh, depth.astype(np.float32), allow_pickle=False)


# =========================================================================== helpers


def _check_mask(mask, shape) -> np.ndarray:
    m = np.asarray(mask)
    if m.dtype != bool:
        raise ValueError(f"mask: expected a bool array, got {m.dtype}")
    if m.shape != tuple(shape):
        raise ValueError(f"mask: expected shape {tuple(shape)}, got {m.shape}")
    return m


def _check_positive(name: str, value) -> None:
    if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name}: expected a positive finite number of mm, got {value!r}")


def _imwrite(path, rgb: np.ndarray) -> None:
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: cannot write the image (is the suffix .png and the folder writable?)")


__all__ = [
    "COLOUR_STOPS",
    "default_limit_mm",
    "deviation_colormap",
    "save_depth",
    "write_deviation_png",
    "write_normals_png",
    "write_surface_ply",
    "write_target_ply",
]
