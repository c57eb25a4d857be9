"""What the simulated cell holds: the plate (shape, outline, openings, dents, pose) and what lies under it.

A plate is a height field ``h(x_p, y_p)`` in a *plate frame* (x_p, y_p in the plate's plane, z_p pointing
away from the cameras, origin at the plate centre, ``h(0, 0) = 0``); ``T_cam_plate``
(:func:`pipeline.simulate.geometry.plate_pose`) maps plate-frame points into the left-camera frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

ShapeName = Literal["plane", "cylinder", "sphere", "saddle"]


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
                raise ValueError(
                    f"Dent.{name}: expected a finite number, got {getattr(self, name)}"
                )
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
                raise ValueError(
                    f"Cutout.{name}: expected a finite number, got {getattr(self, name)}"
                )
            object.__setattr__(self, name, value)
        if self.width_mm <= 0 or self.height_mm <= 0:
            raise ValueError(
                f"Cutout.width_mm, height_mm: expected > 0, got {self.width_mm}, {self.height_mm}"
            )
        if not 0 <= self.corner_mm <= min(self.width_mm, self.height_mm) / 2 + 1e-9:
            raise ValueError(
                f"Cutout.corner_mm: expected in [0, {min(self.width_mm, self.height_mm) / 2:g}] mm, got {self.corner_mm}"
            )

    @classmethod
    def circle(cls, x_mm: float, y_mm: float, radius_mm: float) -> Cutout:
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
        edge: np.ndarray = densify(np.concatenate(corners), step_mm) + np.array(
            [self.x_mm, self.y_mm]
        )
        return edge


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
                raise ValueError(
                    f"Support.{name}: expected a finite number, got {getattr(self, name)}"
                )
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


def rail_supports(
    size_mm: tuple[float, float],
    gap_mm: float,
    n: int,
    *,
    heights_mm: tuple[float, float] = (200.0, 400.0),
    width_mm: float = 150.0,
    overhang_mm: float = 500.0,
) -> tuple[Support, ...]:
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
            raise ValueError(
                f"PlateSpec.shape: expected plane, cylinder, sphere or saddle, got {self.shape!r}"
            )
        size = tuple(float(v) for v in self.size_mm)
        if len(size) != 2 or not all(math.isfinite(v) and v > 0 for v in size):
            raise ValueError(
                f"PlateSpec.size_mm: expected two positive sizes in mm, got {self.size_mm}"
            )
        object.__setattr__(self, "size_mm", size)
        half_w, half_h = size[0] / 2, size[1] / 2
        if self.shape != "plane":
            if self.radius_mm is None or not math.isfinite(self.radius_mm) or self.radius_mm <= 0:
                raise ValueError(
                    f"PlateSpec.radius_mm: expected a positive radius for a {self.shape}, got {self.radius_mm}"
                )
            need = {"cylinder": half_w, "sphere": math.hypot(half_w, half_h), "saddle": half_w}[
                self.shape
            ]
            if self.radius_mm <= need:
                raise ValueError(
                    f"PlateSpec.radius_mm: expected > {need:.1f} mm for a {self.shape} of size {size}, got {self.radius_mm}"
                )
        if (
            self.shape == "saddle"
            and self.radius2_mm is not None
            and (not math.isfinite(self.radius2_mm) or self.radius2_mm <= half_h)
        ):
            raise ValueError(
                f"PlateSpec.radius2_mm: expected > {half_h:.1f} mm for a saddle, got {self.radius2_mm}"
            )
        if not math.isfinite(self.distance_mm) or self.distance_mm <= 0:
            raise ValueError(f"PlateSpec.distance_mm: expected > 0, got {self.distance_mm}")
        tilt = tuple(float(v) for v in self.tilt_deg)
        if len(tilt) != 2 or not all(math.isfinite(v) and abs(v) < 60 for v in tilt):
            raise ValueError(
                f"PlateSpec.tilt_deg: expected two angles within +-60 deg, got {self.tilt_deg}"
            )
        object.__setattr__(self, "tilt_deg", tilt)
        if not math.isfinite(self.in_plane_deg):
            raise ValueError(
                f"PlateSpec.in_plane_deg: expected a finite angle, got {self.in_plane_deg}"
            )
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
            if (
                vertices.ndim != 2
                or vertices.shape[0] < 3
                or vertices.shape[1] != 2
                or not np.isfinite(vertices).all()
            ):
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
            raise TypeError(
                f"PlateSpec.floor: expected a Floor or None, got {type(self.floor).__name__}"
            )

    @property
    def curved_radius_mm(self) -> float:
        """The radius of a curved plate (a saddle's along x_p), mm; ValueError for a plane."""
        if self.radius_mm is None:
            raise ValueError(
                f"PlateSpec.radius_mm: a {self.shape} plate needs its radius, got none"
            )
        return self.radius_mm

    @property
    def lit_floor(self) -> Floor:
        """The shop floor of a plate over one; ValueError over the dark conveyor (``floor`` None)."""
        if self.floor is None:
            raise ValueError("PlateSpec.floor: the plate lies on the dark conveyor, not a floor")
        return self.floor

    @property
    def radius2(self) -> float | None:
        """Saddle radius along y_p (``radius2_mm`` or ``radius_mm``), mm; None for other shapes."""
        if self.shape != "saddle":
            return None
        return self.radius2_mm if self.radius2_mm is not None else self.radius_mm


def densify(polygon: np.ndarray, step_mm: float) -> np.ndarray:
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
