"""A simulated capture bundle: what the binocular head with a ring of lights records, and the truth behind it.

Shading (intensities as fractions of the sensor's full scale ``2**bit_depth - 1``)::

    I_k = exposure * e_k * (albedo * max(0, n . l_k) + specular * [n . l_k > 0] * max(0, n . h_k)**shininess)
          + dark + N(0, noise**2)

with ``h_k`` the Blinn-Phong half vector of the light and the per-pixel view direction, the light's
direction and attenuation per pixel (:class:`pipeline.lights.model.Lights`). Attached shadows come from
``max(0, .)``; cast shadows and interreflections are not modelled. Values are quantised to
``bit_depth`` and saturate at full scale.

``truth.npz`` holds, on the LEFT UNDISTORTED grid (pixel (u, v) sees ray ``K^-1 (u, v, 1)``):
``depth_mm`` (H, W) float64 z along the optical axis, NaN off the plate; ``normals`` (H, W, 3) float32
camera frame, towards the camera, NaN off the plate; ``mask`` (H, W) bool; ``albedo`` (H, W) float32
(the conveyor's off the plate); ``plate_xy_mm`` (H, W, 2) float32 plate-frame coordinates, NaN off the
plate; on the RAW grid ``depth_raw_mm`` float32 and ``mask_raw``; and ``radius_mm``, ``radius2_mm``
(NaN if none), ``shape``, ``convex``, ``size_mm``, ``dents`` (D, 4) rows ``x, y, radius, depth`` mm,
``T_cam_plate`` (4, 4), the true lights: ``light_dirs`` (N, 3) (seen from the plate centre),
``light_intensity`` (N,), ``light_positions_mm`` (N, 3) (NaN for distant lights), ``light_axes``
(N, 3), ``light_mu`` (N,); ``K``, ``dist``, ``bit_depth``, ``noise``, ``exposure``; ``surface`` (H, W)
int8, what each pixel sees (:data:`~pipeline.simulate.geometry.SURFACE_PLATE`, ``SURFACE_CONVEYOR``,
``SURFACE_FLOOR``, ``SURFACE_SUPPORT + k`` for support k) and ``scene_depth_mm`` (H, W) float32, the
depth of whatever it sees. ``mask`` is exactly ``surface == SURFACE_PLATE``.

Kept as one module (~700 lines, half of them docstrings) on purpose: :class:`CaptureSpec` and the rendering that reads it change
together; the scene, its geometry and textures, the rig, the target and the boards are apart.
"""

from __future__ import annotations

import json
import math
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from pipeline.camera import StereoRig
from pipeline.formats import CAPTURE_FORMAT, CaptureFile, StereoCalibrationFile
from pipeline.io import calibration_document
from pipeline.lights.model import Lights
from pipeline.parallel import default_workers
from pipeline.simulate.geometry import SURFACE_SUPPORT, Hits, conveyor_z, intersect, plate_pose
from pipeline.simulate.rig import BASELINE_MM, default_rig, quantise, raw_pixel_rays, write_png
from pipeline.simulate.scene import PlateSpec
from pipeline.simulate.targets import target_object
from pipeline.simulate.texture import (
    TEXEL_MM,
    Texture,
    conveyor_texture,
    floor_texture,
    plate_albedo_texture,
)

