"""The cell simulator: what the binocular head with a ring of lights sees, rendered from a known truth.

A plate is a height field ``h(x_p, y_p)`` in a *plate frame* (x_p, y_p in the plate's plane, z_p
pointing away from the cameras, origin at the plate centre, ``h(0, 0) = 0``); ``T_cam_plate`` maps
plate-frame points into the left-camera frame. Every pixel of a camera is rendered as a real
calibrated camera sees it: the raw (distorted) pixel centre is undistorted to its ray with the
camera's K and distortion (iterative ``cv2.undistortPoints``), the ray is intersected with the
surface (analytic for plane, cylinder and sphere; Newton steps along the ray for the saddle and for
dents), and the surface point is shaded there. No orthographic shortcut.

Shading (intensities as fractions of the sensor's full scale ``2**bit_depth - 1``)::

    I_k = exposure * e_k * (albedo * max(0, n . l_k) + specular * [n . l_k > 0] * max(0, n . h_k)**shininess)
          + dark + N(0, noise**2)

with ``h_k`` the Blinn-Phong half vector of the light and the per-pixel view direction. Attached
shadows come from ``max(0, .)``; cast shadows are not modelled. Pixels off the plate see a dark,
slightly textured conveyor plane behind it (lit by the same lights). The albedo is a painted/rusty
texture fixed to the plate (a function of plate coordinates), so both cameras see the same texture.
Values are quantised to ``bit_depth`` and saturate at full scale.

The plate's material may have another outline than its size's rectangle (``PlateSpec.outline``) and
openings (``PlateSpec.cutouts``); rays that miss the material see what lies behind it. Instead of the
conveyor a plate may lie over a lit, textured shop floor with supports standing on it
(``PlateSpec.floor``), shaded by the same lights (no cast shadows, no interreflections). With these
options off the bundle is bit-identical to what it was without them.

Conventions (docs/formats.md): mm, pixels, radians in code (degrees only in the spec dataclasses, named
``*_deg``); OpenCV camera frame (x right, y down, z forward); left camera = reference frame;
``X_right = R @ X_left + T``; light directions are unit vectors from the surface towards the light
(``l_z < 0``); normals point out of the surface towards the cameras (``n_z < 0``).
"""

from __future__ import annotations

import json
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from .camera import CameraModel, StereoRig
from .formats import (
    CAPTURE_FORMAT,
    TARGET_FORMAT,
    CaptureFile,
    StereoCalibrationFile,
    TargetFile,
)
from .io import calibration_document
from .lights import Lights
from .parallel import default_workers

# Reference head: fx = 900 px at 1224 px width (a 3000 mm plate at 3000 mm fills ~74 % of the width).
_FX_PER_WIDTH_PX = 900.0 / 1224.0
_BASELINE_MM = 800.0
_TOE_IN_DEG = 10.0
#: Finest plate texture step, mm per texel (coarser when a camera pixel covers more than 2 texels).
_TEXEL_MM = 1.5
#: Conveyor plane behind the plate: this far (mm, along z_p) behind the plate's farthest point.
_CONVEYOR_GAP_MM = 40.0
#: Fixed-point iterations of cv2.undistortPoints: 10 reach 5e-13 px re-projection error on the default
#: rig's lenses (5: 7e-7 px); a count-only criterion skips the per-point error check (3x faster).
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT, 12, 0.0)
_CAPTURED_AT = "2026-01-01T00:00:00Z"
#: Calibration boards are seen within 50 deg of head-on by both cameras.
_BOARD_MIN_COS = math.cos(math.radians(50.0))

ShapeName = Literal["plane", "cylinder", "sphere", "saddle"]


# --------------------------------------------------------------------------- rig


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def default_rig(*, width: int = 1224, height: int = 1024) -> StereoRig:
    """The simulated binocular head.

    The left camera is the reference; it looks along +z at a plate ~3000 mm away and covers a
    field of ``width * 3000 / fx`` x ``height * 3000 / fx`` mm there (4080 x 3413 mm at any
    resolution, since ``fx = 900 * width / 1224`` px). The right camera sits 800 mm along +x,
    toed in by 10 deg (plus small residual rotations) so both cameras see the plate.

    Parameters
    ----------
    width, height : int
        Image size in pixels (both cameras), at least 64 each.

    Returns
    -------
    StereoRig
        ``X_right = R @ X_left + T`` (mm), as ``cv2.stereoCalibrate`` gives it. Distortion
        ``k1 k2 p1 p2 k3`` ~ ``(-0.08, 0.05, 4e-4, -3e-4, 0)`` (left), slightly different right.
    """
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))):
        raise TypeError(f"width, height: expected integers, got {type(width).__name__}, {type(height).__name__}")
    if width < 64 or height < 64:
        raise ValueError(f"width, height: expected at least 64 x 64 pixels, got {width} x {height}")
    s = width / 1224.0
    fx = _FX_PER_WIDTH_PX * width
    K_left = np.array([[fx, 0.0, (width - 1) / 2 + 3.2 * s], [0.0, fx, (height - 1) / 2 - 2.1 * s], [0.0, 0.0, 1.0]])
    K_right = np.array(
        [[fx * 1.004, 0.0, (width - 1) / 2 - 2.5 * s], [0.0, fx * 1.004, (height - 1) / 2 + 1.8 * s], [0.0, 0.0, 1.0]]
    )
    left = CameraModel(K_left, np.array([-0.08, 0.05, 4e-4, -3e-4, 0.0]), (width, height))
    right = CameraModel(K_right, np.array([-0.075, 0.045, -3e-4, 2e-4, 0.0]), (width, height))
    # Rows of R are the right camera's axes in the left frame; its optical axis turns towards -x.
    R = _rot_x(math.radians(0.25)) @ _rot_z(math.radians(-0.15)) @ _rot_y(math.radians(_TOE_IN_DEG))
    centre_right = np.array([_BASELINE_MM, 0.0, 0.0])
    T = -R @ centre_right
    return StereoRig(left, right, R, T)


def _raw_pixel_rays(camera: CameraModel) -> np.ndarray:
    """Rays ``(x, y, 1)`` of the raw (distorted) pixel centres, (H, W, 3) float64, camera frame."""
    w, h = camera.image_size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(pts, camera.K, camera.dist, None, np.eye(3), np.eye(3), _UNDISTORT_CRITERIA)
    rays = np.empty((h, w, 3), dtype=np.float64)
    rays[..., :2] = xy.reshape(h, w, 2)
    rays[..., 2] = 1.0
    return rays


# --------------------------------------------------------------------------- plate


@dataclass(frozen=True)
class Dent:
    """A local dent (``depth_mm > 0``, into the plate, away from the cameras) or bump (``< 0``).

    Profile ``depth_mm * (1 - r^2 / radius_mm^2)^3`` for ``r < radius_mm`` (C2-smooth, zero outside),
    added to the plate's height along z_p; centre ``(x_mm, y_mm)`` in plate coordinates.
    """

    x_mm: float
    y_mm: float
    radius_mm: float
    depth_mm: float

    def __post_init__(self) -> None:
        for name in ("x_mm", "y_mm", "radius_mm", "depth_mm"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"Dent.{name}: expected a finite number, got {getattr(self, name)}")
        if self.radius_mm <= 0:
            raise ValueError(f"Dent.radius_mm: expected > 0, got {self.radius_mm}")


@dataclass(frozen=True)
class Cutout:
    """An opening cut through the plate: a rounded rectangle in plate coordinates (a circle is one).

    Attributes
    ----------
    x_mm, y_mm : float
        Centre, plate frame, mm.
    width_mm, height_mm : float
        Extent along x_p and y_p, mm (> 0).
    corner_mm : float
        Corner radius, mm, ``0 <= corner_mm <= min(width_mm, height_mm) / 2``; equal to half of both
        sides: a circle or a slot with round ends.

    Notes
    -----
    An opening that overlaps the plate's outline is a notch in its edge. Rays through an opening
    see what lies behind the plate (the conveyor, or the floor and the supports).
    """

    x_mm: float
    y_mm: float
    width_mm: float
    height_mm: float
    corner_mm: float = 0.0

    def __post_init__(self) -> None:
        for name in ("x_mm", "y_mm", "width_mm", "height_mm", "corner_mm"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"Cutout.{name}: expected a finite number, got {getattr(self, name)}")
            object.__setattr__(self, name, value)
        if self.width_mm <= 0 or self.height_mm <= 0:
            raise ValueError(f"Cutout.width_mm, height_mm: expected > 0, got {self.width_mm}, {self.height_mm}")
        if not 0 <= self.corner_mm <= min(self.width_mm, self.height_mm) / 2 + 1e-9:
            raise ValueError(
                f"Cutout.corner_mm: expected in [0, {min(self.width_mm, self.height_mm) / 2:g}] mm, got {self.corner_mm}"
            )

    @classmethod
    def circle(cls, x_mm: float, y_mm: float, radius_mm: float) -> "Cutout":
        """A round hole of ``radius_mm`` centred at ``(x_mm, y_mm)`` (plate frame, mm)."""
        if not (math.isfinite(radius_mm) and radius_mm > 0):
            raise ValueError(f"Cutout.radius_mm: expected > 0, got {radius_mm}")
        return cls(x_mm, y_mm, 2.0 * radius_mm, 2.0 * radius_mm, radius_mm)

    def signed_distance(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of plate points to the opening's edge: negative inside the opening."""
        r = self.corner_mm
        qx = np.abs(np.asarray(x_mm, np.float64) - self.x_mm) - (self.width_mm / 2 - r)
        qy = np.abs(np.asarray(y_mm, np.float64) - self.y_mm) - (self.height_mm / 2 - r)
        outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
        return outside + np.minimum(np.maximum(qx, qy), 0.0) - r

    def boundary(self, step_mm: float) -> np.ndarray:
        """(M, 2) points along the opening's edge (plate frame, mm), counter-clockwise, at most ``step_mm`` apart."""
        r = self.corner_mm
        a, b = self.width_mm / 2 - r, self.height_mm / 2 - r
        corners = []
        for k, (cx, cy) in enumerate(((a, b), (-a, b), (-a, -b), (a, -b))):
            n_arc = int(math.ceil(r * math.pi / 2 / step_mm)) if r > 0 else 0
            t = k * math.pi / 2 + np.linspace(0.0, math.pi / 2, n_arc + 1)
            corners.append(np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], axis=1))
        return _densify(np.concatenate(corners), step_mm) + [self.x_mm, self.y_mm]


