"""The stations registered to one another: texture-matched overlaps, one pose-graph least squares.

A plate rolled about its long axis is a cylinder along the travel: its surface alone cannot fix a
station's travel along it, nor a turn about it. The plate's own texture can. Each overlap is matched
patch by patch on the photometric albedo (normalised cross-correlation, from where the current poses
put it), and each match is a pair of measured 3D points, one per station, that must coincide: along
the surface's normal to the surfaces' own noise (:data:`NORMAL_SD_MM`: this fixes the stations' tilt
and height), along the surface to the match's (:data:`MATCH_SD_PX`: this fixes the travel and the
yaw). All the stations' poses are then fitted at once to every pair of every overlap (stations two
apart too, where they share a view) and to the encoder's travels (a weak prior of
:data:`ENCODER_SD_MM`): a pose graph solved by least squares (soft-L1 at 3 standard deviations).

The result is checked on the surfaces themselves: in each overlap the distance along the normal from one
station's surface to the other's (RMS and max). A station whose overlap with the one before it has too
few matches, a surface distance RMS over the limit, or a travel that disagrees with the encoder by more
than :data:`ENCODER_LIMIT_MM` cannot be registered: the inspection ends in error naming it
(:class:`pipeline.formats.CaptureError`), never stitched wrongly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from pipeline.formats import CaptureError
from pipeline.judge.details import OverlapDetails

#: Standard deviation of the encoder's travel as a prior on each station's pose, mm.
ENCODER_SD_MM = 5.0
#: A refined travel further than this from the encoder's means a wrong registration (or a slipping
#: plate): the station is not stitched, mm.
ENCODER_LIMIT_MM = 50.0
#: An overlap needs at least this many matched patches.
MIN_MATCHES = 12
#: A patch matches where its normalised cross-correlation reaches this.
MIN_NCC = 0.6
#: The first search reaches this far around where the encoder's travel puts a patch, mm.
SEARCH_MM = 40.0
#: Standard deviation of a matched point pair along the surface's normal, mm: the two surfaces' own
#: noise (a match's error along the surface moves it within the tangent plane, not off it).
NORMAL_SD_MM = 0.1
#: Standard deviation of a match along the surface, pixels of the matched station.
MATCH_SD_PX = 0.5
#: Rounds of matching and fitting (a second round, from the fitted poses with a 3 px search, was
#: measured to change nothing: a match's position does not depend on where its search starts).
ROUNDS = 1
#: Patches per overlap, at most.
MAX_PATCHES = 400


@dataclass(frozen=True)
class StationView:
    """One station's reconstruction, what the registration and the mosaic need of it.

    Attributes
    ----------
    index : int
    label : str
        How errors name the station's bundle.
    points : (H, W, 3) float64
        Measured points, mm, the station's left camera frame; NaN off the plate.
    mask : (H, W) bool
    albedo : (H, W) float32
        Photometric albedo (NaN off the plate).
    normals : (H, W, 3) float32
        Unit normals towards the camera (NaN off the plate).
    K : (3, 3) float64
        The left camera's matrix (undistorted grid).
    encoder_mm : float
        The encoder's travel since station 0, mm.
    direction : (3,) float64
        The plate's direction of motion, left camera frame.
    """

    index: int
    label: str
    points: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    normals: np.ndarray
    K: np.ndarray
    encoder_mm: float
    direction: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.mask.shape
        return int(h), int(w)

    @cached_property
    def depth_mm(self) -> float:
        """Median depth of the plate (every 4th pixel), mm."""
        return float(np.median(self.points[::4, ::4, 2][self.mask[::4, ::4]]))

    @property
    def footprint_mm(self) -> float:
        """Median size of a pixel on the plate, mm."""
        return self.depth_mm / float(math.sqrt(self.K[0, 0] * self.K[1, 1]))


@dataclass(frozen=True)
class StationPoses:
    """The registration of every station into station 0's camera frame.

    Attributes
    ----------
    poses : list of (4, 4) float64
        ``G_k`` maps station ``k``'s camera frame into station 0's (``G_0`` the identity).
    travel_mm : list of float
        Refined travel of each station since station 0: how far the plate point under the head at
        station ``k`` moved along the direction, mm.
    overlaps : list of OverlapDetails
        Consecutive stations' overlaps (and two apart where they share a view).
    """

    poses: list[np.ndarray]
    travel_mm: list[float]
    overlaps: list[OverlapDetails]


def register_stations(views: list[StationView], *, seam_limit_mm: float) -> StationPoses:
    """Register the stations to one another (see the module docstring).

    Parameters
    ----------
    views : list of StationView
        In station order, station 0 first.
    seam_limit_mm : float
        The largest RMS surface distance in an overlap that still counts as registered, mm.

    Returns
    -------
    StationPoses

    Raises
    ------
    pipeline.formats.CaptureError
        A station that cannot be registered (named by its bundle).
    """
    n = len(views)
    direction = views[0].direction
    poses = [_translation(-direction * v.encoder_mm) for v in views]
    pairs = [(k, k + 1) for k in range(n - 1)] + [(k, k + 2) for k in range(n - 2)]
    search = [max(4, round(SEARCH_MM / v.footprint_mm)) for v in views]
    matches: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for round_ in range(ROUNDS):
        matches = {}
        for k, l in pairs:
            radius = search[l] if round_ == 0 else 3
            found = _match(views[k], views[l], poses[k], poses[l], radius)
            if found[0].shape[0] >= MIN_MATCHES or l == k + 1:
                matches[(k, l)] = found
        for k in range(n - 1):
            got = matches[(k, k + 1)][0].shape[0]
            if got < MIN_MATCHES:
                raise CaptureError(
                    f"{views[k + 1].label}: station: station {k + 1}'s overlap with station {k} cannot be "
                    f"registered: {got} patches of the plate's texture matched, at least {MIN_MATCHES} needed"
                )
        poses = _solve(views, poses, matches, direction)
    travel = [_travel(v, g, direction) for v, g in zip(views, poses, strict=True)]
    overlaps = [
        _overlap(views[k], views[l], poses[k], poses[l], matches[(k, l)])
        for k, l in sorted(matches)
    ]
    _check(views, travel, overlaps, seam_limit_mm)
    return StationPoses(poses=poses, travel_mm=travel, overlaps=overlaps)


def _check(
    views: list[StationView],
    travel: list[float],
    overlaps: list[OverlapDetails],
    seam_limit_mm: float,
) -> None:
    """A station whose travel or overlap says it was not registered: CaptureError naming it."""
    for view, t in zip(views, travel, strict=True):
        if abs(t - view.encoder_mm) > ENCODER_LIMIT_MM:
            raise CaptureError(
                f"{view.label}: station.travel_mm: station {view.index} cannot be registered: its overlap "
                f"puts it {t:.1f} mm along, the encoder {view.encoder_mm:.1f} mm (more than "
                f"{ENCODER_LIMIT_MM:g} mm apart)"
            )
    for o in overlaps:
        first, second = o.stations
        if second == first + 1 and not o.rms_mm <= seam_limit_mm:
            raise CaptureError(
                f"{views[second].label}: station: station {second} cannot be registered to station "
                f"{first}: their surfaces differ by {o.rms_mm:.2f} mm RMS over the overlap, more than "
                f"{seam_limit_mm:.2f} mm"
            )


def _translation(t: np.ndarray) -> np.ndarray:
    g = np.eye(4)
    g[:3, 3] = t
    return g


def _travel(view: StationView, pose: np.ndarray, direction: np.ndarray) -> float:
    """How far the plate point on the optical axis at this station moved since station 0, mm."""
    here = np.array([0.0, 0.0, view.depth_mm])
    before = pose[:3, :3] @ here + pose[:3, 3]
    return float(direction @ (here - before))


def _project(K: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(M, 2) pixels of points (M, 3) in a camera frame."""
    uv = (x @ K.T)[:, :2] / x[:, 2:3]
    out: np.ndarray = uv
    return out


