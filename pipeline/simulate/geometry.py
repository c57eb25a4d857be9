"""The simulated scene's geometry: the plate's pose, outline and height field, and rays cast into the scene.

Every pixel is rendered as a real calibrated camera sees it: its ray is intersected with the surface
(analytic for plane, cylinder and sphere; Newton steps along the ray for the saddle and for dents); rays
that miss the plate's material see the conveyor, or the floor and the supports standing on it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .rig import rot_x, rot_y, rot_z
from .scene import CURVED_SAGITTA, TRAPEZOID_TOP, PlateSpec, densify

#: Conveyor plane behind the plate: this far (mm, along z_p) behind the plate's farthest point.
CONVEYOR_GAP_MM = 40.0


def plate_pose(plate: PlateSpec) -> np.ndarray:
    """``T_cam_plate``: (4, 4) float64 mapping plate-frame points (mm) into the left-camera frame.

    ``R = Rx(tilt_x) @ Ry(tilt_y) @ Rz(in_plane)``, translation ``(0, 0, distance_mm)``.
    """
    tx, ty = (math.radians(a) for a in plate.tilt_deg)
    T = np.eye(4)
    T[:3, :3] = rot_x(tx) @ rot_y(ty) @ rot_z(math.radians(plate.in_plane_deg))
    T[:3, 3] = (0.0, 0.0, plate.distance_mm)
    return T


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
        area2 = np.sum(
            corners[:, 0] * np.roll(corners[:, 1], -1) - np.roll(corners[:, 0], -1) * corners[:, 1]
        )
        return densify(corners if area2 > 0 else corners[::-1], step_mm)
    if plate.outline == "rectangle":
        corners = np.array(
            [[-half_w, -half_h], [half_w, -half_h], [half_w, half_h], [-half_w, half_h]]
        )
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
    return densify(corners, step_mm)


def inside_outline(plate: PlateSpec, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Whether plate-frame points lie inside the plate's outline (its openings not considered)."""
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
    box = (np.abs(x) <= half_w) & (np.abs(y) <= half_h)
    if plate.outline == "rectangle":
        rect: np.ndarray = box
        return rect
    if plate.outline == "trapezoid":
        with np.errstate(invalid="ignore"):
            trapezoid: np.ndarray = box & (
                np.abs(x) <= half_w * (1.0 - 0.5 * (1.0 - TRAPEZOID_TOP) * (1.0 + y / half_h))
            )
        return trapezoid
    if plate.outline == "curved":
        yc, rho = _curved_edge(plate)
        curved: np.ndarray = box & (x * x + (y - yc) ** 2 <= rho * rho)
        return curved
    # a polygon: even-odd crossing count over its edges
    vertices = np.array(plate.outline, dtype=np.float64)
    inside = np.zeros(np.shape(x), dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        for (x0, y0), (x1, y1) in zip(vertices, np.roll(vertices, -1, axis=0)):
            if y0 == y1:
                continue
            crosses = ((y0 > y) != (y1 > y)) & (x < x0 + (y - y0) * (x1 - x0) / (y1 - y0))
            inside ^= crosses
    polygon: np.ndarray = inside & box
    return polygon


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
    inside = inside_outline(plate, x, y)
    for cut in plate.cutouts:
        with np.errstate(invalid="ignore"):
            inside &= ~(cut.signed_distance(x, y) < 0)
    return inside


def plate_height(
    plate: PlateSpec, x_mm: np.ndarray, y_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        R = plate.curved_radius_mm
        root = np.sqrt(R * R - x * x)
        h = c * (R - root)
        hx = c * x / root
        hy = np.zeros_like(x)
    elif plate.shape == "sphere":
        R = plate.curved_radius_mm
        root = np.sqrt(R * R - x * x - y * y)
        h = c * (R - root)
        hx = c * x / root
        hy = c * y / root
    else:  # saddle
        R1 = plate.curved_radius_mm
        R2 = plate.radius2 if plate.radius2 is not None else R1
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
class Hits:
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


def intersect(
    plate: PlateSpec, T_cam_plate: np.ndarray, origin: np.ndarray, dirs: np.ndarray
) -> Hits:
    """Intersect rays ``origin + s * dirs`` (left-camera frame) with the plate, else with the conveyor."""
    R = T_cam_plate[:3, :3]
    t = T_cam_plate[:3, 3]
    o = R.T @ (np.asarray(origin, dtype=np.float64) - t)
    d = dirs @ R  # row-wise R^T d
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    c = 1.0 if plate.convex else -1.0

    with np.errstate(invalid="ignore", divide="ignore"):
        s = -o[2] / dz  # plane z_p = 0
        if plate.shape in ("cylinder", "sphere"):
            Rr = plate.curved_radius_mm
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
            s = _refine_on_height(plate, o, d, s)

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
            z_bg = conveyor_z(plate)
            s_bg = (z_bg - o[2]) / dz
        else:
            s_bg, n_bg, surface_bg = _surroundings(plate, o, d)
    if plate.floor is None:
        s = np.where(on_plate, s, s_bg)
        xyz = np.stack([o[0] + s * dx, o[1] + s * dy, np.where(on_plate, h, z_bg)], axis=-1)
        n_plate = np.stack(
            [np.where(on_plate, hx, 0.0), np.where(on_plate, hy, 0.0), -np.ones_like(s)], axis=-1
        )
        surface = np.where(on_plate, SURFACE_PLATE, SURFACE_CONVEYOR).astype(np.int8)
    else:
        s = np.where(on_plate, s, s_bg)
        xyz = np.stack(
            [o[0] + s * dx, o[1] + s * dy, np.where(on_plate, h, o[2] + s * dz)], axis=-1
        )
        n_plate = np.where(on_plate[..., None], np.stack([hx, hy, -np.ones_like(s)], axis=-1), n_bg)
        surface = np.where(on_plate, SURFACE_PLATE, surface_bg).astype(np.int8)
    n_plate /= np.linalg.norm(n_plate, axis=-1, keepdims=True)
    normals = n_plate @ R.T
    return Hits(s=s, xyz_plate=xyz, normals=normals, on_plate=on_plate, surface=surface)


def _refine_on_height(plate: PlateSpec, o: np.ndarray, d: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Ray parameters ``s`` refined onto the plate's height field (saddles, dents).

    Newton on f(s) = z_p(s) - h(x_p(s), y_p(s)); h is evaluated inside the footprint only
    (constant continuation outside), off-plate rays are sorted out by the caller.
    """
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
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
    return s


def _surroundings(
    plate: PlateSpec, o: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays ``o + s d`` (plate frame) against the floor and the supports: nearest hit ``s`` (...,), its
    outward normal (..., 3) (plate frame, towards the rays' side) and surface code (...,) int8."""
    floor = plate.lit_floor
    z_floor = conveyor_z(plate) - CONVEYOR_GAP_MM + floor.gap_mm
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (z_floor - o[2]) / d[..., 2]
        s = np.where(s > 0, s, np.inf)
        normal = np.zeros(d.shape)
        normal[..., 2] = -1.0
        surface = np.full(s.shape, SURFACE_FLOOR, dtype=np.int8)
        for k, sup in enumerate(floor.supports):
            lo = np.array(
                [
                    sup.x_mm - sup.size_x_mm / 2,
                    sup.y_mm - sup.size_y_mm / 2,
                    z_floor - sup.height_mm,
                ]
            )
            hi = np.array([sup.x_mm + sup.size_x_mm / 2, sup.y_mm + sup.size_y_mm / 2, z_floor])
            t1 = (lo - o) / d
            t2 = (hi - o) / d
            near = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf)
            far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf)
            enter = near.max(axis=-1)
            hit = (enter <= far.min(axis=-1)) & (enter > 0) & (enter < s)
            axis = near.argmax(axis=-1)
            face = np.zeros(d.shape)
            np.put_along_axis(
                face,
                axis[..., None],
                -np.sign(np.take_along_axis(d, axis[..., None], axis=-1)),
                axis=-1,
            )
            s = np.where(hit, enter, s)
            normal = np.where(hit[..., None], face, normal)
            surface = np.where(hit, SURFACE_SUPPORT + k, surface).astype(np.int8)
    return s, normal, surface


def conveyor_z(plate: PlateSpec) -> float:
    """z_p (mm) of the conveyor plane: CONVEYOR_GAP_MM behind the plate's farthest point."""
    half_w, half_h = plate.size_mm[0] / 2, plate.size_mm[1] / 2
    gx, gy = np.meshgrid(np.linspace(-half_w, half_w, 121), np.linspace(-half_h, half_h, 121))
    h, _, _ = plate_height(plate, gx, gy)
    return float(h.max()) + CONVEYOR_GAP_MM