_CAPTURED_AT = "2026-01-01T00:00:00Z"


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
        (see :mod:`pipeline.lights.model`). Each light's ``intensity`` is chosen so that it casts
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
            raise ValueError(
                f"CaptureSpec.light_elevation_deg: expected in (0, 90), got {self.light_elevation_deg}"
            )
        if not 0.0 <= self.intensity_spread < 0.5:
            raise ValueError(
                f"CaptureSpec.intensity_spread: expected in [0, 0.5), got {self.intensity_spread}"
            )
        if not (math.isfinite(self.noise) and self.noise >= 0):
            raise ValueError(
                f"CaptureSpec.noise: expected a fraction of full scale >= 0, got {self.noise}"
            )
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
            raise ValueError(
                f"CaptureSpec.texture: expected rusty, painted or uniform, got {self.texture!r}"
            )
        if self.working_distance_mm is not None and not (
            math.isfinite(self.working_distance_mm) and self.working_distance_mm > 0
        ):
            raise ValueError(
                f"CaptureSpec.working_distance_mm: expected > 0 or None, got {self.working_distance_mm}"
            )
        if self.width < 64 or self.height < 64:
            raise ValueError(
                f"CaptureSpec.width, height: expected at least 64 x 64, got {self.width} x {self.height}"
            )
        if self.near_field_mm is not None and not (
            math.isfinite(self.near_field_mm) and self.near_field_mm > 0
        ):
            raise ValueError(
                f"CaptureSpec.near_field_mm: expected a height > 0 mm or None, got {self.near_field_mm}"
            )
        if not (math.isfinite(self.led_mu) and self.led_mu >= 0):
            raise ValueError(f"CaptureSpec.led_mu: expected >= 0, got {self.led_mu}")
        if not (math.isfinite(self.light_error_deg) and 0 <= self.light_error_deg < 30):
            raise ValueError(
                f"CaptureSpec.light_error_deg: expected in [0, 30), got {self.light_error_deg}"
            )
        if self.manifest_lights not in ("exact", "nominal"):
            raise ValueError(
                f"CaptureSpec.manifest_lights: expected exact or nominal, got {self.manifest_lights!r}"
            )

    def light_directions(self) -> np.ndarray:
        """(n_lights, 3) float64 unit vectors, left-camera frame, from the surface towards each light."""
        el = math.radians(self.light_elevation_deg)
        phi = (
            math.radians(self.light_azimuth_deg)
            + 2.0 * np.pi * np.arange(self.n_lights) / self.n_lights
        )
        return np.stack(
            [
                math.sin(el) * np.cos(phi),
                math.sin(el) * np.sin(phi),
                np.full(phi.shape, -math.cos(el)),
            ],
            1,
        )

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
        reach = (
            self.near_field_mm / -dirs[:, 2]
        )  # distance along each direction to the lights' plane
        positions = centre + reach[:, None] * dirs
        axes = -dirs
        unit = Lights.points(
            positions, np.ones(len(dirs)), axes=axes, mu=np.full(len(dirs), self.led_mu)
        )
        at_centre = unit.attenuation_at(centre)  # cos(theta) = 1 on the axis
        return unit.with_intensity(np.asarray(intensities) / at_centre)


@dataclass(frozen=True)
class _Scene:
    """The plate posed in front of the rig, its texture, and the texture of what lies behind it."""

    plate: PlateSpec
    T_cam_plate: np.ndarray
    albedo: Texture
    conveyor: Texture  # the conveyor's texture, or the floor's when the plate lies over a floor


def _render_view(scene: _Scene, origin: np.ndarray, rays: np.ndarray) -> tuple[Hits, np.ndarray]:
    """Hits and albedo (H, W) float32 for rays (H, W, 3) from ``origin`` (left-camera frame)."""
    hits = intersect(scene.plate, scene.T_cam_plate, origin, rays)
    x = hits.xyz_plate[..., 0]
    y = hits.xyz_plate[..., 1]
    albedo = np.where(hits.on_plate, scene.albedo.sample(x, y), scene.conveyor.sample(x, y))
    floor = scene.plate.floor
    if floor is not None:
        for k, sup in enumerate(
            floor.supports
        ):  # the floor's texture, scaled to the support's albedo
            albedo = np.where(
                hits.surface == SURFACE_SUPPORT + k,
                albedo * np.float32(sup.albedo / floor.albedo),
                albedo,
            )
    return hits, albedo.astype(np.float32)


def _shade(
    hits: Hits,
    albedo: np.ndarray,
    points_cam: np.ndarray,
    eye: np.ndarray,
    lights: Lights,
    capture: CaptureSpec,
) -> np.ndarray:
    """Noise-free radiance (N, H, W) float32 in fractions of full scale, dark not added.

    Per pixel and light: the direction towards the light and its attenuation at the surface point
    (:class:`pipeline.lights.model.Lights`; constant for distant lights).
    """
    n = hits.normals.astype(np.float32)
    out = np.empty((lights.n, *albedo.shape), dtype=np.float32)
    view = None
    if capture.specular > 0:
        view = eye.astype(np.float32) - points_cam.astype(np.float32)
        view /= np.linalg.norm(view, axis=-1, keepdims=True)
    for k in range(lights.n):
        one = Lights(
            lights.directions[k : k + 1],
            lights.positions_mm[k : k + 1],
            lights.axes[k : k + 1],
            lights.mu[k : k + 1],
            lights.intensity[k : k + 1],
        )
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
    far = plate.distance_mm + conveyor_z(plate) + plate.lit_floor.gap_mm
    field = max(w / rig.left.K[0, 0], h / rig.left.K[1, 1]) * far
    return float(1.2 * field + BASELINE_MM)


