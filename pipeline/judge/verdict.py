"""The pass/fail verdict of a plate from its deviation map."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import ndimage

from pipeline.solvers import percentile

#: Default smallest out-of-tolerance region (mm^2) that fails a plate: 100 mm^2 = 1 cm^2, i.e. tens of
#: pixels at 1.2-3.5 mm/pixel, far more than a noisy pixel, far less than a real dent (a 6 mm dent of
#: radius 100 mm is out of a 2 mm tolerance over ~13 000 mm^2).
MIN_DEFECT_AREA_MM2 = 100.0
#: Default largest share (%) of the measured area allowed out of tolerance in total, scattered or not.
MAX_OUTSIDE_PCT = 1.0


@dataclass(frozen=True)
class DefectRegion:
    """A connected region (8-neighbour) of pixels out of tolerance.

    Attributes
    ----------
    centroid_px : (float, float)
        ``(u, v)`` = (column, row) of the region's centroid, pixels.
    area_mm2 : float
        Surface area of the region, mm^2.
    peak_deviation_mm : float
        Signed deviation of largest magnitude in the region, mm.
    n_pixels : int
    mean_deviation_mm : float
        Area-weighted mean of the signed deviation over the region, mm.
    """

    centroid_px: tuple[float, float]
    area_mm2: float
    peak_deviation_mm: float
    n_pixels: int
    mean_deviation_mm: float = float("nan")
    #: Expanded uncertainty (k = 2) of the measurement at the peak, mm (NaN when not known).
    uncertainty_mm: float = float("nan")


@dataclass(frozen=True)
class Judgement:
    """Deviation statistics and the verdict (see :func:`judge` for the rule).

    Attributes
    ----------
    rms_mm, max_abs_mm, p95_mm : float
        RMS, maximum and 95th percentile of ``|deviation|`` over the judged pixels, mm.
    within_tolerance_pct : float
        Share of the judged surface area with ``|deviation| <= tolerance_mm``, percent.
    verdict : {"pass", "fail"}
    defects : tuple of DefectRegion
        Out-of-tolerance regions of at least ``min_defect_area_mm2``, largest first.
    outside_area_mm2 : float
        Total out-of-tolerance area, mm^2 (regions of any size).
    n_pixels : int
        Pixels judged (in the mask, with a finite deviation).
    reasons : tuple of str
        Why the plate failed (empty when it passed).
    """

    rms_mm: float
    max_abs_mm: float
    p95_mm: float
    within_tolerance_pct: float
    verdict: str
    defects: tuple[DefectRegion, ...]
    outside_area_mm2: float
    n_pixels: int
    reasons: tuple[str, ...]


def judge(
    deviation_mm: npt.ArrayLike,
    mask: npt.ArrayLike,
    tolerance_mm: float,
    *,
    pixel_area_mm2: float | npt.ArrayLike,
    min_defect_area_mm2: float = MIN_DEFECT_AREA_MM2,
    max_outside_pct: float = MAX_OUTSIDE_PCT,
    uncertainty_mm: npt.ArrayLike | None = None,
) -> Judgement:
    """Deviation statistics and the pass/fail verdict of a plate.

    Parameters
    ----------
    deviation_mm : (H, W) array_like of float
        Signed deviation, mm (from :func:`deviation_map`); NaN pixels are not judged.
    mask : (H, W) bool
        Measured pixels.
    tolerance_mm : float
        Allowed ``|deviation|``, mm, > 0.
    pixel_area_mm2 : float or (H, W) array_like of float
        Surface area one pixel covers, mm^2 (one value, or per pixel).
    min_defect_area_mm2 : float
        Smallest connected out-of-tolerance region that fails the plate, mm^2 (default 100 mm^2).
    max_outside_pct : float
        Largest share of the judged area allowed out of tolerance in total, percent (default 1 %).
    uncertainty_mm : (H, W) array_like of float, optional
        Per-point expanded uncertainty (k = 2) of the measurement, mm. With it, an out-of-tolerance
        region is a defect only where its peak exceeds the tolerance by more than the standard
        uncertainty there (``U / 2``): a region of noise grazing the tolerance is not a defect;
        each defect carries its ``U``.

    Returns
    -------
    Judgement

    Raises
    ------
    ValueError
        Bad shapes, non-positive tolerance or areas, or no pixel with a finite deviation in the mask.

    Notes
    -----
    Rule: the plate **fails** when some 8-connected region of pixels with ``|deviation| > tolerance_mm``
    covers at least ``min_defect_area_mm2``, or when the out-of-tolerance pixels together cover more than
    ``max_outside_pct`` of the judged area; otherwise it passes. So isolated noisy pixels do not fail a
    good plate, while a real local defect (a dent, a kink) or a plate wrong all over does. Statistics are
    over the judged pixels (mask and finite deviation); ``within_tolerance_pct`` is area-weighted.
    """
    dev, m, area = _check_inputs(
        deviation_mm, mask, tolerance_mm, pixel_area_mm2, min_defect_area_mm2, max_outside_pct
    )
    judged = m & np.isfinite(dev)
    n = int(np.count_nonzero(judged))
    if n == 0:
        raise ValueError("deviation_mm: expected finite deviations inside the mask, got none")
    area_judged = area[judged] if area.ndim == 2 else None
    if area_judged is not None and not np.all(np.isfinite(area_judged) & (area_judged > 0)):
        raise ValueError("pixel_area_mm2: expected positive finite areas at every judged pixel")

    a = np.abs(dev[judged])
    rms = float(np.sqrt(np.mean(np.square(a, dtype=np.float64))))
    max_abs = float(a.max())
    p95 = float(percentile(a, 95))
    w = np.full(n, float(area)) if area_judged is None else area_judged
    outside = a > tolerance_mm
    total_area = float(w.sum())
    outside_area = float(w[outside].sum())
    within_pct = 100.0 * (1.0 - outside_area / total_area)
    u_map = None if uncertainty_mm is None else np.asarray(uncertainty_mm)
    if u_map is not None and u_map.shape != dev.shape:
        raise ValueError(f"uncertainty_mm: expected shape {dev.shape}, got {u_map.shape}")
    defects = (
        _defect_regions(dev, judged, outside, area, min_defect_area_mm2, tolerance_mm, u_map)
        if outside.any()
        else []
    )
    reasons = []
    if defects:
        reasons.append(
            f"{len(defects)} {'region' if len(defects) == 1 else 'regions'} out of the "
            f"{tolerance_mm:g} mm tolerance over {min_defect_area_mm2 / 100.0:g} cm² "
            f"(largest {defects[0].area_mm2 / 100.0:.1f} cm²)"
        )
    if 100.0 - within_pct > max_outside_pct:
        reasons.append(
            f"{100.0 - within_pct:.2f} % of the area out of tolerance (over {max_outside_pct:g} %)"
        )
    return Judgement(
        rms_mm=rms,
        max_abs_mm=max_abs,
        p95_mm=p95,
        within_tolerance_pct=within_pct,
        verdict="fail" if reasons else "pass",
        defects=tuple(defects),
        outside_area_mm2=outside_area,
        n_pixels=n,
        reasons=tuple(reasons),
    )


def _check_inputs(
    deviation_mm: npt.ArrayLike,
    mask: npt.ArrayLike,
    tolerance_mm: float,
    pixel_area_mm2: float | npt.ArrayLike,
    min_defect_area_mm2: float,
    max_outside_pct: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arguments of :func:`judge` checked: deviation (H, W) float64, mask, pixel area (scalar or (H, W))."""
    dev = np.asarray(deviation_mm)
    if not np.issubdtype(dev.dtype, np.floating):  # float32 maps stay float32: no copy
        dev = dev.astype(np.float64)
    if dev.ndim != 2:
        raise ValueError(f"deviation_mm: expected shape (H, W), got {dev.shape}")
    m = np.asarray(mask)
    if m.dtype != np.bool_ or m.shape != dev.shape:
        raise ValueError(
            f"mask: expected a bool array of shape {dev.shape}, got {m.dtype} {m.shape}"
        )
    if not (math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise ValueError(f"tolerance_mm: expected a positive number of mm, got {tolerance_mm}")
    if not (math.isfinite(min_defect_area_mm2) and min_defect_area_mm2 > 0):
        raise ValueError(
            f"min_defect_area_mm2: expected a positive area in mm^2, got {min_defect_area_mm2}"
        )
    if not (math.isfinite(max_outside_pct) and 0 <= max_outside_pct <= 100):
        raise ValueError(
            f"max_outside_pct: expected a percentage in [0, 100], got {max_outside_pct}"
        )
    area = np.asarray(pixel_area_mm2, dtype=np.float64)
    if area.ndim == 0:
        if not (math.isfinite(float(area)) and area > 0):
            raise ValueError(f"pixel_area_mm2: expected a positive area in mm^2, got {float(area)}")
    elif area.shape != dev.shape:
        raise ValueError(
            f"pixel_area_mm2: expected a number or shape {dev.shape}, got shape {area.shape}"
        )
    return dev, m, area


def _defect_regions(
    dev: np.ndarray,
    judged: np.ndarray,
    outside: np.ndarray,
    area: np.ndarray,
    min_defect_area_mm2: float,
    tolerance_mm: float,
    u_map: np.ndarray | None,
) -> list[DefectRegion]:
    """The 8-connected regions of the out-of-tolerance judged pixels that cover at least
    ``min_defect_area_mm2`` (and, with ``u_map``, whose peak exceeds the tolerance by more than its
    standard uncertainty), largest first (``outside``: per judged pixel)."""
    defects: list[DefectRegion] = []
    out_map = np.zeros(dev.shape, dtype=bool)
    out_map[judged] = outside
    labels, n_lab = ndimage.label(out_map, structure=np.ones((3, 3), dtype=bool))
    rows, cols = np.nonzero(out_map)  # few pixels: per-region sums by bincount over them only
    lab = labels[rows, cols]
    px_area = np.full(lab.size, float(area)) if area.ndim == 0 else area[rows, cols]
    reg_area = np.bincount(lab, weights=px_area, minlength=n_lab + 1)
    reg_count = np.bincount(lab, minlength=n_lab + 1)
    reg_row = np.bincount(lab, weights=rows, minlength=n_lab + 1)
    reg_col = np.bincount(lab, weights=cols, minlength=n_lab + 1)
    vals = dev[rows, cols]
    reg_dev = np.bincount(lab, weights=px_area * vals, minlength=n_lab + 1)
    for k in np.nonzero(reg_area >= min_defect_area_mm2)[0]:
        if k == 0:
            continue
        v = vals[lab == k]
        i_peak = int(np.argmax(np.abs(v)))
        peak = float(v[i_peak])
        u_peak = float("nan")
        if u_map is not None:
            r_k, c_k = rows[lab == k][i_peak], cols[lab == k][i_peak]
            u_peak = float(u_map[r_k, c_k])
            if np.isfinite(u_peak) and abs(peak) - tolerance_mm <= u_peak / 2.0:
                continue  # within its own noise of the tolerance: not proven out of it
        defects.append(
            DefectRegion(
                centroid_px=(float(reg_col[k] / reg_count[k]), float(reg_row[k] / reg_count[k])),
                area_mm2=float(reg_area[k]),
                peak_deviation_mm=peak,
                n_pixels=int(reg_count[k]),
                mean_deviation_mm=float(reg_dev[k] / reg_area[k]),
                uncertainty_mm=u_peak,
            )
        )
    defects.sort(key=lambda d: -d.area_mm2)
    return defects