def _sample(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of an (H, W) or (H, W, C) image at pixels (M, 2) (NaN where any neighbour is)."""
    mx = uv[:, 0].astype(np.float32).reshape(-1, 1)
    my = uv[:, 1].astype(np.float32).reshape(-1, 1)
    src = image.astype(np.float32) if image.dtype != np.float32 else image
    got = cv2.remap(
        src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan
    )
    out: np.ndarray = got.reshape(uv.shape[0], -1).astype(np.float64)
    return out


def _match(
    a: StationView, b: StationView, pose_a: np.ndarray, pose_b: np.ndarray, radius: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texture matches of station ``a``'s patches in station ``b``: their 3D points in each station's
    frame (M, 3), (M, 3), and ``b``'s unit normals there (M, 3), ``b``'s frame."""
    h, w = a.shape
    side = max(10, round(min(h, w) / 40)) // 2 * 2 + 1  # odd patch side ~ 1/40 of the image
    step = side
    rows = np.arange(side + 1, h - side - 1, step)
    cols = np.arange(side + 1, w - side - 1, step)
    vv, uu = np.meshgrid(rows, cols, indexing="ij")
    centres = np.stack([uu.ravel(), vv.ravel()], axis=1)
    ok = a.mask[centres[:, 1], centres[:, 0]]
    centres = centres[ok]
    xa = a.points[centres[:, 1], centres[:, 0]]
    rel = np.linalg.inv(pose_b) @ pose_a
    xb_pred = xa @ rel[:3, :3].T + rel[:3, 3]
    uv_b = _project(b.K, xb_pred)
    hb, wb = b.shape
    reach = side // 2 + radius + 2
    inside = (
        (uv_b[:, 0] > reach)
        & (uv_b[:, 0] < wb - 1 - reach)
        & (uv_b[:, 1] > reach)
        & (uv_b[:, 1] < hb - 1 - reach)
    )
    centres, uv_b = centres[inside], uv_b[inside]
    if centres.shape[0] > MAX_PATCHES:
        keep = np.linspace(0, centres.shape[0] - 1, MAX_PATCHES).round().astype(int)
        centres, uv_b = centres[keep], uv_b[keep]
    alb_a = np.nan_to_num(a.albedo, nan=0.0).astype(np.float32)
    alb_b = np.nan_to_num(b.albedo, nan=0.0).astype(np.float32)
    r = side // 2
    found_a, found_b = [], []
    for (u, v), (pu, pv) in zip(centres, uv_b, strict=True):
        patch_mask = a.mask[v - r : v + r + 1, u - r : u + r + 1]
        if not patch_mask.all():
            continue
        iu, iv = int(round(pu)), int(round(pv))
        win = alb_b[iv - r - radius : iv + r + radius + 1, iu - r - radius : iu + r + radius + 1]
        win_mask = b.mask[
            iv - r - radius : iv + r + radius + 1, iu - r - radius : iu + r + radius + 1
        ]
        if not win_mask.all():
            continue
        patch = alb_a[v - r : v + r + 1, u - r : u + r + 1]
        if float(patch.std()) <= 1e-6:
            continue
        score = cv2.matchTemplate(win, patch, cv2.TM_CCOEFF_NORMED)
        _, best, _, (bx, by) = cv2.minMaxLoc(score)
        if best < MIN_NCC or not (0 < bx < score.shape[1] - 1 and 0 < by < score.shape[0] - 1):
            continue
        dx = _parabola(score[by, bx - 1 : bx + 2])
        dy = _parabola(score[by - 1 : by + 2, bx])
        found_a.append((u, v))
        found_b.append((iu - radius + bx + dx, iv - radius + by + dy))
    if not found_a:
        empty = np.empty((0, 3))
        return empty, empty, empty
    pa = np.asarray(found_a, dtype=np.float64)
    pb = np.asarray(found_b, dtype=np.float64)
    xa = a.points[pa[:, 1].astype(int), pa[:, 0].astype(int)]
    xb = _sample(b.points, pb)
    nb = _sample(b.normals, pb)
    nb /= np.linalg.norm(nb, axis=1, keepdims=True)
    good = np.isfinite(xa).all(axis=1) & np.isfinite(xb).all(axis=1) & np.isfinite(nb).all(axis=1)
    return xa[good], xb[good], nb[good]


def _parabola(three: np.ndarray) -> float:
    """Sub-pixel offset of a peak from three samples around it."""
    left, mid, right = (float(v) for v in three)
    den = left - 2.0 * mid + right
    return 0.0 if den >= 0 else float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))