@dataclass(frozen=True)
class Support:
    """A block or rail standing on the floor under the plate: a box with sides along x_p and y_p.

    Attributes
    ----------
    x_mm, y_mm : float
        Centre of its footprint, plate frame, mm.
    size_x_mm, size_y_mm : float
        Footprint along x_p and y_p, mm (> 0); a rail is long in one of them.
    height_mm : float
        Height above the floor, mm (> 0, at most the floor's ``gap_mm``: it never reaches through
        the plate).
    albedo : float
        Mean albedo of the support (0..1); it carries the floor's texture scaled to this mean.
    """

    x_mm: float
    y_mm: float
    size_x_mm: float
    size_y_mm: float
    height_mm: float
    albedo: float = 0.35

    def __post_init__(self) -> None:
        for name in ("x_mm", "y_mm", "size_x_mm", "size_y_mm", "height_mm", "albedo"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"Support.{name}: expected a finite number, got {getattr(self, name)}")
            object.__setattr__(self, name, value)
        if self.size_x_mm <= 0 or self.size_y_mm <= 0 or self.height_mm <= 0:
            raise ValueError(
                f"Support.size_x_mm, size_y_mm, height_mm: expected > 0, got "
                f"{self.size_x_mm}, {self.size_y_mm}, {self.height_mm}"
            )
        if not 0 < self.albedo <= 1:
            raise ValueError(f"Support.albedo: expected in (0, 1], got {self.albedo}")


@dataclass(frozen=True)
class Floor:
    """A lit, textured shop floor under the plate, with the supports the plate lies on.

    Replaces the default dark conveyor (a plane 40 mm behind the plate). Floor and supports are
    lit by the same lights as the plate (no cast shadows) and seen by both cameras.

    Attributes
    ----------
    gap_mm : float
        Distance (mm, along the plate frame's z_p, away from the cameras) from the plate's farthest
        point to the floor plane, which is parallel to the plate's xy plane; > 0.
    albedo : float
        Mean albedo of the concrete (0..1); the default is about as bright as the painted plate.
    texture : float
        Contrast of the floor's texture relative to the default (0: uniform; 1: grain, slow
        variation, stains, joints and painted lines).
    supports : tuple of Support
        Blocks or rails standing on the floor (see :func:`rail_supports`).
    """

    gap_mm: float = 300.0
    albedo: float = 0.55
    texture: float = 1.0
    supports: tuple[Support, ...] = ()

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gap_mm) and self.gap_mm > 0):
            raise ValueError(f"Floor.gap_mm: expected a distance > 0 mm, got {self.gap_mm}")
        if not (math.isfinite(self.albedo) and 0 < self.albedo <= 1):
            raise ValueError(f"Floor.albedo: expected in (0, 1], got {self.albedo}")
        if not (math.isfinite(self.texture) and 0 <= self.texture <= 3):
            raise ValueError(f"Floor.texture: expected a contrast in [0, 3], got {self.texture}")
        supports = tuple(self.supports)
        if not all(isinstance(s, Support) for s in supports):
            raise TypeError("Floor.supports: expected a tuple of Support")
        for i, s in enumerate(supports):
            if s.height_mm > self.gap_mm + 1e-9:
                raise ValueError(
                    f"Floor.supports[{i}].height_mm: expected at most the floor's gap_mm {self.gap_mm:g} mm "
                    f"(a taller support would reach through the plate), got {s.height_mm:g}"
                )
        object.__setattr__(self, "supports", supports)


def rail_supports(size_mm: tuple[float, float], gap_mm: float, n: int, *, heights_mm: tuple[float, float] = (200.0, 400.0),
                  width_mm: float = 150.0, overhang_mm: float = 500.0) -> tuple[Support, ...]:
    """``n`` rails across the plate, as a plate lies on them in a shop.

    The rails run along x_p (across a cylinder's curvature), evenly spaced over the middle 70 % of
    the plate's y_p extent, and reach ``overhang_mm`` beyond the plate on both sides, so that they
    are seen beside it. Their heights go evenly from ``heights_mm[0]`` to ``heights_mm[1]``, each
    at most ``gap_mm`` (a rail as high as the gap reaches the level of the plate's farthest point).

    Parameters
    ----------
    size_mm : (float, float)
        The plate's size (``PlateSpec.size_mm``), mm.
    gap_mm : float
        The floor's distance below the plate's farthest point (``Floor.gap_mm``), mm.
    n : int
        Number of rails, >= 1.

    Returns
    -------
    tuple of Support
    """
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n: expected an integer >= 1, got {n}")
    lo, hi = (float(v) for v in heights_mm)
    if not 0 < lo <= hi:
        raise ValueError(f"heights_mm: expected 0 < low <= high, got {heights_mm}")
    half_h = size_mm[1] / 2
    ys = np.linspace(-0.7 * half_h, 0.7 * half_h, n) if n > 1 else np.zeros(1)
    heights = np.linspace(lo, hi, n) if n > 1 else np.array([hi])
    return tuple(
        Support(0.0, float(y), size_mm[0] + 2 * overhang_mm, width_mm, float(min(hgt, gap_mm)))
        for y, hgt in zip(ys, heights)
    )


OutlineName = Literal["rectangle", "trapezoid", "curved"]
#: Trapezoid outline: the edge at y_p = +size_y / 2 is this share of the full width (centred).
TRAPEZOID_TOP = 0.6
#: Curved outline: the edge at y_p = +size_y / 2 is a circular arc through the two corners moved
#: in by this share of size_y, and through the middle of the straight edge (a convex bulge).
CURVED_SAGITTA = 0.2


@dataclass(frozen=True)
class PlateSpec:
    """The simulated plate and where it lies.

    Attributes
    ----------
    shape : {"plane", "cylinder", "sphere", "saddle"}
        Cylinder axis along the plate's y_p (second size axis), curved in x_p.
    radius_mm : float or None
        Cylinder/sphere radius; saddle: radius in x_p. Unused for a plane.
    radius2_mm : float or None
        Saddle: radius in y_p (default ``radius_mm``), curving the opposite way.
    convex : bool
        True: the plate bulges towards the cameras (edges farther away than the centre).
    size_mm : (float, float)
        Extent along x_p and y_p (projected onto the plate plane, not arc length).
    dents : tuple of Dent
    distance_mm : float
        Distance from the left camera to the plate centre, along the optical axis.
    tilt_deg : (float, float)
        Rotations about the camera x and y axes of the plate relative to facing the camera.
    in_plane_deg : float
        Rotation of the plate about its own normal (z_p).
    outline : {"rectangle", "trapezoid", "curved"} or sequence of (x, y)
        The plate's outline in plate coordinates, inside the ``size_mm`` box: the box itself; a
        trapezoid whose edge at ``y_p = +size_y / 2`` is :data:`TRAPEZOID_TOP` of the full width;
        the box with its ``y_p = +size_y / 2`` edge replaced by a convex circular arc through the
        corners moved in by :data:`CURVED_SAGITTA` of ``size_y`` (a developed plate's curved
        edge); or a simple polygon given by its vertices, mm.
    cutouts : tuple of Cutout
        Openings through the plate (holes inside it, notches where they overlap the outline).
    floor : Floor or None
        None: the dark conveyor 40 mm behind the plate. Otherwise a lit, textured shop floor and
        the supports standing on it.
    """

    shape: ShapeName = "cylinder"
    radius_mm: float | None = 5000.0
    radius2_mm: float | None = None
    convex: bool = True
    size_mm: tuple[float, float] = (3000.0, 3000.0)
    dents: tuple[Dent, ...] = ()
    distance_mm: float = 3000.0
    tilt_deg: tuple[float, float] = (3.0, -2.0)
    in_plane_deg: float = 0.0
    outline: OutlineName | tuple[tuple[float, float], ...] = "rectangle"
    cutouts: tuple[Cutout, ...] = ()
    floor: Floor | None = None

    def __post_init__(self) -> None:
        if self.shape not in ("plane", "cylinder", "sphere", "saddle"):
            raise ValueError(f"PlateSpec.shape: expected plane, cylinder, sphere or saddle, got {self.shape!r}")
        size = tuple(float(v) for v in self.size_mm)
        if len(size) != 2 or not all(math.isfinite(v) and v > 0 for v in size):
            raise ValueError(f"PlateSpec.size_mm: expected two positive sizes in mm, got {self.size_mm}")
        object.__setattr__(self, "size_mm", size)
        half_w, half_h = size[0] / 2, size[1] / 2
        if self.shape != "plane":
            if self.radius_mm is None or not math.isfinite(self.radius_mm) or self.radius_mm <= 0:
                raise ValueError(f"PlateSpec.radius_mm: expected a positive radius for a {self.shape}, got {self.radius_mm}")
            need = {"cylinder": half_w, "sphere": math.hypot(half_w, half_h), "saddle": half_w}[self.shape]
            if self.radius_mm <= need:
                raise ValueError(
                    f"PlateSpec.radius_mm: expected > {need:.1f} mm for a {self.shape} of size {size}, got {self.radius_mm}"
                )
        if self.shape == "saddle" and self.radius2_mm is not None:
            if not math.isfinite(self.radius2_mm) or self.radius2_mm <= half_h:
                raise ValueError(f"PlateSpec.radius2_mm: expected > {half_h:.1f} mm for a saddle, got {self.radius2_mm}")
        if not math.isfinite(self.distance_mm) or self.distance_mm <= 0:
            raise ValueError(f"PlateSpec.distance_mm: expected > 0, got {self.distance_mm}")
        tilt = tuple(float(v) for v in self.tilt_deg)
        if len(tilt) != 2 or not all(math.isfinite(v) and abs(v) < 60 for v in tilt):
            raise ValueError(f"PlateSpec.tilt_deg: expected two angles within +-60 deg, got {self.tilt_deg}")
        object.__setattr__(self, "tilt_deg", tilt)
        if not math.isfinite(self.in_plane_deg):
            raise ValueError(f"PlateSpec.in_plane_deg: expected a finite angle, got {self.in_plane_deg}")
        dents = tuple(self.dents)
        if not all(isinstance(d, Dent) for d in dents):
            raise TypeError("PlateSpec.dents: expected a tuple of Dent")
        object.__setattr__(self, "dents", dents)
        if isinstance(self.outline, str):
            if self.outline not in ("rectangle", "trapezoid", "curved"):
                raise ValueError(
                    f"PlateSpec.outline: expected rectangle, trapezoid, curved or polygon vertices, got {self.outline!r}"
                )
        else:
            vertices = np.asarray(self.outline, dtype=np.float64)
            if vertices.ndim != 2 or vertices.shape[0] < 3 or vertices.shape[1] != 2 or not np.isfinite(vertices).all():
                raise ValueError(
                    f"PlateSpec.outline: expected at least 3 finite (x, y) vertices in mm, got shape {vertices.shape}"
                )
            if np.any(np.abs(vertices) > np.array([half_w, half_h]) + 1e-6):
                raise ValueError(
                    f"PlateSpec.outline: expected vertices inside the size_mm box |x| <= {half_w:g}, |y| <= {half_h:g} mm"
                )
            object.__setattr__(self, "outline", tuple((float(x), float(y)) for x, y in vertices))
        cutouts = tuple(self.cutouts)
        if not all(isinstance(c, Cutout) for c in cutouts):
            raise TypeError("PlateSpec.cutouts: expected a tuple of Cutout")
        object.__setattr__(self, "cutouts", cutouts)
        if self.floor is not None and not isinstance(self.floor, Floor):
            raise TypeError(f"PlateSpec.floor: expected a Floor or None, got {type(self.floor).__name__}")

    @property
    def radius2(self) -> float | None:
        """Saddle radius along y_p (``radius2_mm`` or ``radius_mm``), mm; None for other shapes."""
        if self.shape != "saddle":
            return None
        return self.radius2_mm if self.radius2_mm is not None else self.radius_mm


