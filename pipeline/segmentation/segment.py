"""Segment the plate from its surroundings by the stereo depth (:func:`segment_plate`), or by brightness
alone when there is no usable depth."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ..formats import CaptureError
from ..solvers import labelled
from .candidates import DARK_FRACTION, candidate_mask
from .checks import check_bool_image, check_camera_matrix, check_image
from .classify import SUPPORT_WIDTH_MM, Parts, classify
from .edge_band import finish, inner_region
from .result import Segmentation
from .surface import DEPTH_BAND_MM, largest_component

#: Default width (px) of the edge band excluded along the plate's outline and openings.
EDGE_PX = 2
#: Default largest unmatched region (mm^2) inside the plate that is filled as a stereo dropout.
MAX_DROPOUT_MM2 = 1500.0
#: Least share of the candidates with a stereo depth for a geometric segmentation.
MIN_MATCHED_SHARE = 0.1


def segment_plate(
    brightness: npt.ArrayLike,
    depth_mm: npt.ArrayLike | None,
    camera_matrix: npt.ArrayLike,
    *,
    seen: npt.ArrayLike | None = None,
    candidates: npt.ArrayLike | None = None,
    normals: npt.ArrayLike | None = None,
    depth_band_mm: float = DEPTH_BAND_MM,
    edge_px: int = EDGE_PX,
    depth_scale_px: int = 1,
    max_dropout_mm2: float = MAX_DROPOUT_MM2,
    reach_px: int = 4,
    support_width_mm: float = SUPPORT_WIDTH_MM,
    step_zone_px: int = 8,
    target_area_mm2: float | None = None,
    dark_fraction: float = DARK_FRACTION,
    glare_free: npt.ArrayLike | None = None,
) -> Segmentation:
    """Segment the plate from its surroundings by the stereo depth, brightness only as a first guess.

    Parameters
    ----------
    brightness : (H, W) array_like of float
        Brightest photometric sample per pixel on the left undistorted grid (any linear unit), as
        preprocessing computes it.
    depth_mm : (H, W) array_like of float or None
        Stereo depth, mm along the left optical axis, on the same grid; NaN where unmatched. It must
        cover the surroundings too (match the pair over :func:`candidate_mask`, not over a plate mask).
        None: brightness only.
    camera_matrix : (3, 3) array_like
        K of the left undistorted grid (pixels).
    seen : (H, W) bool, optional
        Pixels that have photometric samples (False outside the raw image's undistorted footprint).
    candidates : (H, W) bool, optional
        The pixels that may be plate (default :func:`candidate_mask` of ``brightness``).
    normals : (H, W, 3) array_like of float, optional
        Photometric unit normals (left camera frame, towards the camera; NaN where unknown), e.g.
        :func:`pipeline.surface.normals.estimate_normals` over the candidates: they decide larger unmatched
        areas (step 4) and the normals check near the boundary (step 6: within ``edge_px +
        EDGE_NORMAL_ZONE_PX``, a normal over ``EDGE_NORMAL_DEG`` from the surface's joins the band).
    depth_band_mm : float
        Largest distance (mm, along the optical axis) of a plate pixel's stereo depth from the fitted
        smooth surface.
    edge_px : int
        Width of the edge band, pixels (>= 0), for a stereo depth matched at this grid's resolution.
    depth_scale_px : int
        The stereo depth was matched on this grid reduced this many times (:mod:`pipeline.stages`
        matches a pair wider than ``InspectOptions.stereo_max_width`` reduced): the matcher's smearing across an edge grows with it, so the
        edge band and the zone of the normals check are this many times wider (>= 1).
    max_dropout_mm2 : float
        Largest unmatched region inside the plate filled as a stereo dropout, mm^2 (>= 0).
    reach_px : int
        Unmatched rim pixels up to this far (px) from the matched plate are plate when darkness
        bounds them (a dark background).
    support_width_mm : float
        Parts of the matched plate narrower than this (mm) whose stereo depth leaves the smooth surface
        (``PROTRUSION_SHARE`` of them farther than ``max(PROTRUSION_RESIDUAL_MM, 5 fit_rms_mm)``) are
        supports beside the plate (step 3); 0 disables this.
    step_zone_px : int
        Width (px) of the zone along the plate's boundary where ``surroundings_step_mm`` is given.
    target_area_mm2 : float, optional
        The target's area (mm^2): the segmented area is compared with it (a reason when they differ by
        more than 5 % over or 10 % under).
    dark_fraction : float
        See :func:`candidate_mask`.
    glare_free : (H, W) array_like of float, optional
        A brightness of the same pixels that a broad glare lobe reaches least (the pipeline gives the
        brightest of the darkest quarter of the photometric samples,
        :attr:`pipeline.preprocess.Preprocessed.glare_free`): the outline
        where the depth cannot draw it is found at its step (:mod:`~pipeline.segmentation.outline`).
        None: ``brightness``.

    Returns
    -------
    Segmentation

    Raises
    ------
    ValueError
        Bad shapes, dtypes or option values.
    pipeline.formats.CaptureError
        No plate found: no candidate pixels, or none connected to the fitted surface.

    Notes
    -----
    The steps: see :mod:`pipeline.segmentation`. Brightness only excludes the dark and bounds the rim.
    """
    b, K, ok, depth, normals = _inputs(brightness, camera_matrix, seen, depth_mm, normals)
    _check_options(
        depth_band_mm,
        max_dropout_mm2,
        support_width_mm,
        edge_px,
        reach_px,
        step_zone_px,
        depth_scale_px,
        target_area_mm2,
    )
    cand = (
        candidate_mask(b, seen=ok, dark_fraction=dark_fraction)
        if candidates is None
        else (check_bool_image("candidates", candidates, b.shape) & ok)
    )
    if not cand.any():
        raise CaptureError(
            "photometric images: no plate found (no pixel brighter than the dark background)"
        )
    params = dict(
        depth_band_mm=float(depth_band_mm),
        max_dropout_mm2=float(max_dropout_mm2),
        reach_px=int(reach_px),
        support_width_mm=float(support_width_mm),
        step_zone_px=int(step_zone_px),
    )
    gf = (
        b
        if glare_free is None
        else check_image("glare_free", glare_free, b.shape).astype(np.float32)
    )
    return _segmented(
        b,
        gf,
        depth,
        K,
        ok,
        cand,
        normals,
        params,
        edge_px=int(edge_px) * int(depth_scale_px),
        depth_scale_px=int(depth_scale_px),
        target_area_mm2=target_area_mm2,
    )


def _segmented(
    b: np.ndarray,
    glare_free: np.ndarray,
    depth: np.ndarray | None,
    K: np.ndarray,
    ok: np.ndarray,
    cand: np.ndarray,
    normals: np.ndarray | None,
    params: dict[str, Any],
    *,
    edge_px: int,
    depth_scale_px: int,
    target_area_mm2: float | None,
) -> Segmentation:
    """The geometric segmentation when enough of the candidates have a stereo depth and a smooth surface
    fits it, else the brightness-only one (its reasons say why). ``params``: the options of
    :func:`classify`; ``edge_px`` already scaled by ``depth_scale_px``."""
    dark = ok & ~cand
    reasons: list[str] = []
    finite = np.zeros(b.shape, bool) if depth is None else (np.isfinite(depth) & (depth > 0) & ok)
    matched_share = np.count_nonzero(finite & cand) / np.count_nonzero(cand)
    if depth is None:
        reasons.append(
            "no stereo depth: the plate was told from its surroundings by brightness only"
        )
    elif matched_share < MIN_MATCHED_SHARE:
        reasons.append(
            f"stereo depth on {100 * matched_share:.1f} % of the bright pixels (under {100 * MIN_MATCHED_SHARE:.0f} %): "
            "the plate was told from its surroundings by brightness only"
        )
    else:
        parts = _classified(b, depth, K, ok, cand, normals, depth_scale_px, params)
        if parts is None:
            reasons.append("no smooth surface fits the stereo depth: brightness only")
        else:
            return finish(
                parts,
                glare_free,
                depth,
                K,
                ok,
                cand,
                dark,
                normals,
                reasons,
                edge_px=edge_px,
                depth_scale_px=depth_scale_px,
                depth_band_mm=params["depth_band_mm"],
                max_dropout_mm2=params["max_dropout_mm2"],
                support_width_mm=params["support_width_mm"],
                target_area_mm2=target_area_mm2,
            )
    return _by_brightness(cand, dark, ok, reasons, edge_px=edge_px)


def _inputs(
    brightness: npt.ArrayLike,
    camera_matrix: npt.ArrayLike,
    seen: npt.ArrayLike | None,
    depth_mm: npt.ArrayLike | None,
    normals: npt.ArrayLike | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The images of :func:`segment_plate` checked: brightness float32, K, seen pixels, depth or None, normals or None."""
    b = check_image("brightness", brightness).astype(np.float32)
    shape = b.shape
    K = check_camera_matrix(camera_matrix)
    ok = np.ones(shape, bool) if seen is None else check_bool_image("seen", seen, shape)
    depth = (
        None if depth_mm is None else check_image("depth_mm", depth_mm, shape).astype(np.float32)
    )
    n = None if normals is None else np.asarray(normals)
    if n is not None and n.shape != (*shape, 3):
        raise ValueError(
            f"normals: expected shape {(*shape, 3)} to match brightness, got {n.shape}"
        )
    return b, K, ok, depth, n


def _check_options(
    depth_band_mm: float,
    max_dropout_mm2: float,
    support_width_mm: float,
    edge_px: int,
    reach_px: int,
    step_zone_px: int,
    depth_scale_px: int,
    target_area_mm2: float | None,
) -> None:
    """ValueError naming the first option of :func:`segment_plate` out of its range."""
    for name, value in (
        ("depth_band_mm", depth_band_mm),
        ("max_dropout_mm2", max_dropout_mm2),
        ("support_width_mm", support_width_mm),
    ):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name}: expected a finite value >= 0, got {value}")
    if depth_band_mm <= 0:
        raise ValueError(f"depth_band_mm: expected a band > 0 mm, got {depth_band_mm}")
    for name, value in (
        ("edge_px", edge_px),
        ("reach_px", reach_px),
        ("step_zone_px", step_zone_px),
    ):
        if not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"{name}: expected an integer >= 0, got {value!r}")
    if not isinstance(depth_scale_px, (int, np.integer)) or depth_scale_px < 1:
        raise ValueError(f"depth_scale_px: expected an integer >= 1, got {depth_scale_px!r}")
    if target_area_mm2 is not None and not (math.isfinite(target_area_mm2) and target_area_mm2 > 0):
        raise ValueError(
            f"target_area_mm2: expected a positive area in mm^2 or None, got {target_area_mm2}"
        )


