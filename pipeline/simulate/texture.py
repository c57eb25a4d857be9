"""Textures of the simulated scene: the plate's paint and rust, the dark conveyor, the shop floor."""

from __future__ import annotations

import math

import cv2
import numpy as np

from .scene import PlateSpec

#: Finest plate texture step, mm per texel (coarser when a camera pixel covers more than 2 texels).
TEXEL_MM = 1.5


class Texture:
    """A 2-D scalar texture over a rectangle of plane coordinates (mm), sampled bilinearly."""

    def __init__(self, values: np.ndarray, x0_mm: float, y0_mm: float, texel_mm: float) -> None:
        self.values = np.ascontiguousarray(values, dtype=np.float32)
        self.x0 = x0_mm
        self.y0 = y0_mm
        self.texel = texel_mm

    def prefiltered(self, footprint_mm: float) -> Texture:
        """The texture blurred to the footprint of a camera pixel (anti-aliasing), mm."""
        sigma = 0.5 * footprint_mm / self.texel
        if sigma < 0.3:
            return self
        vals = cv2.GaussianBlur(self.values, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        return Texture(vals, self.x0, self.y0, self.texel)

    def sample(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Bilinear samples at plane points; (H, W) in, (H, W) float32 out (edge values continue)."""
        mx = ((x_mm - self.x0) / self.texel).astype(np.float32)
        my = ((y_mm - self.y0) / self.texel).astype(np.float32)
        return cv2.remap(self.values, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cells: int) -> np.ndarray:
    """Zero-mean, unit-std smooth noise with about ``cells`` features across the larger side."""
    h, w = shape
    gh = max(2, int(round(cells * h / max(h, w)))) + 3
    gw = max(2, int(round(cells * w / max(h, w)))) + 3
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    # Crop a margin so the cubic upsampling has no edge artefacts.
    big = cv2.resize(
        coarse, (w * gw // (gw - 3) + 1, h * gh // (gh - 3) + 1), interpolation=cv2.INTER_CUBIC
    )
    off_y = (big.shape[0] - h) // 2
    off_x = (big.shape[1] - w) // 2
    out = big[off_y : off_y + h, off_x : off_x + w]
    normalised: np.ndarray = (out - out.mean()) / (out.std() + 1e-12)
    return normalised


def plate_albedo_texture(plate: PlateSpec, kind: str, seed: int, texel_mm: float) -> Texture:
    """Painted steel with rust blotches and grain of a few texels, fixed to the plate."""
    margin = 30.0
    w_mm = plate.size_mm[0] + 2 * margin
    h_mm = plate.size_mm[1] + 2 * margin
    nx = int(math.ceil(w_mm / texel_mm)) + 1
    ny = int(math.ceil(h_mm / texel_mm)) + 1
    x0 = -plate.size_mm[0] / 2 - margin
    y0 = -plate.size_mm[1] / 2 - margin
    if kind == "uniform":
        return Texture(np.full((ny, nx), 0.6, np.float32), x0, y0, texel_mm)
    rng = np.random.default_rng(seed)
    paint = 0.62 + 0.05 * smooth_noise(rng, (ny, nx), 6)  # slow variation of the paint
    grain_noise = rng.standard_normal((ny, nx)).astype(np.float32)
    grain: np.ndarray = cv2.GaussianBlur(grain_noise, (0, 0), 1.0)
    grain /= grain.std() + 1e-12
    albedo = paint + 0.05 * grain  # few-mm grain (primer, mill scale)
    if kind == "rusty":
        blotch = smooth_noise(rng, (ny, nx), int(max(plate.size_mm) / 60))  # ~60 mm features
        patch = smooth_noise(rng, (ny, nx), 5)
        # Rust where the medium noise is high, more of it in some regions than others.
        level = blotch + 0.6 * patch
        rust = np.clip((level - 1.2) / 0.5, 0.0, 1.0)
        rust = rust * rust * (3.0 - 2.0 * rust)  # smoothstep edge
        rust_albedo = (
            0.34 + 0.04 * smooth_noise(rng, (ny, nx), int(max(plate.size_mm) / 15)) + 0.04 * grain
        )
        albedo = (1.0 - rust) * albedo + rust * rust_albedo
    elif kind != "painted":
        raise ValueError(f"CaptureSpec.texture: expected rusty, painted or uniform, got {kind!r}")
    # By construction the albedo stays in about [0.2, 0.85]; guard the physical range explicitly.
    albedo = np.clip(albedo, 0.05, 0.95)
    return Texture(albedo.astype(np.float32), x0, y0, texel_mm)


def conveyor_texture(plate: PlateSpec, seed: int) -> Texture:
    """Dark conveyor (albedo ~0.05, slightly textured, slats across x_p) over a wide area."""
    texel = 10.0
    span = 1.5 * max(plate.size_mm) + 3.0 * plate.distance_mm
    n = int(math.ceil(span / texel)) + 1
    rng = np.random.default_rng(seed)
    low = smooth_noise(rng, (n, n), 10)
    grain: np.ndarray = cv2.GaussianBlur(
        rng.standard_normal((n, n)).astype(np.float32), (0, 0), 1.0
    )
    grain /= grain.std() + 1e-12
    y = np.arange(n, dtype=np.float32)[:, None] * texel
    slats = (np.sin(2 * np.pi * y / 300.0) > 0.92).astype(np.float32)
    albedo = 0.05 + 0.008 * low + 0.006 * grain - 0.02 * slats
    return Texture(np.clip(albedo, 0.01, None), -span / 2, -span / 2, texel)


def floor_texture(plate: PlateSpec, seed: int, texel_mm: float, span_mm: float) -> Texture:
    """Concrete shop floor (plate frame x_p, y_p over ``span_mm`` square, centred): grain, slow
    variation, oil stains, joints every 3 m and a painted safety line, mean ``floor.albedo``."""
    floor = plate.lit_floor
    n = int(math.ceil(span_mm / texel_mm)) + 1
    rng = np.random.default_rng(seed)
    grain: np.ndarray = cv2.GaussianBlur(
        rng.standard_normal((n, n)).astype(np.float32), (0, 0), 0.8
    )
    grain /= grain.std() + 1e-12
    slow = smooth_noise(rng, (n, n), max(2, int(span_mm / 800)))
    stains = smooth_noise(rng, (n, n), max(2, int(span_mm / 300)))
    stain = np.clip((stains - 1.3) / 0.5, 0.0, 1.0)
    stain = stain * stain * (3.0 - 2.0 * stain)
    coords = np.arange(n, dtype=np.float32) * texel_mm - span_mm / 2

    def joint(c: np.ndarray) -> np.ndarray:
        return (np.abs(((c + 1500.0) % 3000.0) - 1500.0) < 8.0).astype(np.float32)

    joints = np.maximum(joint(coords)[None, :], joint(coords)[:, None])
    line_x = plate.size_mm[0] / 2 + 350.0
    line = (np.abs(coords - line_x) < 50.0).astype(np.float32)[None, :]
    c = floor.texture
    albedo = (
        floor.albedo
        * (1.0 + c * (0.10 * grain + 0.08 * slow))
        * (1.0 - 0.45 * c * stain)
        * (1.0 - 0.5 * c * joints)
    )
    albedo = albedo * (1.0 - line) + line * min(0.95, floor.albedo + 0.3 * c)
    return Texture(
        np.clip(albedo, 0.02, 0.95).astype(np.float32), -span_mm / 2, -span_mm / 2, texel_mm
    )