def _solve(
    views: list[StationView],
    poses: list[np.ndarray],
    matches: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]],
    direction: np.ndarray,
) -> list[np.ndarray]:
    """Every station's pose (1 on; station 0 holds) fitted at once to all matches and the encoder."""
    n = len(views)
    x0 = np.concatenate([_params(g) for g in poses[1:]])
    encoder = np.array([v.encoder_mm for v in views])
    here = [np.array([0.0, 0.0, v.depth_mm]) for v in views]
    tangential = [MATCH_SD_PX * v.footprint_mm for v in views]

    def unpack(x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        out = [(np.eye(3), np.zeros(3))]
        for k in range(n - 1):
            p = x[6 * k : 6 * k + 6]
            out.append((Rotation.from_rotvec(p[:3]).as_matrix(), p[3:]))
        return out

    def residuals(x: np.ndarray) -> np.ndarray:
        rt = unpack(x)
        parts = []
        for (k, l), (xa, xb, nb) in matches.items():
            (ra, ta), (rb, tb) = rt[k], rt[l]
            r = (xa @ ra.T + ta) - (xb @ rb.T + tb)
            normal = nb @ rb.T
            along = np.einsum("ij,ij->i", r, normal)
            parts.append(along / NORMAL_SD_MM)
            parts.append((r - along[:, None] * normal).ravel() / tangential[l])
        for k in range(1, n):
            r, t = rt[k]
            moved = direction @ (here[k] - (r @ here[k] + t))
            parts.append(np.array([(moved - encoder[k]) / ENCODER_SD_MM]))
        return np.concatenate(parts)

    fit = least_squares(residuals, x0, loss="soft_l1", f_scale=3.0, method="trf", x_scale="jac")
    return [np.eye(4)] + [_pose(r, t) for r, t in unpack(fit.x)[1:]]


def _params(g: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(g[:3, :3]).as_rotvec(), g[:3, 3]])