def plate_pose(plate: PlateSpec) -> np.ndarray:
    """``T_cam_plate``: (4, 4) float64 mapping plate-frame points (mm) into the left-camera frame.

    ``R = Rx(tilt_x) @ Ry(tilt_y) @ Rz(in_plane)``, translation ``(0, 0, distance_mm)``.
    """
    tx, ty = (math.radians(a) for a in plate.tilt_deg)
    T = np.eye(4)
    T[:3, :3] = _rot_x(tx) @ _rot_y(ty) @ _rot_z(math.radians(plate.in_plane_deg))
    T[:3, 3] = (0.0, 0.0, plate.distance_mm)
    return T


def _densify(polygon: np.ndarray, step_mm: float) -> np.ndarray:
    """A closed polygon (V, 2) with points inserted so that no edge is longer than ``step_mm``."""
    out = []
    nxt = np.roll(polygon, -1, axis=0)
    for a, b in zip(polygon, nxt):
        length = float(np.hypot(*(b - a)))
        if length <= 1e-9:
            continue
        n = max(1, int(math.ceil(length / step_mm)))
        t = np.arange(n)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out)


def _curved_edge(plate: PlateSpec) -> tuple[float, float]:
    """Centre y (mm) and radius (mm) of the circle whose arc is the curved outline's edge."""
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
    sag = CURVED_SAGITTA * plate.size_mm[1]
    rho = (half_w * half_w + sag * sag) / (2.0 * sag)
    return half_h - rho, rho


def outline_polygon(plate: PlateSpec, *, step_mm: float = 20.0) -> np.ndarray:
    """The plate's outline as a closed polygon, counter-clockwise (x right, y up), plate frame.

    Parameters
    ----------
    plate : PlateSpec
    step_mm : float
        Longest edge of the polygon, mm (arcs and long sides are subdivided).

    Returns
    -------
    (V, 2) float64
        Vertices ``(x_p, y_p)`` in mm; the last connects to the first. Openings are not included
        (see ``Cutout.boundary``).
    """
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
    if not (math.isfinite(step_mm) and step_mm > 0):
        raise ValueError(f"step_mm: expected > 0, got {step_mm}")
    if not isinstance(plate.outline, str):
        corners = np.array(plate.outline, dtype=np.float64)
        area2 = np.sum(corners[:, 0] * np.roll(corners[:, 1], -1) - np.roll(corners[:, 0], -1) * corners[:, 1])
        return _densify(corners if area2 > 0 else corners[::-1], step_mm)
    if plate.outline == "rectangle":
        corners = np.array([[-half_w, -half_h], [half_w, -half_h], [half_w, half_h], [-half_w, half_h]])
    elif plate.outline == "trapezoid":
        top = TRAPEZOID_TOP * half_w
        corners = np.array([[-half_w, -half_h], [half_w, -half_h], [top, half_h], [-top, half_h]])
    else:
        yc, rho = _curved_edge(plate)
        a0 = math.atan2(half_h - CURVED_SAGITTA * plate.size_mm[1] - yc, half_w)
        n = max(2, int(math.ceil(rho * (math.pi - 2 * a0) / step_mm)))
        t = np.linspace(a0, math.pi - a0, n + 1)
        arc = np.stack([rho * np.cos(t), yc + rho * np.sin(t)], axis=1)
        corners = np.concatenate([[[-half_w, -half_h], [half_w, -half_h]], arc])
    return _densify(corners, step_mm)