def _bumped(
    lights: Lights, centre_mm: np.ndarray, error_deg: float, rng: np.random.Generator
) -> Lights:
    """Every light turned by ``error_deg`` about ``centre_mm``, each about a random axis across its direction."""
    if error_deg == 0:
        return lights
    dirs = lights.directions_at(centre_mm)
    angle = math.radians(error_deg)
    directions, positions, axes = (
        lights.directions.copy(),
        lights.positions_mm.copy(),
        lights.axes.copy(),
    )
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
    pose: np.ndarray | None = None,
    station: dict[str, Any] | None = None,
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
    pose : (4, 4) float or None
        ``T_cam_plate`` in place of :func:`~pipeline.simulate.plate_pose` (a station of a long plate
        that the conveyor moved under the head, :func:`~pipeline.simulate.simulate_stations`). Point
        lights then stay where ``plate_pose`` would put them (they belong to the head, not the plate).
    station : dict or None
        Written as capture.json's ``station`` (``index``, ``travel_mm``, ``direction``).

    Returns
    -------
    Path
        ``out_dir``, holding ``capture.json`` (``plate-capture/1``), ``calibration.json``
        (``stereo-calibration/1`` of the rig), ``target.json`` (``plate-target/1`` of the nominal shape
        without dents; a saddle, and a plate with another outline or with openings, is written as a
        mesh target with ``target.stl``, see :func:`pipeline.simulate.plate_mesh`), the images
        ``ps_00.png`` ... (left camera, raw/distorted, one light each), ``dark.png``,
        ``stereo_left.png``, ``stereo_right.png`` (when ``capture.stereo``), and ``truth.npz`` (its
        arrays: see the module docstring).

    Raises
    ------
    ValueError
        Bad option values, or a plate that does not lie in front of the cameras.
    """
    rig = _check_arguments(plate, capture, rig, plate_id, tolerance_mm)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seeds = np.random.SeedSequence(int(seed)).spawn(6)
    rng_lights, rng_noise, rng_dark, rng_stereo = (np.random.default_rng(s) for s in seeds[:4])
    tex_seed = (
        capture.albedo_seed
        if capture.albedo_seed is not None
        else int(seeds[4].generate_state(1)[0])
    )
    conveyor_seed = int(seeds[5].generate_state(1)[0])
    scene = _scene(plate, capture, rig, tex_seed, conveyor_seed)
    if pose is not None:
        scene = _Scene(scene.plate, np.asarray(pose, np.float64), scene.albedo, scene.conveyor)
    spread = capture.intensity_spread
    intensities = rng_lights.uniform(1.0 - spread, 1.0 + spread, capture.n_lights)
    centre = plate_pose(plate)[:3, 3] if pose is not None else scene.T_cam_plate[:3, 3]
    lights = capture.lights(centre, intensities)
    written = _bumped(lights, centre, capture.light_error_deg, rng_lights)
    if lights.any_point and capture.manifest_lights == "nominal":
        written = written.nominal_directions(centre)
    image_names, hits_raw = _write_images(
        out,
        scene,
        rig,
        lights,
        capture,
        (rng_noise, rng_dark, rng_stereo),
        workers or default_workers(),
    )
    _write_truth(out, scene, rig, hits_raw, lights, capture)
    _write_documents(
        out, rig, plate, capture, plate_id, tolerance_mm, image_names, written, station
    )
    return out


def render_radiance(
    plate: PlateSpec,
    rig: StereoRig,
    lights: Lights,
    *,
    side: Literal["left", "right"],
    capture: CaptureSpec = CaptureSpec(),
    seed: int = 0,
    pose: np.ndarray | None = None,
) -> np.ndarray:
    """What one camera of the rig sees of the plate under each light alone, before the sensor.

    The scene (plate, texture, conveyor or floor) is the one :func:`simulate_capture` renders for the
    same ``plate``, ``capture`` and ``seed``; the lights are any lights (``capture``'s own are not used).
    A cell simulator adds the dark level, noise and quantisation of its sensor.

    Parameters
    ----------
    plate : PlateSpec
    rig : StereoRig
    lights : pipeline.lights.model.Lights
        Left-camera frame, mm.
    side : {"left", "right"}
    capture : CaptureSpec
        Its ``exposure``, ``specular``, ``shininess``, ``texture`` and ``albedo_seed`` are used.
    seed : int
    pose : (4, 4) float or None
        ``T_cam_plate`` in place of :func:`~pipeline.simulate.plate_pose`, as for
        :func:`simulate_capture` (a station of a long plate that a conveyor carried under the head).

    Returns
    -------
    (N, H, W) float32
        Noise-free radiance of light k on the camera's raw (distorted) pixel grid, in fractions of
        full scale (``capture.exposure`` for a white plate facing the light head-on), dark not added;
        ``(W, H)`` is the camera's ``image_size``.

    Raises
    ------
    ValueError
        The camera sees no part of the plate.
    """
    if side not in ("left", "right"):
        raise ValueError(f"side: expected 'left' or 'right', got {side!r}")
    seeds = np.random.SeedSequence(int(seed)).spawn(6)
    tex_seed = (
        capture.albedo_seed
        if capture.albedo_seed is not None
        else int(seeds[4].generate_state(1)[0])
    )
    scene = _scene(plate, capture, rig, tex_seed, int(seeds[5].generate_state(1)[0]))
    if pose is not None:
        scene = _Scene(scene.plate, np.asarray(pose, np.float64), scene.albedo, scene.conveyor)
    camera = getattr(rig, side)
    rays = raw_pixel_rays(camera)
    eye = np.zeros(3)
    if side == "right":
        rays = rays @ rig.R  # directions into the left frame: R^T r
        eye = -rig.R.T @ rig.T
    hits, albedo = _render_view(scene, eye, rays)
    if not hits.on_plate.any():
        raise ValueError(
            f"plate: no pixel of the {side} camera sees the plate (check distance_mm, tilt_deg, size_mm)"
        )
    return _shade(hits, albedo, eye + hits.s[..., None] * rays, eye, lights, capture)


def _check_arguments(
    plate: PlateSpec,
    capture: CaptureSpec,
    rig: StereoRig | None,
    plate_id: str,
    tolerance_mm: float,
) -> StereoRig:
    """The arguments of :func:`simulate_capture` checked; returns the rig (the default one for None)."""
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
    return rig


def _scene(
    plate: PlateSpec, capture: CaptureSpec, rig: StereoRig, tex_seed: int, conveyor_seed: int
) -> _Scene:
    """The plate posed in front of the rig with its texture, and what lies behind it (conveyor or floor)."""
    mm_per_px = plate.distance_mm / rig.left.K[0, 0]
    return _Scene(
        plate=plate,
        T_cam_plate=plate_pose(plate),
        albedo=plate_albedo_texture(
            plate, capture.texture, tex_seed, max(TEXEL_MM, mm_per_px / 2)
        ).prefiltered(mm_per_px),
        conveyor=(
            conveyor_texture(plate, conveyor_seed)
            if plate.floor is None
            else floor_texture(
                plate, conveyor_seed, max(4.0, mm_per_px / 2), _floor_span_mm(plate, rig)
            )
        ).prefiltered(mm_per_px),
    )


def _write_images(
    out: Path,
    scene: _Scene,
    rig: StereoRig,
    lights: Lights,
    capture: CaptureSpec,
    rngs: tuple[np.random.Generator, ...],
    workers: int,
) -> tuple[list[str], Hits]:
    """Render and write the photometric images, the dark frame and the stereo pair.

    PNG encoding (cv2 releases the GIL) overlaps with rendering on ``workers`` threads. ``rngs``: the
    generators of the noise, the dark frames and the stereo pair. Returns the photometric images' names
    and the left camera's hits on its raw grid.
    """
    rng_noise, rng_dark, rng_stereo = rngs
    pool = ThreadPoolExecutor(max_workers=workers)
    writes = []
    try:
        # ---- left camera, raw grid: photometric images and dark frame
        w, h = rig.image_size
        left_rays = raw_pixel_rays(rig.left)
        eye_left = np.zeros(3)
        hits_raw, albedo_raw = _render_view(scene, eye_left, left_rays)
        if not hits_raw.on_plate.any():
            raise ValueError(
                "plate: no pixel of the left camera sees the plate (check distance_mm, tilt_deg, size_mm)"
            )
        points_raw = hits_raw.s[..., None] * left_rays
        radiance = _shade(hits_raw, albedo_raw, points_raw, eye_left, lights, capture)
        dark_map = _dark_map(capture, rng_dark, (h, w))
        image_names = [f"ps_{k:02d}.png" for k in range(capture.n_lights)]
        for k, name in enumerate(image_names):
            noisy = (
                radiance[k]
                + dark_map
                + np.float32(capture.noise) * rng_noise.standard_normal((h, w), np.float32)
            )
            writes.append(pool.submit(write_png, out / name, quantise(noisy, capture.bit_depth)))
        dark = dark_map + np.float32(capture.noise) * rng_noise.standard_normal((h, w), np.float32)
        writes.append(pool.submit(write_png, out / "dark.png", quantise(dark, capture.bit_depth)))
        if capture.stereo:  # all lights on, each at 1/N power
            writes += _write_stereo_pair(
                out,
                scene,
                rig,
                lights,
                capture,
                radiance.mean(axis=0),
                dark_map,
                (rng_dark, rng_stereo),
                pool,
            )
    finally:
        pool.shutdown(wait=True)
    for done in writes:
        done.result()  # re-raise a failed write
    return image_names, hits_raw


def _dark_map(
    capture: CaptureSpec, rng_dark: np.random.Generator, shape: tuple[int, int]
) -> np.ndarray:
    """A camera's dark level with its fixed pattern (H, W) float32, fractions of full scale."""
    dark_map = (capture.dark_level + 0.001 * rng_dark.standard_normal(shape)).astype(np.float32)
    if capture.dark_level == 0:
        dark_map[:] = 0.0
    return dark_map


def _write_stereo_pair(
    out: Path,
    scene: _Scene,
    rig: StereoRig,
    lights: Lights,
    capture: CaptureSpec,
    flash: np.ndarray,
    dark_map: np.ndarray,
    rngs: tuple[np.random.Generator, ...],
    pool: ThreadPoolExecutor,
) -> list[Future[Any]]:
    """Submit the stereo pair's writes; ``flash`` is the left camera's radiance with all lights on, ``rngs``
    the generators of the dark frame and of the pair's noise. Returns the futures."""
    rng_dark, rng_stereo = rngs
    w, h = rig.image_size
    left_img = (
        flash
        + dark_map
        + np.float32(capture.noise) * rng_stereo.standard_normal((h, w), np.float32)
    )
    writes = [
        pool.submit(write_png, out / "stereo_left.png", quantise(left_img, capture.bit_depth))
    ]
    right_rays_cam = raw_pixel_rays(rig.right)
    right_rays = right_rays_cam @ rig.R  # directions into the left frame: R^T r
    eye_right = -rig.R.T @ rig.T
    hits_r, albedo_r = _render_view(scene, eye_right, right_rays)
    points_r = eye_right + hits_r.s[..., None] * right_rays
    flash_r = _shade(hits_r, albedo_r, points_r, eye_right, lights, capture).mean(axis=0)
    dark_r = _dark_map(capture, rng_dark, (h, w))
    right_img = (
        flash_r
        + dark_r
        + np.float32(capture.noise) * rng_stereo.standard_normal((h, w), np.float32)
    )
    writes.append(
        pool.submit(write_png, out / "stereo_right.png", quantise(right_img, capture.bit_depth))
    )
    return writes


def _write_truth(
    out: Path, scene: _Scene, rig: StereoRig, hits_raw: Hits, lights: Lights, capture: CaptureSpec
) -> None:
    """``truth.npz`` (see the module docstring), on the left camera's undistorted grid."""
    plate, T_cam_plate = scene.plate, scene.T_cam_plate
    und_rays = rig.left.pixel_rays()
    hits_u, albedo_u = _render_view(scene, np.zeros(3), und_rays)
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
        radius_mm=np.float64(
            plate.radius_mm if plate.shape != "plane" and plate.radius_mm else np.nan
        ),
        radius2_mm=np.float64(plate.radius2 if plate.radius2 is not None else np.nan),
        shape=np.array(plate.shape),
        convex=np.bool_(plate.convex),
        size_mm=np.array(plate.size_mm),
        dents=np.array(
            [[d.x_mm, d.y_mm, d.radius_mm, d.depth_mm] for d in plate.dents], dtype=np.float64
        ).reshape(-1, 4),
        T_cam_plate=T_cam_plate,
        light_dirs=lights.directions_at(T_cam_plate[:3, 3]),
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


def _write_documents(
    out: Path,
    rig: StereoRig,
    plate: PlateSpec,
    capture: CaptureSpec,
    plate_id: str,
    tolerance_mm: float,
    image_names: list[str],
    written: Lights,
    station: dict[str, Any] | None = None,
) -> None:
    """``calibration.json``, ``target.json`` (and its mesh) and ``capture.json``, each checked against its format."""
    calibration_doc = calibration_document(rig)
    StereoCalibrationFile.model_validate(calibration_doc)
    (out / "calibration.json").write_text(json.dumps(calibration_doc, indent=2))
    (out / "target.json").write_text(json.dumps(target_object(plate, tolerance_mm, out), indent=2))
    capture_obj: dict[str, Any] = {
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
    if station is not None:
        capture_obj["station"] = station
    CaptureFile.model_validate(capture_obj)
    (out / "capture.json").write_text(json.dumps(capture_obj, indent=2))