def _classified(
    b: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    ok: np.ndarray,
    cand: np.ndarray,
    normals: np.ndarray | None,
    s: int,
    params: dict[str, Any],
) -> Parts | None:
    """:func:`classify` on the grid the depth was matched at (``s`` times coarser), its decisions brought
    back to this grid; None if no smooth surface fits."""
    if s == 1:
        return classify(b, depth, K, ok, cand, normals, **params)
    # the depth has the resolution of a grid s times coarser: decide there (s^2 times less work),
    # then bring the decisions back and draw the edge band on this grid
    K_s = np.diag([1.0 / s, 1.0 / s, 1.0]) @ K
    parts = classify(
        b[::s, ::s],
        depth[::s, ::s],
        K_s,
        ok[::s, ::s],
        cand[::s, ::s],
        None if normals is None else normals[::s, ::s],
        **params,
    )
    return None if parts is None else parts.upsampled(s, b.shape)


def _by_brightness(
    cand: np.ndarray, dark: np.ndarray, ok: np.ndarray, reasons: list[str], *, edge_px: int
) -> Segmentation:
    """The plate as the largest candidate component, holes of a few pixels filled (no depth to judge by)."""
    shape = cand.shape
    opened = cv2.morphologyEx(
        cand.view(np.uint8), cv2.MORPH_OPEN, np.ones((5, 5), np.uint8)
    ).astype(bool)
    core = largest_component(opened)
    if not core.any():
        raise CaptureError(
            "photometric images: no plate found (no region brighter than the background)"
        )
    n_lab, labels, areas = labelled(~core, connectivity=4)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    # without depth only specks can be told from openings: at most 0.05 % of the plate
    small = areas <= max(4, int(5e-4 * np.count_nonzero(core)))
    small[border] = False
    small[0] = False
    inner = np.ones(n_lab, bool)
    inner[border] = False
    inner[0] = False
    filled = small[labels]
    holes = (inner & ~small)[labels]
    region = core | filled
    mask = inner_region(region, edge_px) & ok
    edge_band = region & ~mask
    nan = np.full(shape, np.nan, np.float32)
    n_holes = int(np.count_nonzero(inner & ~small))
    if n_holes:
        reasons.append(f"{n_holes} dark region(s) inside the plate kept as holes, not measured")
    return Segmentation(
        mask=mask,
        edge_band=edge_band,
        holes=holes,
        surface_depth_mm=nan,
        surroundings_step_mm=nan.copy(),
        pixel_area_mm2=nan.copy(),
        plate_area_mm2=math.nan,
        edge_band_area_mm2=math.nan,
        holes_area_mm2=math.nan,
        filled_area_mm2=math.nan,
        n_mask=int(np.count_nonzero(mask)),
        n_edge_band=int(np.count_nonzero(edge_band)),
        n_holes=n_holes,
        n_hole_pixels=int(np.count_nonzero(holes)),
        n_off_depth=0,
        n_dark=int(np.count_nonzero(dark)),
        n_unmatched=int(np.count_nonzero(cand)),
        fit_rms_mm=math.nan,
        depth_band_mm=math.nan,
        method="brightness",
        reasons=tuple(reasons),
    )