def _inside_outline(plate: PlateSpec, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
    box = (np.abs(x) <= half_w) & (np.abs(y) <= half_h)
    if plate.outline == "rectangle":
        return box
    if plate.outline == "trapezoid":
        with np.errstate(invalid="ignore"):
            return box & (np.abs(x) <= half_w * (1.0 - 0.5 * (1.0 - TRAPEZOID_TOP) * (1.0 + y / half_h)))
    if plate.outline == "curved":
        yc, rho = _curved_edge(plate)
        return box & (x * x + (y - yc) ** 2 <= rho * rho)
    # a polygon: even-odd crossing count over its edges
    vertices = np.array(plate.outline, dtype=np.float64)
    inside = np.zeros(np.shape(x), dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        for (x0, y0), (x1, y1) in zip(vertices, np.roll(vertices, -1, axis=0)):
            if y0 == y1:
                continue
            crosses = ((y0 > y) != (y1 > y)) & (x < x0 + (y - y0) * (x1 - x0) / (y1 - y0))
            inside ^= crosses
    return inside & box


def plate_region(plate: PlateSpec, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
    """Whether plate-frame points lie on the plate's material: inside its outline, outside its openings.

    Parameters
    ----------
    plate : PlateSpec
    x_mm, y_mm : array_like, same shape
        Plate-frame coordinates, mm (NaN: not on the plate).

    Returns
    -------
    bool array of that shape
        True on the plate (its edge included).
    """
    x = np.asarray(x_mm, dtype=np.float64)
    y = np.asarray(y_mm, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"x_mm, y_mm: expected the same shape, got {x.shape} and {y.shape}")
    inside = _inside_outline(plate, x, y)
    for cut in plate.cutouts:
        with np.errstate(invalid="ignore"):
            inside &= ~(cut.signed_distance(x, y) < 0)
    return inside


def plate_height(plate: PlateSpec, x_mm: np.ndarray, y_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Height field of the plate and its analytic gradient.

    Parameters
    ----------
    plate : PlateSpec
    x_mm, y_mm : array_like, same shape
        Plate-frame coordinates, mm (inside the domain of the shape: ``|x| < radius`` etc.).

    Returns
    -------
    h, h_x, h_y : arrays of that shape, float64
        ``h`` along z_p in mm (away from the cameras), and ``dh/dx_p``, ``dh/dy_p``.

    Notes
    -----
    Convex cylinder: ``h = R - sqrt(R^2 - x^2)``; concave: its negative. Sphere likewise with
    ``x^2 + y^2``. Saddle: ``c * ((R1 - sqrt(R1^2 - x^2)) - (R2 - sqrt(R2^2 - y^2)))``. Dents add
    ``depth * (1 - r^2/rho^2)^3`` inside their radius.
    """
    x = np.asarray(x_mm, dtype=np.float64)
    y = np.asarray(y_mm, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"x_mm, y_mm: expected the same shape, got {x.shape} and {y.shape}")
    c = 1.0 if plate.convex else -1.0
    if plate.shape == "plane":
        h = np.zeros_like(x)
        hx = np.zeros_like(x)
        hy = np.zeros_like(x)
    elif plate.shape == "cylinder":
        R = plate.radius_mm
        root = np.sqrt(R * R - x * x)
        h = c * (R - root)
        hx = c * x / root
        hy = np.zeros_like(x)
    elif plate.shape == "sphere":
        R = plate.radius_mm
        root = np.sqrt(R * R - x * x - y * y)
        h = c * (R - root)
        hx = c * x / root
        hy = c * y / root
    else:  # saddle
        R1, R2 = plate.radius_mm, plate.radius2
        r1 = np.sqrt(R1 * R1 - x * x)
        r2 = np.sqrt(R2 * R2 - y * y)
        h = c * ((R1 - r1) - (R2 - r2))
        hx = c * x / r1
        hy = -c * y / r2
    for d in plate.dents:
        dx = x - d.x_mm
        dy = y - d.y_mm
        q = (dx * dx + dy * dy) / (d.radius_mm * d.radius_mm)
        inside = q < 1.0
        one_q = np.where(inside, 1.0 - q, 0.0)
        h = h + d.depth_mm * one_q**3
        slope = -6.0 * d.depth_mm * one_q**2 / (d.radius_mm * d.radius_mm)
        hx = hx + slope * dx
        hy = hy + slope * dy
    return h, hx, hy


@dataclass(frozen=True)
class _Hits:
    """Ray hits: ``s`` ray parameter, plate-frame point, camera-frame normal, whether on the plate, and
    which surface was hit (:data:`SURFACE_PLATE`, :data:`SURFACE_CONVEYOR`, :data:`SURFACE_FLOOR` or
    ``SURFACE_SUPPORT + k`` for support k)."""

    s: np.ndarray  # (...,) float64
    xyz_plate: np.ndarray  # (..., 3) float64
    normals: np.ndarray  # (..., 3) float64, camera frame, towards the cameras
    on_plate: np.ndarray  # (...,) bool
    surface: np.ndarray  # (...,) int8


#: Codes of ``truth.npz: surface``: what each pixel sees.
SURFACE_PLATE, SURFACE_CONVEYOR, SURFACE_FLOOR, SURFACE_SUPPORT = 0, 1, 2, 3


def _intersect(plate: PlateSpec, T_cam_plate: np.ndarray, origin: np.ndarray, dirs: np.ndarray) -> _Hits:
    """Intersect rays ``origin + s * dirs`` (left-camera frame) with the plate, else with the conveyor."""
    R = T_cam_plate[:3, :3]
    t = T_cam_plate[:3, 3]
    o = R.T @ (np.asarray(origin, dtype=np.float64) - t)
    d = dirs @ R  # row-wise R^T d
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
    c = 1.0 if plate.convex else -1.0

    with np.errstate(invalid="ignore", divide="ignore"):
        s = -o[2] / dz  # plane z_p = 0
        if plate.shape in ("cylinder", "sphere"):
            Rr = plate.radius_mm
            oc = o - np.array([0.0, 0.0, c * Rr])
            if plate.shape == "cylinder":
                A = dx * dx + dz * dz
                B = 2.0 * (oc[0] * dx + oc[2] * dz)
                C = oc[0] ** 2 + oc[2] ** 2 - Rr * Rr
            else:
                A = dx * dx + dy * dy + dz * dz
                B = 2.0 * (oc[0] * dx + oc[1] * dy + oc[2] * dz)
                C = float(oc @ oc) - Rr * Rr
            root = np.sqrt(B * B - 4.0 * A * C)
            # Convex: the near side of a circle centred behind the plate; concave: the far side of
            # one centred in front of it.
            # A ray that misses the base surface (NaN) misses the plate: it sees the conveyor.
            s = (-B - c * root) / (2.0 * A)

        if plate.shape == "saddle" or plate.dents:
            # Newton on f(s) = z_p(s) - h(x_p(s), y_p(s)); h is evaluated inside the footprint only
            # (constant continuation outside), off-plate rays are sorted out afterwards.
            for _ in range(30):
                x = o[0] + s * dx
                y = o[1] + s * dy
                xc = np.clip(x, -half_w, half_w)
                yc = np.clip(y, -half_h, half_h)
                h, hx, hy = plate_height(plate, xc, yc)
                hx = np.where(xc == x, hx, 0.0)
                hy = np.where(yc == y, hy, 0.0)
                f = o[2] + s * dz - h
                step = f / (dz - hx * dx - hy * dy)
                s = s - step
                moving = np.abs(step[np.isfinite(step)])
                if moving.size == 0 or moving.max() <= 1e-9:
                    break

        x = o[0] + s * dx
        y = o[1] + s * dy
        on_plate = np.isfinite(s) & (s > 0) & plate_region(plate, x, y)
        xq = np.where(on_plate, x, 0.0)
        yq = np.where(on_plate, y, 0.0)
        h, hx, hy = plate_height(plate, xq, yq)
        residual = np.abs(o[2] + s * dz - h)[on_plate]
        if residual.size and residual.max() > 1e-6:
            raise ValueError(
                f"plate: ray casting did not converge (|z - h| up to {residual.max():.3g} mm); "
                "are the dents too steep (depth_mm comparable to radius_mm)?"
            )

        if plate.floor is None:
            # The conveyor: a plane z_p = const behind the plate's farthest point.
            z_bg = _conveyor_z(plate)
            s_bg = (z_bg - o[2]) / dz
        else:
            s_bg, n_bg, surface_bg = _surroundings(plate, o, d)
    if plate.floor is None:
        s = np.where(on_plate, s, s_bg)
        xyz = np.stack([o[0] + s * dx, o[1] + s * dy, np.where(on_plate, h, z_bg)], axis=-1)
        n_plate = np.stack([np.where(on_plate, hx, 0.0), np.where(on_plate, hy, 0.0), -np.ones_like(s)], axis=-1)
        surface = np.where(on_plate, SURFACE_PLATE, SURFACE_CONVEYOR).astype(np.int8)
    else:
        s = np.where(on_plate, s, s_bg)
        xyz = np.stack([o[0] + s * dx, o[1] + s * dy, np.where(on_plate, h, o[2] + s * dz)], axis=-1)
        n_plate = np.where(on_plate[..., None], np.stack([hx, hy, -np.ones_like(s)], axis=-1), n_bg)
        surface = np.where(on_plate, SURFACE_PLATE, surface_bg).astype(np.int8)
    n_plate /= np.linalg.norm(n_plate, axis=-1, keepdims=True)
    normals = n_plate @ R.T
    return _Hits(s=s, xyz_plate=xyz, normals=normals, on_plate=on_plate, surface=surface)


def _surroundings(plate: PlateSpec, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays ``o + s d`` (plate frame) against the floor and the supports: nearest hit ``s`` (...,), its
    outward normal (..., 3) (plate frame, towards the rays' side) and surface code (...,) int8."""
    floor = plate.floor
    z_floor = _conveyor_z(plate) - _CONVEYOR_GAP_MM + floor.gap_mm
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (z_floor - o[2]) / d[..., 2]
        s = np.where(s > 0, s, np.inf)
        normal = np.zeros(d.shape)
        normal[..., 2] = -1.0
        surface = np.full(s.shape, SURFACE_FLOOR, dtype=np.int8)
        for k, sup in enumerate(floor.supports):
            lo = np.array([sup.x_mm - sup.size_x_mm / 2, sup.y_mm - sup.size_y_mm / 2, z_floor - sup.height_mm])
            hi = np.array([sup.x_mm + sup.size_x_mm / 2, sup.y_mm + sup.size_y_mm / 2, z_floor])
            t1 = (lo - o) / d
            t2 = (hi - o) / d
            near = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf)
            far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf)
            enter = near.max(axis=-1)
            hit = (enter <= far.min(axis=-1)) & (enter > 0) & (enter < s)
            axis = near.argmax(axis=-1)
            face = np.zeros(d.shape)
            np.put_along_axis(face, axis[..., None], -np.sign(np.take_along_axis(d, axis[..., None], axis=-1)), axis=-1)
            s = np.where(hit, enter, s)
            normal = np.where(hit[..., None], face, normal)
            surface = np.where(hit, SURFACE_SUPPORT + k, surface).astype(np.int8)
    return s, normal, surface


def _conveyor_z(plate: PlateSpec) -> float:
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
    gx, gy = np.meshgrid(np.linspace(-half_w, half_w, 121), np.linspace(-half_h, half_h, 121))
    h, _, _ = plate_height(plate, gx, gy)
    return float(h.max()) + _CONVEYOR_GAP_MM


# --------------------------------------------------------------------------- texture


class _Texture:
    """A 2-D scalar texture over a rectangle of plane coordinates (mm), sampled bilinearly."""

    def __init__(self, values: np.ndarray, x0_mm: float, y0_mm: float, texel_mm: float):
        self.values = np.ascontiguousarray(values, dtype=np.float32)
        self.x0 = x0_mm
        self.y0 = y0_mm
        self.texel = texel_mm

    def prefiltered(self, footprint_mm: float) -> "_Texture":
        """The texture blurred to the footprint of a camera pixel (anti-aliasing), mm."""
        sigma = 0.5 * footprint_mm / self.texel
        if sigma < 0.3:
            return self
        vals = cv2.GaussianBlur(self.values, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        return _Texture(vals, self.x0, self.y0, self.texel)

    def sample(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Bilinear samples at plane points; (H, W) in, (H, W) float32 out (edge values continue)."""
        mx = ((x_mm - self.x0) / self.texel).astype(np.float32)
        my = ((y_mm - self.y0) / self.texel).astype(np.float32)
        return cv2.remap(self.values, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cells: int) -> np.ndarray:
    """Zero-mean, unit-std smooth noise with about ``cells`` features across the larger side."""
    h, w = shape
    gh = max(2, int(round(cells * h / max(h, w)))) + 3
    gw = max(2, int(round(cells * w / max(h, w)))) + 3
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    # Crop a margin so the cubic upsampling has no edge artefacts.
    big = cv2.resize(coarse, (w * gw // (gw - 3) + 1, h * gh // (gh - 3) + 1), interpolation=cv2.INTER_CUBIC)
    off_y = (big.shape[0] - h) // 2
    off_x = (big.shape[1] - w) // 2
    out = big[off_y : off_y + h, off_x : off_x + w]
    return (out - out.mean()) / (out.std() + 1e-12)


def _plate_albedo_texture(plate: PlateSpec, kind: str, seed: int, texel_mm: float) -> _Texture:
    """Painted steel with rust blotches and grain of a few texels, fixed to the plate."""
    margin = 30.0
    w_mm = plate.size_mm[0] + 2 * margin
    h_mm = plate.size_mm[1] + 2 * margin
    nx = int(math.ceil(w_mm / texel_mm)) + 1
    ny = int(math.ceil(h_mm / texel_mm)) + 1
    x0 = -plate.size_mm[0] / 2 - margin
    y0 = -plate.size_mm[1] / 2 - margin
    if kind == "uniform":
        return _Texture(np.full((ny, nx), 0.6, np.float32), x0, y0, texel_mm)
    rng = np.random.default_rng(seed)
    paint = 0.62 + 0.05 * _smooth_noise(rng, (ny, nx), 6)  # slow variation of the paint
    grain_noise = rng.standard_normal((ny, nx)).astype(np.float32)
    grain = cv2.GaussianBlur(grain_noise, (0, 0), 1.0)
    grain /= grain.std() + 1e-12
    albedo = paint + 0.05 * grain  # few-mm grain (primer, mill scale)
    if kind == "rusty":
        blotch = _smooth_noise(rng, (ny, nx), int(max(plate.size_mm) / 60))  # ~60 mm features
        patch = _smooth_noise(rng, (ny, nx), 5)
        # Rust where the medium noise is high, more of it in some regions than others.
        level = blotch + 0.6 * patch
        rust = np.clip((level - 1.2) / 0.5, 0.0, 1.0)
        rust = rust * rust * (3.0 - 2.0 * rust)  # smoothstep edge
        rust_albedo = 0.34 + 0.04 * _smooth_noise(rng, (ny, nx), int(max(plate.size_mm) / 15)) + 0.04 * grain
        albedo = (1.0 - rust) * albedo + rust * rust_albedo
    elif kind != "painted":
        raise ValueError(f"CaptureSpec.texture: expected rusty, painted or uniform, got {kind!r}")
    # By construction the albedo stays in about [0.2, 0.85]; guard the physical range explicitly.
    albedo = np.clip(albedo, 0.05, 0.95)
    return _Texture(albedo.astype(np.float32), x0, y0, texel_mm)


def _conveyor_texture(plate: PlateSpec, seed: int) -> _Texture:
    """Dark conveyor (albedo ~0.05, slightly textured, slats across x_p) over a wide area."""
    texel = 10.0
    span = 1.5 * max(plate.size_mm) + 3.0 * plate.distance_mm
    n = int(math.ceil(span / texel)) + 1
    rng = np.random.default_rng(seed)
    low = _smooth_noise(rng, (n, n), 10)
    grain = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), 1.0)
    grain /= grain.std() + 1e-12
    y = np.arange(n, dtype=np.float32)[:, None] * texel
    slats = (np.sin(2 * np.pi * y / 300.0) > 0.92).astype(np.float32)
    albedo = 0.05 + 0.008 * low + 0.006 * grain - 0.02 * slats
    return _Texture(np.clip(albedo, 0.01, None), -span / 2, -span / 2, texel)


def _floor_texture(plate: PlateSpec, seed: int, texel_mm: float, span_mm: float) -> _Texture:
    """Concrete shop floor (plate frame x_p, y_p over ``span_mm`` square, centred): grain, slow
    variation, oil stains, joints every 3 m and a painted safety line, mean ``floor.albedo``."""
    floor = plate.floor
    n = int(math.ceil(span_mm / texel_mm)) + 1
    rng = np.random.default_rng(seed)
    grain = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), 0.8)
    grain /= grain.std() + 1e-12
    slow = _smooth_noise(rng, (n, n), max(2, int(span_mm / 800)))
    stains = _smooth_noise(rng, (n, n), max(2, int(span_mm / 300)))
    stain = np.clip((stains - 1.3) / 0.5, 0.0, 1.0)
    stain = stain * stain * (3.0 - 2.0 * stain)
    coords = (np.arange(n, dtype=np.float32) * texel_mm - span_mm / 2)
    joint = lambda c: (np.abs(((c + 1500.0) % 3000.0) - 1500.0) < 8.0).astype(np.float32)  # noqa: E731
    joints = np.maximum(joint(coords)[None, :], joint(coords)[:, None])
    line_x = plate.size_mm[0] / 2 + 350.0
    line = (np.abs(coords - line_x) < 50.0).astype(np.float32)[None, :]
    c = floor.texture
    albedo = floor.albedo * (1.0 + c * (0.10 * grain + 0.08 * slow)) * (1.0 - 0.45 * c * stain) * (1.0 - 0.5 * c * joints)
    albedo = albedo * (1.0 - line) + line * min(0.95, floor.albedo + 0.3 * c)
    return _Texture(np.clip(albedo, 0.02, 0.95).astype(np.float32), -span_mm / 2, -span_mm / 2, texel_mm)


# --------------------------------------------------------------------------- capture


@dataclass(frozen=True)
class CaptureSpec:
    """How the cell photographs the plate.

    Attributes
    ----------
    n_lights : int
        Lights on a ring around the left camera (at least 3), one photometric image each.
    light_elevation_deg : float
        Angle between each light direction and the optical axis (0 < . < 90).
    light_azimuth_deg : float
        Azimuth of light 0 on the ring (in the image plane, from +x towards +y).
    intensity_spread : float
        Light intensities ``e_k`` are drawn uniformly in ``1 +- intensity_spread``.
    noise : float
        Std of the additive Gaussian sensor noise, as a fraction of full scale ``2**bit_depth - 1``
        (0.004 = 0.4 %).
    bit_depth : {8, 12, 16}
        8 writes 8-bit PNGs; 12 and 16 write 16-bit PNGs (12-bit values stay <= 4095).
    exposure : float
        Fraction of full scale that a white (albedo 1) plate facing a light head-on reaches.
    specular : float
        Strength of a Blinn-Phong lobe relative to a white Lambertian surface (0: pure Lambertian).
    shininess : float
        Blinn-Phong exponent.
    dark_level : float
        Dark offset as a fraction of full scale (plus a small fixed pattern); the dark frame is
        written with its own noise.
    albedo_seed : int or None
        Seed of the plate texture (None: derived from the capture seed).
    texture : {"rusty", "painted", "uniform"}
    stereo : bool
        Render and write the stereo pair (all lights on, each at ``1 / n_lights`` of its power).
    working_distance_mm : float or None
        Written into ``capture.json``; None omits it.
    width, height : int
        Image size of :func:`default_rig` when no rig is given (ignored when a rig is given).
    near_field_mm : float or None
        None: distant lights (``light_directions``). Otherwise point lights (LEDs) on a ring this far
        (mm, along the optical axis) in front of the plate centre, i.e. that high above the plate,
        each seen from the plate centre at ``light_elevation_deg`` from the optical axis; the
        irradiance falls off with the inverse square of the distance and the LED profile ``led_mu``
        (see :mod:`pipeline.lights`). Each light's ``intensity`` is chosen so that it casts
        ``e_k`` (``1 +- intensity_spread``) on the plate centre, as bright as a distant light.
    led_mu : float
        Point lights: exponent of the LED beam profile ``cos^mu`` about its axis, which points at
        the plate centre (0: isotropic).
    light_error_deg : float
        The lights written into ``capture.json`` are the true ones turned by this angle about the
        plate centre, each about its own random axis (a light bumped out of place); the images are
        rendered with the true lights (``truth.npz``).
    manifest_lights : {"exact", "nominal"}
        Point lights only: ``"exact"`` writes positions, axes and profiles; ``"nominal"`` writes
        only each light's direction and irradiance as seen from the plate centre (what a cell
        without a light calibration knows).
    """

    n_lights: int = 12
    light_elevation_deg: float = 45.0
    light_azimuth_deg: float = 0.0
    intensity_spread: float = 0.05
    noise: float = 0.004
    bit_depth: Literal[8, 12, 16] = 16
    exposure: float = 0.85
    specular: float = 0.0
    shininess: float = 40.0
    dark_level: float = 0.01
    albedo_seed: int | None = None
    texture: Literal["rusty", "painted", "uniform"] = "rusty"
    stereo: bool = True
    working_distance_mm: float | None = 3000.0
    width: int = 1224
    height: int = 1024
    near_field_mm: float | None = None
    led_mu: float = 0.0
    light_error_deg: float = 0.0
    manifest_lights: Literal["exact", "nominal"] = "exact"

    def __post_init__(self) -> None:
        if not isinstance(self.n_lights, (int, np.integer)) or self.n_lights < 3:
            raise ValueError(f"CaptureSpec.n_lights: expected an integer >= 3, got {self.n_lights}")
        if not 0.0 < self.light_elevation_deg < 90.0:
            raise ValueError(f"CaptureSpec.light_elevation_deg: expected in (0, 90), got {self.light_elevation_deg}")
        if not 0.0 <= self.intensity_spread < 0.5:
            raise ValueError(f"CaptureSpec.intensity_spread: expected in [0, 0.5), got {self.intensity_spread}")
        if not (math.isfinite(self.noise) and self.noise >= 0):
            raise ValueError(f"CaptureSpec.noise: expected a fraction of full scale >= 0, got {self.noise}")
        if self.bit_depth not in (8, 12, 16):
            raise ValueError(f"CaptureSpec.bit_depth: expected 8, 12 or 16, got {self.bit_depth}")
        if not (math.isfinite(self.exposure) and self.exposure > 0):
            raise ValueError(f"CaptureSpec.exposure: expected > 0, got {self.exposure}")
        if not (math.isfinite(self.specular) and self.specular >= 0):
            raise ValueError(f"CaptureSpec.specular: expected >= 0, got {self.specular}")
        if not (math.isfinite(self.shininess) and self.shininess > 0):
            raise ValueError(f"CaptureSpec.shininess: expected > 0, got {self.shininess}")
        if not (math.isfinite(self.dark_level) and 0 <= self.dark_level < 0.5):
            raise ValueError(f"CaptureSpec.dark_level: expected in [0, 0.5), got {self.dark_level}")
        if self.texture not in ("rusty", "painted", "uniform"):
            raise ValueError(f"CaptureSpec.texture: expected rusty, painted or uniform, got {self.texture!r}")
        if self.working_distance_mm is not None and not (
            math.isfinite(self.working_distance_mm) and self.working_distance_mm > 0
        ):
            raise ValueError(f"CaptureSpec.working_distance_mm: expected > 0 or None, got {self.working_distance_mm}")
        if self.width < 64 or self.height < 64:
            raise ValueError(f"CaptureSpec.width, height: expected at least 64 x 64, got {self.width} x {self.height}")
        if self.near_field_mm is not None and not (math.isfinite(self.near_field_mm) and self.near_field_mm > 0):
            raise ValueError(f"CaptureSpec.near_field_mm: expected a height > 0 mm or None, got {self.near_field_mm}")
        if not (math.isfinite(self.led_mu) and self.led_mu >= 0):
            raise ValueError(f"CaptureSpec.led_mu: expected >= 0, got {self.led_mu}")
        if not (math.isfinite(self.light_error_deg) and 0 <= self.light_error_deg < 30):
            raise ValueError(f"CaptureSpec.light_error_deg: expected in [0, 30), got {self.light_error_deg}")
        if self.manifest_lights not in ("exact", "nominal"):
            raise ValueError(f"CaptureSpec.manifest_lights: expected exact or nominal, got {self.manifest_lights!r}")

    def light_directions(self) -> np.ndarray:
        """(n_lights, 3) float64 unit vectors, left-camera frame, from the surface towards each light."""
        el = math.radians(self.light_elevation_deg)
        phi = math.radians(self.light_azimuth_deg) + 2.0 * np.pi * np.arange(self.n_lights) / self.n_lights
        return np.stack([math.sin(el) * np.cos(phi), math.sin(el) * np.sin(phi), np.full(phi.shape, -math.cos(el))], 1)

    def lights(self, centre_mm: np.ndarray, intensities: np.ndarray) -> Lights:
        """The true lights for a plate centred at ``centre_mm`` (3,) (left-camera frame, mm).

        Distant: :meth:`light_directions` with ``intensities``. Near field: point lights on a ring
        ``near_field_mm`` in front of the centre, each in its light direction from the centre, aimed
        at it, with intensities that cast ``intensities`` on it (see the class docstring).
        """
        dirs = self.light_directions()
        if self.near_field_mm is None:
            return Lights.distant(dirs, intensities)
        centre = np.asarray(centre_mm, dtype=np.float64)
        reach = self.near_field_mm / -dirs[:, 2]  # distance along each direction to the lights' plane
        positions = centre + reach[:, None] * dirs
        axes = -dirs
        unit = Lights.points(positions, np.ones(len(dirs)), axes=axes, mu=np.full(len(dirs), self.led_mu))
        at_centre = unit.attenuation_at(centre)  # cos(theta) = 1 on the axis
        return unit.with_intensity(np.asarray(intensities) / at_centre)


@dataclass(frozen=True)
class _Scene:
    plate: PlateSpec
    T_cam_plate: np.ndarray
    albedo: _Texture
    conveyor: _Texture  # the conveyor's texture, or the floor's when the plate lies over a floor


def _render_view(scene: _Scene, origin: np.ndarray, rays: np.ndarray) -> tuple[_Hits, np.ndarray]:
    """Hits and albedo (H, W) float32 for rays (H, W, 3) from ``origin`` (left-camera frame)."""
    hits = _intersect(scene.plate, scene.T_cam_plate, origin, rays)
    x = hits.xyz_plate[..., 0]
    y = hits.xyz_plate[..., 1]
    albedo = np.where(hits.on_plate, scene.albedo.sample(x, y), scene.conveyor.sample(x, y))
    floor = scene.plate.floor
    if floor is not None:
        for k, sup in enumerate(floor.supports):  # the floor's texture, scaled to the support's albedo
            albedo = np.where(hits.surface == SURFACE_SUPPORT + k, albedo * np.float32(sup.albedo / floor.albedo), albedo)
    return hits, albedo.astype(np.float32)


def _shade(
    hits: _Hits,
    albedo: np.ndarray,
    points_cam: np.ndarray,
    eye: np.ndarray,
    lights: Lights,
    capture: CaptureSpec,
) -> np.ndarray:
    """Noise-free radiance (N, H, W) float32 in fractions of full scale, dark not added.

    Per pixel and light: the direction towards the light and its attenuation at the surface point
    (:class:`pipeline.lights.Lights`; constant for distant lights).
    """
    n = hits.normals.astype(np.float32)
    out = np.empty((lights.n,) + albedo.shape, dtype=np.float32)
    view = None
    if capture.specular > 0:
        view = eye.astype(np.float32) - points_cam.astype(np.float32)
        view /= np.linalg.norm(view, axis=-1, keepdims=True)
    for k in range(lights.n):
        one = Lights(lights.directions[k:k + 1], lights.positions_mm[k:k + 1], lights.axes[k:k + 1],
                     lights.mu[k:k + 1], lights.intensity[k:k + 1])
        l = one.directions_at(points_cam)[0].astype(np.float32)
        gain = (one.intensity[0] * one.attenuation_at(points_cam)[0]).astype(np.float32)
        ndotl = np.einsum("hwc,hwc->hw", n, l)
        lit = np.maximum(ndotl, 0.0)
        img = albedo * lit
        if view is not None:
            half = view + l
            half /= np.linalg.norm(half, axis=-1, keepdims=True)
            ndoth = np.maximum(np.einsum("hwc,hwc->hw", n, half), 0.0)
            img = img + np.where(ndotl > 0, capture.specular * ndoth**capture.shininess, 0.0)
        out[k] = np.float32(capture.exposure) * gain * img
    return out


def _floor_span_mm(plate: PlateSpec, rig: StereoRig) -> float:
    """Side (mm) of a floor square centred under the plate that covers what both cameras see of it."""
    w, h = rig.image_size
    far = plate.distance_mm + _conveyor_z(plate) + plate.floor.gap_mm
    field = max(w / rig.left.K[0, 0], h / rig.left.K[1, 1]) * far
    return 1.2 * field + _BASELINE_MM


def _bumped(lights: Lights, centre_mm: np.ndarray, error_deg: float, rng: np.random.Generator) -> Lights:
    """Every light turned by ``error_deg`` about ``centre_mm``, each about a random axis across its direction."""
    if error_deg == 0:
        return lights
    dirs = lights.directions_at(centre_mm)
    angle = math.radians(error_deg)
    directions, positions, axes = lights.directions.copy(), lights.positions_mm.copy(), lights.axes.copy()
    for k in range(lights.n):
        across = np.cross(dirs[k], rng.standard_normal(3))
        across /= np.linalg.norm(across)
        rot, _ = cv2.Rodrigues(across * angle)
        if lights.is_point[k]:
            positions[k] = centre_mm + rot @ (positions[k] - centre_mm)
            if np.isfinite(axes[k]).all():
                axes[k] = rot @ axes[k]
        else:
            directions[k] = rot @ directions[k]
    return Lights(directions, positions, axes, lights.mu.copy(), lights.intensity.copy())


def _quantise(frac: np.ndarray, bit_depth: int) -> np.ndarray:
    """Fractions of full scale -> counts, rounded, saturated at 0 and full scale (sensor behaviour)."""
    full = float(2**bit_depth - 1)
    counts = np.clip(np.rint(frac * full), 0.0, full)
    return counts.astype(np.uint8 if bit_depth == 8 else np.uint16)


def _write_png(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise OSError(f"{path}: could not write the image")


def simulate_capture(
    out_dir: str | Path,
    *,
    plate: PlateSpec = PlateSpec(),
    capture: CaptureSpec = CaptureSpec(),
    rig: StereoRig | None = None,
    plate_id: str = "SIM-0001",
    tolerance_mm: float = 2.0,
    seed: int = 0,
    workers: int | None = None,
) -> Path:
    """Render a capture bundle of a plate with known truth.

    Parameters
    ----------
    out_dir : str or Path
        Folder to write into (created if missing; files of the same names are overwritten).
    plate : PlateSpec
    capture : CaptureSpec
    rig : StereoRig or None
        The binocular head; None: ``default_rig(width=capture.width, height=capture.height)``.
    plate_id : str
    tolerance_mm : float
        Written into ``target.json``.
    seed : int
        Seeds the texture (unless ``capture.albedo_seed``), light intensities and all noise; the
        output is the same for the same arguments.
    workers : int, optional
        Threads that encode and write the images while the next ones render (None:
        :func:`pipeline.parallel.default_workers`); the output does not depend on it.

    Returns
    -------
    Path
        ``out_dir``, holding:

        - ``capture.json`` (``plate-capture/1``), ``calibration.json`` (``stereo-calibration/1`` of
          the rig), ``target.json`` (``plate-target/1`` of the nominal shape without dents; a saddle,
          and a plate with another outline or with openings, is written as a mesh target with
          ``target.stl``, plate frame, mm, see :func:`plate_mesh`);
        - ``ps_00.png`` ... (left camera, raw/distorted, one light each), ``dark.png``,
          ``stereo_left.png``, ``stereo_right.png`` (when ``capture.stereo``);
        - ``truth.npz`` on the LEFT UNDISTORTED grid (pixel (u, v) sees ray ``K^-1 (u, v, 1)``):
          ``depth_mm`` (H, W) float64 z along the optical axis, NaN off the plate; ``normals``
          (H, W, 3) float32 camera frame, towards the camera, NaN off the plate; ``mask`` (H, W)
          bool; ``albedo`` (H, W) float32 (the conveyor's off the plate); ``plate_xy_mm``
          (H, W, 2) float32 plate-frame coordinates, NaN off the plate; on the RAW grid
          ``depth_raw_mm`` float32 and ``mask_raw``; and ``radius_mm``,
          ``radius2_mm`` (NaN if none), ``shape``, ``convex``, ``size_mm``, ``dents`` (D, 4) rows
          ``x, y, radius, depth`` mm, ``T_cam_plate`` (4, 4), the true lights: ``light_dirs`` (N, 3)
          (seen from the plate centre), ``light_intensity`` (N,), ``light_positions_mm`` (N, 3) (NaN
          for distant lights), ``light_axes`` (N, 3), ``light_mu`` (N,); ``K``, ``dist``,
          ``bit_depth``, ``noise``, ``exposure``; ``surface`` (H, W) int8, what each pixel sees
          (:data:`SURFACE_PLATE`, :data:`SURFACE_CONVEYOR`, :data:`SURFACE_FLOOR`, ``SURFACE_SUPPORT + k``
          for support k) and ``scene_depth_mm`` (H, W) float32, the depth of whatever it sees.
          ``mask`` is exactly ``surface == SURFACE_PLATE``.

    Raises
    ------
    ValueError
        Bad option values, or a plate that does not lie in front of the cameras.
    """
    if not isinstance(plate, PlateSpec):
        raise TypeError(f"plate: expected a PlateSpec, got {type(plate).__name__}")
    if not isinstance(capture, CaptureSpec):
        raise TypeError(f"capture: expected a CaptureSpec, got {type(capture).__name__}")
    if rig is None:
        rig = default_rig(width=capture.width, height=capture.height)
    elif not isinstance(rig, StereoRig):
        raise TypeError(f"rig: expected a StereoRig or None, got {type(rig).__name__}")
    if not plate_id:
        raise ValueError("plate_id: expected a non-empty string")
    if not (math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise ValueError(f"tolerance_mm: expected > 0, got {tolerance_mm}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    seeds = np.random.SeedSequence(int(seed)).spawn(6)
    rng_lights, rng_noise, rng_dark, rng_stereo = (np.random.default_rng(s) for s in seeds[:4])
    tex_seed = capture.albedo_seed if capture.albedo_seed is not None else int(seeds[4].generate_state(1)[0])
    conveyor_seed = int(seeds[5].generate_state(1)[0])

    T_cam_plate = plate_pose(plate)
    mm_per_px = plate.distance_mm / rig.left.K[0, 0]
    scene = _Scene(
        plate=plate,
        T_cam_plate=T_cam_plate,
        albedo=_plate_albedo_texture(plate, capture.texture, tex_seed, max(_TEXEL_MM, mm_per_px / 2)).prefiltered(
            mm_per_px
        ),
        conveyor=(
            _conveyor_texture(plate, conveyor_seed)
            if plate.floor is None
            else _floor_texture(plate, conveyor_seed, max(4.0, mm_per_px / 2), _floor_span_mm(plate, rig))
        ).prefiltered(mm_per_px),
    )
    spread = capture.intensity_spread
    intensities = rng_lights.uniform(1.0 - spread, 1.0 + spread, capture.n_lights)
    centre = T_cam_plate[:3, 3]
    lights = capture.lights(centre, intensities)
    written = _bumped(lights, centre, capture.light_error_deg, rng_lights)
    if lights.any_point and capture.manifest_lights == "nominal":
        written = written.nominal_directions(centre)

    # PNG encoding (cv2 releases the GIL) overlaps with rendering on other threads.
    pool = ThreadPoolExecutor(max_workers=workers or default_workers())
    writes = []
    try:
        # ---- left camera, raw grid: photometric images and dark frame
        w, h = rig.image_size
        left_rays = _raw_pixel_rays(rig.left)
        eye_left = np.zeros(3)
        hits_raw, albedo_raw = _render_view(scene, eye_left, left_rays)
        if not hits_raw.on_plate.any():
            raise ValueError("plate: no pixel of the left camera sees the plate (check distance_mm, tilt_deg, size_mm)")
        points_raw = hits_raw.s[..., None] * left_rays
        radiance = _shade(hits_raw, albedo_raw, points_raw, eye_left, lights, capture)
        dark_map = (capture.dark_level + 0.001 * rng_dark.standard_normal((h, w))).astype(np.float32)
        if capture.dark_level == 0:
            dark_map[:] = 0.0
        image_names = [f"ps_{k:02d}.png" for k in range(capture.n_lights)]
        for k, name in enumerate(image_names):
            noisy = radiance[k] + dark_map + np.float32(capture.noise) * rng_noise.standard_normal((h, w), np.float32)
            writes.append(pool.submit(_write_png, out / name, _quantise(noisy, capture.bit_depth)))
        dark = dark_map + np.float32(capture.noise) * rng_noise.standard_normal((h, w), np.float32)
        writes.append(pool.submit(_write_png, out / "dark.png", _quantise(dark, capture.bit_depth)))

        # ---- stereo pair: all lights on, each at 1/N power
        if capture.stereo:
            flash = radiance.mean(axis=0)
            left_img = flash + dark_map + np.float32(capture.noise) * rng_stereo.standard_normal((h, w), np.float32)
            writes.append(pool.submit(_write_png, out / "stereo_left.png", _quantise(left_img, capture.bit_depth)))
            right_rays_cam = _raw_pixel_rays(rig.right)
            right_rays = right_rays_cam @ rig.R  # directions into the left frame: R^T r
            eye_right = -rig.R.T @ rig.T
            hits_r, albedo_r = _render_view(scene, eye_right, right_rays)
            points_r = eye_right + hits_r.s[..., None] * right_rays
            flash_r = _shade(hits_r, albedo_r, points_r, eye_right, lights, capture).mean(axis=0)
            dark_r = (capture.dark_level + 0.001 * rng_dark.standard_normal((h, w))).astype(np.float32)
            if capture.dark_level == 0:
                dark_r[:] = 0.0
            right_img = flash_r + dark_r + np.float32(capture.noise) * rng_stereo.standard_normal((h, w), np.float32)
            writes.append(pool.submit(_write_png, out / "stereo_right.png", _quantise(right_img, capture.bit_depth)))
    finally:
        pool.shutdown(wait=True)
    for done in writes:
        done.result()  # re-raise a failed write

    # ---- truth on the left undistorted grid
    und_rays = rig.left.pixel_rays()
    hits_u, albedo_u = _render_view(scene, eye_left, und_rays)
    mask = hits_u.on_plate
    scene_depth = hits_u.s * und_rays[..., 2]
    depth = np.where(mask, scene_depth, np.nan)
    normals = np.where(mask[..., None], hits_u.normals, np.nan)
    plate_xy = np.where(mask[..., None], hits_u.xyz_plate[..., :2], np.nan)
    np.savez(
        out / "truth.npz",
        depth_mm=depth,
        normals=normals.astype(np.float32),
        mask=mask,
        albedo=albedo_u,
        plate_xy_mm=plate_xy.astype(np.float32),
        depth_raw_mm=np.where(hits_raw.on_plate, hits_raw.s, np.nan).astype(np.float32),
        mask_raw=hits_raw.on_plate,
        surface=hits_u.surface,
        scene_depth_mm=scene_depth.astype(np.float32),
        radius_mm=np.float64(plate.radius_mm if plate.shape != "plane" and plate.radius_mm else np.nan),
        radius2_mm=np.float64(plate.radius2 if plate.radius2 is not None else np.nan),
        shape=np.array(plate.shape),
        convex=np.bool_(plate.convex),
        size_mm=np.array(plate.size_mm),
        dents=np.array([[d.x_mm, d.y_mm, d.radius_mm, d.depth_mm] for d in plate.dents], dtype=np.float64).reshape(-1, 4),
        T_cam_plate=T_cam_plate,
        light_dirs=lights.directions_at(centre),
        light_intensity=lights.intensity,
        light_positions_mm=lights.positions_mm,
        light_axes=lights.axes,
        light_mu=lights.mu,
        K=rig.left.K,
        dist=rig.left.dist,
        bit_depth=np.int64(capture.bit_depth),
        noise=np.float64(capture.noise),
        exposure=np.float64(capture.exposure),
    )

    # ---- JSON files
    calibration_doc = calibration_document(rig)
    StereoCalibrationFile.model_validate(calibration_doc)
    (out / "calibration.json").write_text(json.dumps(calibration_doc, indent=2))
    (out / "target.json").write_text(json.dumps(_target_object(plate, tolerance_mm, out), indent=2))
    capture_obj = {
        "format": CAPTURE_FORMAT,
        "plate_id": plate_id,
        "captured_at": _CAPTURED_AT,
        "calibration": "calibration.json",
        "bit_depth": capture.bit_depth,
        "photometric": {
            "lights": written.documents(),
            "images": image_names,
            "dark": "dark.png",
        },
    }
    if capture.stereo:
        capture_obj["stereo"] = {"left": "stereo_left.png", "right": "stereo_right.png"}
    if capture.working_distance_mm is not None:
        capture_obj["working_distance_mm"] = float(capture.working_distance_mm)
    CaptureFile.model_validate(capture_obj)
    (out / "capture.json").write_text(json.dumps(capture_obj, indent=2))
    return out


def _target_object(plate: PlateSpec, tolerance_mm: float, out: Path) -> dict:
    """The ``plate-target/1`` object of the nominal plate (no dents); writes ``target.stl`` for a saddle
    and for a plate with a non-rectangular outline or with openings (see :func:`plate_mesh`)."""
    if plate.outline != "rectangle" or plate.cutouts:
        # the analytic shapes know only a size: the outline and the openings need a mesh
        plate_mesh(plate).export(out / "target.stl")
        shape = {"type": "mesh", "file": "target.stl"}
    elif plate.shape == "plane":
        shape = {"type": "plane"}
    elif plate.shape in ("cylinder", "sphere"):
        shape = {"type": plate.shape, "radius_mm": float(plate.radius_mm)}
    else:
        _saddle_mesh(plate).export(out / "target.stl")
        shape = {"type": "mesh", "file": "target.stl"}
    obj = {"format": TARGET_FORMAT, "shape": shape, "size_mm": list(plate.size_mm), "tolerance_mm": float(tolerance_mm)}
    TargetFile.model_validate(obj)
    return obj


def plate_mesh(plate: PlateSpec, *, spacing_mm: float = 50.0):
    """The nominal plate (its shape without dents) over its outline, openings cut out, as a triangle mesh.

    Parameters
    ----------
    plate : PlateSpec
    spacing_mm : float
        Spacing of the interior vertices, mm; the outline and the openings' edges are sampled at half
        of it (a chord of a 100 mm radius opening then errs by < 0.8 mm from the arc).

    Returns
    -------
    trimesh.Trimesh
        Vertices in the plate frame (mm, z_p = nominal height ``plate_height``), faces with normals
        towards -z_p (the cameras). Boundary-conforming: a Delaunay triangulation of the edge samples
        and an interior grid, keeping the triangles whose centroid lies on the plate.
    """
    import trimesh
    from scipy.spatial import Delaunay, cKDTree

    if not (math.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"spacing_mm: expected > 0, got {spacing_mm}")
    nominal = PlateSpec(
        shape=plate.shape, radius_mm=plate.radius_mm, radius2_mm=plate.radius2_mm, convex=plate.convex,
        size_mm=plate.size_mm, outline=plate.outline, cutouts=plate.cutouts,
    )
    edge_step = spacing_mm / 2
    outline = outline_polygon(plate, step_mm=edge_step)
    edges = [outline[~np.any([c.signed_distance(*outline.T) < 0 for c in plate.cutouts], axis=0)]
             if plate.cutouts else outline]
    for cut in plate.cutouts:
        ring = cut.boundary(edge_step)
        edges.append(ring[_inside_outline(plate, ring[:, 0], ring[:, 1])])
    boundary = np.concatenate(edges)
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
    gx, gy = np.meshgrid(np.arange(-half_w, half_w + 1e-9, spacing_mm), np.arange(-half_h, half_h + 1e-9, spacing_mm))
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    grid = grid[plate_region(nominal, grid[:, 0], grid[:, 1])]
    near_edge, _ = cKDTree(boundary).query(grid)
    points = np.concatenate([boundary, grid[near_edge >= 0.4 * spacing_mm]])
    tri = Delaunay(points).simplices
    # a triangle bridging an opening or a concave stretch of the outline has its centroid off the plate
    centroid = points[tri].mean(axis=1)
    tri = tri[plate_region(nominal, centroid[:, 0], centroid[:, 1])]
    # faces counter-clockwise seen from -z_p (the cameras' side): clockwise in (x_p, y_p)
    a, b, c = (points[tri[:, i]] for i in range(3))
    ccw = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]) > 0
    tri[ccw] = tri[ccw][:, ::-1]
    used = np.unique(tri)
    remap = np.full(len(points), -1)
    remap[used] = np.arange(used.size)
    xy = points[used]
    z, _, _ = plate_height(nominal, xy[:, 0], xy[:, 1])
    return trimesh.Trimesh(vertices=np.column_stack([xy, z]), faces=remap[tri], process=False)


def _saddle_mesh(plate: PlateSpec, n: int = 61):
    """Nominal saddle as a triangle mesh in the plate frame (mm), ``n x n`` vertices."""
    import trimesh

    nominal = PlateSpec(
        shape=plate.shape,
        radius_mm=plate.radius_mm,
        radius2_mm=plate.radius2_mm,
        convex=plate.convex,
        size_mm=plate.size_mm,
    )
    xs = np.linspace(-plate.size_mm[0] / 2, plate.size_mm[0] / 2, n)
    ys = np.linspace(-plate.size_mm[1] / 2, plate.size_mm[1] / 2, n)
    gx, gy = np.meshgrid(xs, ys)
    gz, _, _ = plate_height(nominal, gx, gy)
    vertices = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


# --------------------------------------------------------------------------- calibration boards


def _board_pose(rng: np.random.Generator, distance_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """A random board pose: R_cam_board (3, 3), centre t (3,) mm, board facing the camera."""
    rx, ry = rng.uniform(-np.radians(35), np.radians(35), 2)
    rz = rng.uniform(-np.radians(12), np.radians(12))
    R = _rot_x(rx) @ _rot_y(ry) @ _rot_z(rz)
    z = rng.uniform(*distance_mm)
    xn, yn = rng.uniform(-0.45, 0.45), rng.uniform(-0.35, 0.35)
    return R, np.array([xn * z, yn * z, z])


def _board_view(
    rays: np.ndarray,
    R_cb: np.ndarray,
    t_cb: np.ndarray,
    squares: tuple[int, int],
    square_mm: float,
    margin_sq: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Grey image (H, W) float32 in [0, 1] of an area-antialiased board; ``t_cb`` = board centre."""
    h, w = rays.shape[:2]
    nb = R_cb[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (nb @ t_cb) / (rays @ nb)
    pts = s[..., None] * rays - t_cb
    q = pts @ R_cb  # board frame, mm, origin at the board centre
    a = q[..., 0] / square_mm + squares[0] / 2  # squares, 0 .. n_cols along the board
    b = q[..., 1] / square_mm + squares[1] / 2
    front = np.isfinite(s) & (s > 0)
    a = np.where(front, a, -1e3)
    b = np.where(front, b, -1e3)
    # Pixel footprint in squares (box filter width) from the local derivatives.
    wa = np.abs(np.gradient(a, axis=1)) + np.abs(np.gradient(a, axis=0))
    wb = np.abs(np.gradient(b, axis=1)) + np.abs(np.gradient(b, axis=0))
    wa = np.clip(wa, 1e-3, None)
    wb = np.clip(wb, 1e-3, None)

    def box_square_wave(x, width):
        d = np.arcsin(np.sin(np.pi * x)) / np.pi  # signed distance to the nearest edge, squares
        return np.clip(2.0 * d / width, -1.0, 1.0)

    def box_inside(x, lo, hi, width):
        return np.clip(0.5 + np.minimum(x - lo, hi - x) / width, 0.0, 1.0)

    checker = box_square_wave(a, wa) * box_square_wave(b, wb)
    black, white = 0.08, 0.85
    grid_val = 0.5 * (black + white) - 0.5 * (white - black) * checker
    in_grid = box_inside(a, 0, squares[0], wa) * box_inside(b, 0, squares[1], wb)
    in_board = box_inside(a, -margin_sq, squares[0] + margin_sq, wa) * box_inside(
        b, -margin_sq, squares[1] + margin_sq, wb
    )
    background = 0.3 + 0.08 * _smooth_noise(rng, (h, w), 5)
    board = in_grid * grid_val + (1.0 - in_grid) * white
    img = in_board * board + (1.0 - in_board) * background
    # Uneven illumination: brighter in the middle of the image.
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 2) / (h / 2)) ** 2
    return (img * (1.0 - 0.12 * r2)).astype(np.float32)


def render_calibration_pairs(
    out_dir: str | Path,
    *,
    rig: StereoRig | None = None,
    n_pairs: int = 12,
    inner_corners: tuple[int, int] = (9, 6),
    square_mm: float = 100.0,
    seed: int = 0,
    blur_px: float = 0.7,
    noise: float = 0.01,
) -> list[Path]:
    """Render checkerboard pairs of the binocular head for calibration (Zhang 2000).

    Each pair shows one board pose in both cameras, fully inside both images, rendered through
    each camera's K and distortion (raw pixels undistorted to rays, intersected with the board
    plane, the checker box-filtered over the pixel footprint), then Gaussian blur, additive
    Gaussian noise and 8-bit quantisation.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    rig : StereoRig or None
        None: :func:`default_rig` (1224 x 1024).
    n_pairs : int
        Number of pairs, >= 1.
    inner_corners : (int, int)
        Inner corners (columns, rows) as ``cv2.findChessboardCorners`` counts them.
    square_mm : float
        Side of one square, mm. The board has a white border of 0.6 square around the squares.
    seed : int
    blur_px : float
        Std of the Gaussian blur (optics), pixels; 0 for none.
    noise : float
        Std of the sensor noise, fraction of full scale (255).

    Returns
    -------
    list of Path
        ``[left01.png, right01.png, left02.png, right02.png, ...]`` in ``out_dir`` (names as
        ``plate-inspect calibrate`` expects). ``out_dir/board_truth.npz`` holds the true poses:
        ``R_cam_board`` (P, 3, 3), ``t_cam_board`` (P, 3) mm (left frame; board frame origin at the
        board centre, x along the columns), ``object_points`` (C, 3) mm of the inner corners in
        the board frame in ``findChessboardCorners`` row-major order up to the board's symmetry.

    Raises
    ------
    ValueError
        Bad options, or no pose fitting both images found (board too large for the field).
    """
    if rig is None:
        rig = default_rig()
    elif not isinstance(rig, StereoRig):
        raise TypeError(f"rig: expected a StereoRig or None, got {type(rig).__name__}")
    if not isinstance(n_pairs, (int, np.integer)) or n_pairs < 1:
        raise ValueError(f"n_pairs: expected an integer >= 1, got {n_pairs}")
    cols, rows = (int(v) for v in inner_corners)
    if len(tuple(inner_corners)) != 2 or cols < 2 or rows < 2:
        raise ValueError(f"inner_corners: expected (columns, rows) >= 2 each, got {inner_corners}")
    if not (math.isfinite(square_mm) and square_mm > 0):
        raise ValueError(f"square_mm: expected > 0, got {square_mm}")
    if not (math.isfinite(blur_px) and blur_px >= 0):
        raise ValueError(f"blur_px: expected >= 0, got {blur_px}")
    if not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise: expected >= 0, got {noise}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    squares = (cols + 1, rows + 1)
    margin_sq = 0.6
    w, h = rig.image_size
    # Distances at which the board spans roughly 35 .. 60 % of the image width.
    board_w = (squares[0] + 2 * margin_sq) * square_mm
    fx = rig.left.K[0, 0]
    dist_range = (fx * board_w / (0.60 * w), fx * board_w / (0.35 * w))
    half = np.array([squares[0] / 2 + margin_sq, squares[1] / 2 + margin_sq]) * square_mm
    outline = np.array([[-half[0], -half[1], 0], [half[0], -half[1], 0], [half[0], half[1], 0], [-half[0], half[1], 0]])
    # Densify the outline so distortion cannot push an edge out between corners.
    edge = np.linspace(0, 1, 9)[:, None]
    outline = np.concatenate([outline[i] + edge * (outline[(i + 1) % 4] - outline[i]) for i in range(4)])

    rays_l = _raw_pixel_rays(rig.left)
    rays_r = _raw_pixel_rays(rig.right)
    digits = max(2, len(str(n_pairs)))
    paths: list[Path] = []
    Rs, ts = [], []
    margin_px = 0.04 * w
    for i in range(n_pairs):
        for _ in range(2000):
            R_lb, t_lb = _board_pose(rng, dist_range)
            R_rb = rig.R @ R_lb
            t_rb = rig.R @ t_lb + rig.T
            ok = True
            for cam, Rc, tc in ((rig.left, R_lb, t_lb), (rig.right, R_rb, t_rb)):
                pc = outline @ Rc.T + tc
                # In front, facing the camera, and seen within 50 deg of head-on (oblique views of
                # the right camera, toed in and 800 mm aside, would otherwise defeat the detector).
                if np.any(pc[:, 2] <= 0) or (Rc[:, 2] @ tc) / np.linalg.norm(tc) < _BOARD_MIN_COS:
                    ok = False
                    break
                uv = cam.project(pc)
                if np.any(uv < margin_px) or np.any(uv[:, 0] > w - 1 - margin_px) or np.any(uv[:, 1] > h - 1 - margin_px):
                    ok = False
                    break
            if ok:
                break
        else:
            raise ValueError(
                f"square_mm: no board pose of {squares[0]} x {squares[1]} squares of {square_mm} mm fits both images"
            )
        Rs.append(R_lb)
        ts.append(t_lb)
        for side, rays, Rc, tc in (("left", rays_l, R_lb, t_lb), ("right", rays_r, R_rb, t_rb)):
            img = _board_view(rays, Rc, tc, squares, square_mm, margin_sq, rng)
            if blur_px > 0:
                img = cv2.GaussianBlur(img, (0, 0), blur_px)
            img = img + np.float32(noise) * rng.standard_normal(img.shape, np.float32)
            path = out / f"{side}{i + 1:0{digits}d}.png"
            _write_png(path, _quantise(img, 8))
            paths.append(path)
    gx, gy = np.meshgrid(np.arange(1, cols + 1) - squares[0] / 2, np.arange(1, rows + 1) - squares[1] / 2)
    obj = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1) * square_mm
    np.savez(out / "board_truth.npz", R_cam_board=np.array(Rs), t_cam_board=np.array(ts), object_points=obj)
    return paths
