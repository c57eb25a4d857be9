"""Steps 2-5 and 7 on the depth's grid: the plate's region, the holes kept and filled, the rim, the supports
taken out, and the depth step to the surroundings along the boundary."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from ..formats import CaptureError
from .surface import (
    Geometry,
    Surface,
    fit_surface,
    largest_component,
    surface_depth,
    surface_geometry,
)

#: Default width (mm) under which a part of the matched plate that leaves the smooth surface is taken for a
#: support reaching out beside the plate (rails and blocks are 100-200 mm wide).
SUPPORT_WIDTH_MM = 250.0
#: A narrow part is a support when PROTRUSION_SHARE of its pixels have a stereo depth farther from the smooth
#: surface than this (mm) or five times the fit's RMS: a support's flat top parts from a curved plate's
#: continuation.
PROTRUSION_RESIDUAL_MM = 8.0
PROTRUSION_SHARE = 0.3
#: Such a part is the plate's own corner (bent off the smooth surface: a forming defect, kept and judged),
#: not a support, when the concavity it leaves beside it in the plate's outline is under this share of
#: how far it reaches beyond the rest of the plate's convex hull. A support reaching out from an edge
#: leaves a concavity on either side about as deep as its reach (the share near 1); a corner the
#: opening cut off rounds the outline out, leaving only the outline's roughness beside it. A corner
#: reaches at most the opening disc's radius beyond the rest (a corner of 60 deg: the disc inscribed in
#: it leaves its tip one radius beyond; a right angle 0.41 of it): a part reaching farther is not one.
CORNER_CONCAVITY_SHARE = 0.75
#: A larger unmatched area inside the plate is filled when the median angle between its photometric
#: normals and the fitted surface's is at most this (deg): the stereo pair missed plate there.
DROPOUT_NORMAL_DEG = 3.0
#: A dropout may hold at most this share of pixels with off-plate depth or darkness.
DROPOUT_MAX_OFF_SHARE = 0.25


@dataclass(frozen=True)
class Parts:
    """What the geometric segmentation decided, on its grid (internal)."""

    surface: Surface
    region: np.ndarray  # (H, W) bool: plate, before the edge band
    holes: np.ndarray  # (H, W) bool
    feet: np.ndarray  # (H, W) bool: wide supports removed beside the plate
    step: np.ndarray  # (H, W) float32, see Segmentation.surroundings_step_mm
    mm_per_px: float  # on this grid
    n_holes: int
    largest_hole_mm2: float
    filled_mm2: float  # small dropouts filled
    filled_by_normals_mm2: float  # larger unmatched areas filled, their normals agreeing
    largest_by_normals_mm2: float
    protrusions_mm2: float  # supports removed
    px_scale: int = 1  # pixels of the final grid per pixel of this one, along each axis

    def upsampled(self, s: int, shape: tuple[int, int]) -> Parts:
        """The decisions on a grid ``s`` times finer of ``shape`` (coarse pixel i covers s i .. s i + s - 1)."""
        h, w = shape

        def up(a: np.ndarray) -> np.ndarray:
            src = a.view(np.uint8) if a.dtype == np.bool_ else a
            big = cv2.resize(src, (a.shape[1] * s, a.shape[0] * s), interpolation=cv2.INTER_NEAREST)
            out = (
                np.zeros((h, w), src.dtype)
                if a.dtype == np.bool_
                else np.full((h, w), np.nan, a.dtype)
            )
            out[: min(h, big.shape[0]), : min(w, big.shape[1])] = big[:h, :w]
            return out.view(np.bool_) if a.dtype == np.bool_ else out

        return replace(
            self,
            region=up(self.region),
            holes=up(self.holes),
            feet=up(self.feet),
            step=up(self.step),
            mm_per_px=self.mm_per_px / s,
            px_scale=s,
        )


def classify(
    b: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    ok: np.ndarray,
    cand: np.ndarray,
    normals: np.ndarray | None,
    *,
    depth_band_mm: float,
    max_dropout_mm2: float,
    reach_px: int,
    support_width_mm: float,
    step_zone_px: int,
) -> Parts | None:
    """Steps 2-5 and 7 of the module docstring on the given grid; None if no smooth surface fits.

    ``b`` brightness, ``depth`` stereo depth (mm, NaN unmatched), ``ok`` pixels seen, ``cand`` candidates,
    ``normals`` photometric normals or None, all (H, W) on this grid with its camera matrix ``K``.
    """
    shape = b.shape
    dark = ok & ~cand
    finite = np.isfinite(depth) & (depth > 0) & ok
    surface = fit_surface(depth, cand & finite, K, depth_band_mm)
    if surface is None:
        return None
    z_fit = surface_depth(surface, K, shape)
    residual = depth - z_fit  # NaN where unmatched
    with np.errstate(invalid="ignore"):
        near = finite & cand & (np.abs(residual) < depth_band_mm)
        off = finite & ~near  # matched, off the plate's surface (or a dark pixel with depth)
    core = largest_component(near)
    if not core.any():
        raise CaptureError("stereo: no plate found (no matched pixels near the fitted surface)")
    geometry = surface_geometry(surface, K, shape)
    area = geometry.area_full(shape)
    mm_per_px = math.sqrt(float(np.nanmedian(area[core])))
    protrusions = _protrusions(
        core,
        residual,
        mm_per_px,
        support_width_mm,
        max(PROTRUSION_RESIDUAL_MM, 5.0 * surface.rms_mm),
    )
    wide = wide_parts(protrusions, max(1.5, support_width_mm / mm_per_px / 20))
    corners = outline_corners(core, wide, 0.5 * support_width_mm / mm_per_px)
    protrusions &= ~corners
    if protrusions.any():
        core &= ~protrusions
        core = largest_component(core)
    feet = wide & ~corners  # whole components leave: the others stay as wide as they were
    enclosed = _enclosed(core, off | dark | ~ok, area, geometry, normals, max_dropout_mm2)
    # the rim: a pixel mostly dark (under half the plate's median brightness, unsmoothed) is not taken
    lit = b >= 0.5 * float(np.median(b[::4, ::4][core[::4, ::4]]))
    region = _with_rim(
        core | enclosed.filled, ok & cand & ~finite & lit & ~enclosed.holes, dark, reach_px
    )
    step = _surroundings_step(region, off, dark | ~lit | ~ok, depth, z_fit, step_zone_px, reach_px)
    return Parts(
        surface=surface,
        region=region,
        holes=enclosed.holes,
        feet=feet,
        step=step,
        mm_per_px=mm_per_px,
        n_holes=enclosed.n_holes,
        largest_hole_mm2=enclosed.largest_hole_mm2,
        filled_mm2=enclosed.filled_mm2,
        filled_by_normals_mm2=enclosed.by_normals_mm2,
        largest_by_normals_mm2=enclosed.largest_by_normals_mm2,
        protrusions_mm2=float(np.nansum(area[protrusions])),
    )


@dataclass(frozen=True)
class _Enclosed:
    """The regions enclosed by the plate's core: filled (dropouts) or kept as holes, and their areas (mm^2)."""

    filled: np.ndarray  # (H, W) bool
    holes: np.ndarray  # (H, W) bool
    n_holes: int
    largest_hole_mm2: float
    filled_mm2: float
    by_normals_mm2: float
    largest_by_normals_mm2: float