def _pose(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    g = np.eye(4)
    g[:3, :3] = r
    g[:3, 3] = t
    return g


def _overlap(
    a: StationView,
    b: StationView,
    pose_a: np.ndarray,
    pose_b: np.ndarray,
    found: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> OverlapDetails:
    """The two surfaces compared over their overlap: ``b``'s points (every 4th pixel) moved into ``a``'s
    frame, against ``a``'s surface at the same pixel, along ``a``'s normal."""
    xa, xb, _ = found
    rel_ab = np.linalg.inv(pose_a) @ pose_b
    moved = xb @ rel_ab[:3, :3].T + rel_ab[:3, 3]
    match_rms = float(np.sqrt(np.mean(np.sum((moved - xa) ** 2, axis=1)))) if xa.size else math.nan
    step = 4
    pts = b.points[::step, ::step][b.mask[::step, ::step]]
    inb = pts @ rel_ab[:3, :3].T + rel_ab[:3, 3]
    uv = _project(a.K, inb)
    ha, wa = a.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= wa - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= ha - 1)
    inb, uv = inb[inside], uv[inside]
    on_a = _sample(a.points, uv)
    nrm = _sample(a.normals, uv)
    dist = np.einsum("ij,ij->i", inb - on_a, nrm)
    dist = dist[np.isfinite(dist)]
    rms = float(np.sqrt(np.mean(dist**2))) if dist.size else math.nan
    worst = float(np.max(np.abs(dist))) if dist.size else math.nan
    return OverlapDetails(
        stations=[a.index, b.index],
        matches=int(xa.shape[0]),
        match_rms_mm=round(match_rms, 3),
        rms_mm=round(rms, 3),
        max_mm=round(worst, 3),
        points=int(dist.size),
    )
