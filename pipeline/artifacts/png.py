"""deviation.png (the colour map with its scale bar in mm) and normals.png."""

from __future__ import annotations

import functools
import math
import os

import cv2
import numba
import numpy as np
import numpy.typing as npt

from ..io.png import write_rgb
from .checks import check_mask, check_positive
from .colours import default_limit_mm, deviation_colormap

#: Minimum height in pixels of the deviation PNG (small maps are enlarged by an integer factor).
MIN_PNG_HEIGHT = 540
#: Tallest map drawn (px); a taller one is sampled down by a whole stride.
MAX_PNG_HEIGHT = 1080

#: Widest enlargement of a small map (px), so thin maps are not blown up without bound.
MAX_PNG_WIDTH = 4000


def write_deviation_png(
    path: str | os.PathLike[str],
    deviation_mm: npt.ArrayLike,
    mask: npt.ArrayLike,
    *,
    tolerance_mm: float,
    limit_mm: float | None = None,
) -> None:
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
    mask = check_mask(mask, dev.shape)
    check_positive("tolerance_mm", tolerance_mm)
    limit = default_limit_mm(tolerance_mm) if limit_mm is None else limit_mm
    check_positive("limit_mm", limit)
    stride, k = deviation_png_layout(dev.shape)
    if stride > 1:
        dev, mask = dev[::stride, ::stride], mask[::stride, ::stride]

    rgb = deviation_colormap(np.where(mask, dev, np.nan), limit_mm=limit)
    if k > 1:
        rgb = np.repeat(np.repeat(rgb, k, axis=0), k, axis=1)
    height = max(rgb.shape[0], MIN_PNG_HEIGHT)
    panel = _scale_panel(height, limit_mm=float(limit), tolerance_mm=float(tolerance_mm))
    canvas = np.full((height, rgb.shape[1] + panel.shape[1], 3), 255, dtype=np.uint8)
    canvas[: rgb.shape[0], : rgb.shape[1]] = rgb
    canvas[:, rgb.shape[1] :] = panel
    write_rgb(path, canvas)


def deviation_png_layout(shape_hw: tuple[int, ...]) -> tuple[int, int]:
    """How deviation.png draws an (H, W) map: ``(stride, k)``.

    A map taller than a screen is shown reduced anyway: it is sampled every ``stride`` pixels; the
    sampled map is then enlarged ``k`` times (nearest neighbour), so image pixel ``(r, c)`` lands at
    PNG pixel ``(r * k / stride, c * k / stride)`` (:func:`write_deviation_png`).
    """
    stride = math.ceil(shape_hw[0] / MAX_PNG_HEIGHT)
    h, w = -(-shape_hw[0] // stride), -(-shape_hw[1] // stride)
    return stride, max(1, min(math.ceil(MIN_PNG_HEIGHT / h), MAX_PNG_WIDTH // w))


@functools.lru_cache(maxsize=16)
def _scale_panel(height: int, *, limit_mm: float, tolerance_mm: float) -> np.ndarray:
    """(height, width, 3) uint8 RGB, read-only: colour bar, ticks in mm, tolerance marks, legend.

    Drawn once a process for each height, limit and tolerance (a cell's maps share them): OpenCV
    sets up its font in every thread that first draws text (``cv2.getTextSize`` / ``putText``), and
    the inspections' artifact writers are new threads each time.
    """
    font = cv2.FONT_HERSHEY_SIMPLEX
    text_px = max(14, round(height / 40))
    scale = text_px / 22.0  # FONT_HERSHEY_SIMPLEX capitals are ~22 px high at scale 1
    thick = max(1, round(scale * 1.3))
    margin = text_px
    bar_w = 2 * text_px
    top, bottom = 3 * text_px, height - 7 * text_px
    decimals = 2 if limit_mm < 1 else 1

    ticks = {
        0.0: "0",
        limit_mm: f"{limit_mm:+.{decimals}f}",
        -limit_mm: f"{-limit_mm:+.{decimals}f}",
    }
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
    panel[top : bottom + 1, margin : margin + bar_w] = deviation_colormap(
        values, limit_mm=limit_mm
    )[:, None, :]
    black = (0, 0, 0)
    cv2.rectangle(panel, (margin, top), (margin + bar_w - 1, bottom), black, 1)

    def row_of(value: float) -> int:
        return round(top + (limit_mm - value) / (2 * limit_mm) * (bottom - top))

    for value, text in sorted(ticks.items()):
        y = row_of(value)
        is_tol = text.endswith("tol")
        if is_tol:
            cv2.line(
                panel,
                (margin - text_px // 3, y),
                (margin + bar_w + text_px // 3, y),
                black,
                max(2, thick + 1),
            )
        else:
            cv2.line(
                panel,
                (margin + bar_w - text_px // 2, y),
                (margin + bar_w + text_px // 4, y),
                black,
                1,
            )
        cv2.putText(
            panel, text, (label_x, y + text_px // 2), font, scale, black, thick, cv2.LINE_AA
        )
    cv2.putText(panel, title, (margin, top - text_px), font, scale, black, thick, cv2.LINE_AA)
    for i, text in enumerate(legend):
        y = bottom + round((i + 1.5) * 1.5 * text_px)
        cv2.putText(panel, text, (margin, y), font, scale, black, thick, cv2.LINE_AA)
    panel.flags.writeable = False  # shared by every call with the same arguments
    return panel


# =========================================================================== normals


def write_normals_png(
    path: str | os.PathLike[str], normals: npt.ArrayLike, mask: npt.ArrayLike
) -> None:
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
    mask = np.ascontiguousarray(check_mask(mask, n.shape[:2]))
    rgb = np.empty(n.shape, np.uint8)
    n_bad, worst = _encode_normals(n, mask, rgb)
    if n_bad:
        raise ValueError(f"normals: expected finite values inside the mask, got {n_bad} non-finite")
    if worst > 1e-3:
        raise ValueError(
            f"normals: expected unit vectors inside the mask, got a length off by {worst:.3g}"
        )
    write_rgb(path, rgb)


@numba.njit(nogil=True, cache=True)
def _encode_normals(
    n: npt.NDArray[np.float32], mask: npt.NDArray[np.bool_], rgb: npt.NDArray[np.uint8]
) -> tuple[int, float]:
    """The normal map of :func:`write_normals_png` into ``rgb`` (H, W, 3) uint8.

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
                rgb[i, j, 0] = rgb[i, j, 1] = rgb[i, j, 2] = 0
                continue
            x, y, z = n[i, j, 0], n[i, j, 1], n[i, j, 2]
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                bad_rows[i] += 1
                rgb[i, j, 0] = rgb[i, j, 1] = rgb[i, j, 2] = 0
                continue
            worst_rows[i] = max(worst_rows[i], abs(np.sqrt(x * x + y * y + z * z) - 1.0))
            # (R, G, B) = 127.5 (1 + x, 1 - y, 1 - z), rounded half to even like np.rint, clipped
            rgb[i, j, 0] = min(max(np.rint(127.5 + 127.5 * x), 0.0), 255.0)
            rgb[i, j, 1] = min(max(np.rint(127.5 - 127.5 * y), 0.0), 255.0)
            rgb[i, j, 2] = min(max(np.rint(127.5 - 127.5 * z), 0.0), 255.0)
    return int(bad_rows.sum()), float(worst_rows.max()) if h else 0.0