def _enclosed(
    core: np.ndarray,
    offish: np.ndarray,
    area: np.ndarray,
    geometry: Geometry,
    normals: np.ndarray | None,
    max_dropout_mm2: float,
) -> _Enclosed:
    """Step 4: small dropouts are filled, openings and large unmatched areas stay holes.

    ``offish``: pixels that show what lies behind the plate (matched off its surface, dark, unseen). A
    larger unmatched area is filled when its photometric normals follow the fitted surface's.
    """
    n_lab, labels = cv2.connectedComponents((~core).view(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    inner = np.ones(n_lab, bool)
    inner[border] = False
    inner[0] = False  # label 0 is the core
    lab = labels.ravel()
    count = np.bincount(lab, minlength=n_lab)
    n_offish = np.bincount(lab, weights=offish.ravel().astype(np.float64), minlength=n_lab)
    area_lab = np.bincount(
        lab, weights=np.nan_to_num(area, nan=0.0).ravel().astype(np.float64), minlength=n_lab
    )
    no_depth_behind = inner & (n_offish <= DROPOUT_MAX_OFF_SHARE * count)
    fill = no_depth_behind & (area_lab <= max_dropout_mm2)
    larger = no_depth_behind & ~fill
    by_normals = np.zeros(n_lab, bool)
    if normals is not None and larger.any():
        # a larger unmatched area is plate if its photometric normals follow the plate's surface: with no
        # stereo depth in it, filling it lets no depth step into the solve, only normals that agree
        rows, cols = np.nonzero(larger[labels])
        cos = np.einsum(
            "mc,mc->m", np.asarray(normals[rows, cols], np.float32), geometry.normals_at(rows, cols)
        )
        agree = np.nan_to_num(cos, nan=-1.0) >= math.cos(math.radians(DROPOUT_NORMAL_DEG))
        n_agree = np.bincount(labels[rows, cols], weights=agree.astype(np.float64), minlength=n_lab)
        by_normals = larger & (n_agree > 0.5 * count)
        fill |= by_normals
    hole_lab = inner & ~fill
    small = fill & ~by_normals
    return _Enclosed(
        filled=fill[labels],
        holes=hole_lab[labels],
        n_holes=int(np.count_nonzero(hole_lab)),
        largest_hole_mm2=float(area_lab[hole_lab].max()) if hole_lab.any() else 0.0,
        filled_mm2=float(area_lab[small].sum()),
        by_normals_mm2=float(area_lab[by_normals].sum()),
        largest_by_normals_mm2=float(area_lab[by_normals].max()) if by_normals.any() else 0.0,
    )


def _with_rim(
    region: np.ndarray, reachable: np.ndarray, dark: np.ndarray, reach_px: int
) -> np.ndarray:
    """Step 5: the region grown by the ``reachable`` (unmatched, lit) pixels next to it that darkness bounds
    within ``reach_px`` (a dark background), up to ``reach_px`` steps."""
    near_dark = cv2.distanceTransform((~dark).view(np.uint8), cv2.DIST_L2, 3) <= reach_px + 1
    return grow_within(region, region | (reachable & near_dark), reach_px)


def grow_within(seed: np.ndarray, allowed: np.ndarray, steps: int) -> np.ndarray:
    """(H, W) bool: ``seed`` grown through the ``allowed`` pixels (8-neighbours), at most ``steps`` pixels
    (``seed`` within ``allowed``)."""
    kernel = np.ones((3, 3), np.uint8)
    keep = allowed.view(np.uint8)
    grown: np.ndarray = seed.view(np.uint8).copy()
    for _ in range(steps):
        nxt: np.ndarray = np.bitwise_and(cv2.dilate(grown, kernel), keep)
        if np.array_equal(nxt, grown):
            break
        grown = nxt
    return grown.astype(bool)


def _surroundings_step(
    region: np.ndarray,
    off: np.ndarray,
    no_depth: np.ndarray,
    depth: np.ndarray,
    z_fit: np.ndarray,
    step_zone_px: int,
    reach_px: int,
) -> np.ndarray:
    """Step 7: the depth step (mm) to the surroundings along the boundary, for telling edge artefacts from
    defects: to the nearest surroundings with a depth (``off``), unless ``no_depth`` (darkness: no depth,
    a dark background; ``+inf``) is nearer; NaN away from the boundary (see ``Segmentation``)."""
    outside = ~region
    zone = region & (cv2.distanceTransform(region.view(np.uint8), cv2.DIST_L2, 3) <= step_zone_px)
    dist_off, nearest_off = _nearest(off & outside)
    dist_dark = cv2.distanceTransform((~(no_depth & outside)).view(np.uint8), cv2.DIST_L2, 3)
    reach = step_zone_px + 2 * reach_px + 4  # past the unmatched strip beside the plate
    step = np.full(region.shape, np.nan, np.float32)
    use_off = zone & (dist_off <= np.minimum(dist_dark, reach))
    step[zone & ~use_off & (dist_dark <= reach)] = np.inf
    step[use_off] = depth.ravel()[nearest_off[use_off]] - z_fit[use_off]
    return step


def _protrusions(
    core: np.ndarray,
    residual: np.ndarray,
    mm_per_px: float,
    width_mm: float,
    max_residual_mm: float,
) -> np.ndarray:
    """(H, W) bool: the parts of ``core`` narrower than ``width_mm`` (:func:`narrow_parts`) of which
    ``PROTRUSION_SHARE`` have ``|residual|`` (mm) over ``max_residual_mm``."""
    parts = narrow_parts(core, mm_per_px, width_mm)
    if not parts.any():
        return parts
    n, labels = cv2.connectedComponents(parts.view(np.uint8), connectivity=8)
    res = np.abs(residual[parts])
    ok = np.isfinite(res)
    lab = labels[parts][ok]
    # a support's part holds the plate's edge strip next to it too (the reduced opening's slivers), whose depth
    # follows the surface: a part is a support when a good share of it (not necessarily half) leaves it
    above = np.bincount(lab, weights=(res[ok] > max_residual_mm).astype(np.float64), minlength=n)
    counted = np.bincount(lab, minlength=n)
    out = above > PROTRUSION_SHARE * counted
    out[0] = False
    kept: np.ndarray = out[labels] & parts
    return kept


def narrow_parts(core: np.ndarray, mm_per_px: float, width_mm: float) -> np.ndarray:
    """(H, W) bool: the parts of ``core`` narrower than ``width_mm``, removed by an opening with a disc of
    that diameter (none when ``width_mm`` or ``mm_per_px`` is not positive).

    The opening runs on the mask reduced so the disc is ~15 px across (a plate is smooth at that scale);
    the reduction adds slivers along straight edges."""
    if width_mm <= 0 or not math.isfinite(mm_per_px) or mm_per_px <= 0:
        return np.zeros_like(core)
    h, w = core.shape
    d_px = width_mm / mm_per_px
    f = max(1, int(d_px // 15))
    small = (
        cv2.resize(
            core.astype(np.float32), (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA
        )
        > 0.5
    )
    k = max(3, int(round(d_px / f)) | 1)
    opened = cv2.morphologyEx(
        small.view(np.uint8), cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    )
    back = cv2.resize(opened, (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    parts: np.ndarray = core & ~back
    return parts


def outline_corners(core: np.ndarray, parts: np.ndarray, max_reach_px: float) -> np.ndarray:
    """(H, W) bool: the connected components of ``parts`` (within ``core``) that are corners of the plate's
    outline rather than supports reaching out of it (``CORNER_CONCAVITY_SHARE``).

    For each component: its reach, the largest distance of its pixels beyond the convex hull of the rest
    of ``core`` (less every component); and the depth of the concavity it leaves, the largest distance
    from the hull of the rest and the component of a pixel that this hull gains but neither fills. Only
    a component that reaches beyond the rest's hull, by at most ``max_reach_px`` (the radius of the
    opening that cut it off), can be a corner (a part inside a notch is not, nor surroundings at the
    plate's depth reaching out far from its corner)."""
    out = np.zeros_like(parts)
    rest = core & ~parts
    if not parts.any() or not rest.any():
        return out
    rest_hull = cv2.convexHull(cv2.findNonZero(rest.view(np.uint8)))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(parts.view(np.uint8), connectivity=8)
    for i in range(1, n):
        x, y, w, h = (int(v) for v in stats[i, :4])
        part = labels == i
        pts = np.argwhere(part)[:, ::-1]  # (x, y) of its pixels
        reach = _beyond_hull(rest_hull, pts)
        if not 0 < reach <= max_reach_px:
            continue
        m = int(math.ceil(2 * reach)) + 2  # the concavity beside a support lies within its reach
        window = (
            max(0, x - m),
            max(0, y - m),
            min(core.shape[1], x + w + m),
            min(core.shape[0], y + h + m),
        )
        if _concavity(rest_hull, rest, (part, pts), window) < CORNER_CONCAVITY_SHARE * reach:
            out |= part
    return out


def _filled_hull(points: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
    """(h, w) uint8: the convex polygon of ``points`` (N, 1, 2) filled on the window ``(x0, y0, x1, y1)``."""
    x0, y0, x1, y1 = window
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    hull = cv2.convexHull(points.reshape(-1, 1, 2).astype(np.int32))
    cv2.fillConvexPoly(mask, hull - np.array([x0, y0], np.int32), 1)
    return mask


def _beyond_hull(hull: np.ndarray, pts: np.ndarray) -> float:
    """How far (px) the pixels ``pts`` ((M, 2) x, y) reach beyond the convex polygon ``hull`` (N, 1, 2): the
    largest distance of one past the polygon's edge lines (0 when every pixel is inside)."""
    v = hull.reshape(-1, 2).astype(np.float64)
    edges = np.roll(v, -1, axis=0) - v
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    centre = v.mean(axis=0)
    normals *= np.where(np.einsum("kc,kc->k", normals, centre - v) > 0, -1.0, 1.0)[:, None]
    signed = (pts.astype(np.float64) @ normals.T) - np.einsum("kc,kc->k", normals, v)
    return float(max(0.0, signed.max(axis=1).max()))


def _concavity(
    rest_hull: np.ndarray,
    rest: np.ndarray,
    part_and_pts: tuple[np.ndarray, np.ndarray],
    window: tuple[int, int, int, int],
) -> float:
    """The depth (px) of the concavity beside a part (its mask and its pixels' (x, y)), within ``window``:
    see :func:`outline_corners`."""
    x0, y0, x1, y1 = window
    part, part_pts = part_and_pts
    pts = np.concatenate([rest_hull.reshape(-1, 2), part_pts]).astype(np.int32)
    hull = _filled_hull(pts, window)
    before = _filled_hull(rest_hull, window)
    gap = (hull > 0) & (before == 0) & ~rest[y0:y1, x0:x1] & ~part[y0:y1, x0:x1]
    if not gap.any():
        return 0.0
    return float(cv2.distanceTransform(hull, cv2.DIST_L2, 3)[gap].max())


def wide_parts(parts: np.ndarray, min_half_width_px: float) -> np.ndarray:
    """The connected components of ``parts`` (8-neighbour) at least ``2 min_half_width_px`` wide somewhere
    (slivers along an edge are not)."""
    if not parts.any():
        return parts
    inside = cv2.distanceTransform(parts.view(np.uint8), cv2.DIST_L2, 3)
    n, labels = cv2.connectedComponents(parts.view(np.uint8), connectivity=8)
    widest = np.zeros(n, np.float32)
    np.maximum.at(widest, labels[parts], inside[parts])
    wide = widest >= min_half_width_px
    wide[0] = False
    widened: np.ndarray = wide[labels]
    return widened


def _nearest(outside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (px, L2 5x5 mask) from each pixel to the nearest ``outside`` pixel, and that pixel's flat index."""
    src = (~outside).view(np.uint8)
    dist, labels = cv2.distanceTransformWithLabels(
        src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    zeros = np.flatnonzero(outside.ravel())
    if zeros.size == 0:
        return np.full(outside.shape, np.inf, np.float32), np.zeros(outside.shape, np.intp)
    return dist, zeros[np.clip(labels - 1, 0, zeros.size - 1)]
