"""Tiny valid capture bundles for tests; each bad-input test changes one thing.

``write_bundle(tmp_path)`` writes a folder holding ``capture.json``, a
``calibration.json`` whose ``image_size`` matches the images, ``n_lights``
16-bit PNGs of a Lambertian sphere cap lit from a ring of lights, a dark frame
and a stereo pair. Keyword overrides change the capture document or the files:

>>> write_bundle(tmp_path, bit_depth=12)                       # a top-level key of capture.json
>>> write_bundle(tmp_path, working_distance_mm=DELETE)         # remove a key
>>> write_bundle(tmp_path, mutate=lambda d: d["photometric"]["lights"].pop())
>>> write_bundle(tmp_path, files={"ps_02.png": np.zeros((40, 64), np.uint16)})  # replace a file (array or bytes)
>>> write_bundle(tmp_path, omit=["ps_01.png"])                  # do not write a file
>>> write_bundle(tmp_path, as_zip=True, top_folder="plate7")     # a .zip of it
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import cv2
import numpy as np

DELETE = object()

WIDTH, HEIGHT = 64, 48
FX = 80.0


def calibration_doc(width: int = WIDTH, height: int = HEIGHT) -> dict:
    """A ``stereo-calibration/1`` object: two identical cameras, 100 mm baseline along x."""
    K = [[FX, 0.0, (width - 1) / 2], [0.0, FX, (height - 1) / 2], [0.0, 0.0, 1.0]]
    return {
        "format": "stereo-calibration/1",
        "image_size": [width, height],
        "left": {"K": K, "dist": [0.01, -0.002, 0.0, 0.0, 0.0]},
        "right": {"K": K, "dist": [0.0, 0.0, 0.0, 0.0, 0.0]},
        "R": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "T": [-100.0, 0.0, 0.0],
        "rms_px": 0.25,
        "board": {"inner_corners": [9, 6], "square_mm": 30.0},
    }


def target_doc(**overrides) -> dict:
    """A ``plate-target/1`` object (cylinder R 5000 mm), top-level keys overridable."""
    doc = {
        "format": "plate-target/1",
        "shape": {"type": "cylinder", "radius_mm": 5000.0},
        "size_mm": [3000.0, 3000.0],
        "tolerance_mm": 2.0,
    }
    return _apply(doc, overrides)


def light_ring(n: int, *, slant_rad: float = 0.5) -> np.ndarray:
    """(n, 3) unit light directions on a cone of half angle ``slant_rad`` around -z."""
    phi = 2 * np.pi * np.arange(n) / n
    return np.stack(
        [
            np.sin(slant_rad) * np.cos(phi),
            np.sin(slant_rad) * np.sin(phi),
            -np.cos(slant_rad) * np.ones(n),
        ],
        axis=1,
    )


def sphere_images(
    dirs: np.ndarray, width: int, height: int, *, peak: float, seed: int = 0
) -> np.ndarray:
    """(N, H, W) float64 Lambertian images of a sphere cap filling the frame, counts up to ``peak``."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    r = 0.45 * min(width, height)
    x, y = (u - (width - 1) / 2) / r, (v - (height - 1) / 2) / r
    inside = x**2 + y**2 < 1
    nz = -np.sqrt(np.clip(1 - x**2 - y**2, 0, None))
    normals = np.stack([x, y, nz], axis=-1)
    shading = np.clip(normals @ dirs.T, 0, None) * inside[..., None]  # (H, W, N)
    rng = np.random.default_rng(seed)
    images = 0.8 * peak * np.moveaxis(shading, -1, 0) + 0.02 * peak
    return images + rng.normal(0, 0.002 * peak, images.shape)


def write_image(path: Path, image) -> None:
    """Write an array with cv2.imwrite (uint8/uint16 as given) or raw bytes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(image, (bytes, bytearray)):
        path.write_bytes(image)
    elif not cv2.imwrite(str(path), image):
        raise OSError(f"cv2.imwrite failed for {path}")


def write_bundle(
    tmp_path,
    *,
    name: str = "bundle",
    n_lights: int = 4,
    width: int = WIDTH,
    height: int = HEIGHT,
    inline_calibration: bool = False,
    with_dark: bool = True,
    with_stereo: bool = True,
    files: dict | None = None,
    omit=(),
    mutate=None,
    as_zip: bool = False,
    top_folder: str | None = None,
    seed: int = 0,
    **overrides,
) -> Path:
    """Write a small valid capture bundle and return its folder (or .zip) path.

    Parameters
    ----------
    tmp_path : Path
        Where to write (``tmp_path / name``).
    files : dict, optional
        Bundle-relative name -> array (written with cv2.imwrite) or bytes, replacing
        or adding files.
    omit : iterable of str
        Names not to write.
    mutate : callable, optional
        Called with the capture document (a dict) before it is written.
    as_zip, top_folder
        Also pack the folder into ``tmp_path / (name + ".zip")``, members under
        ``top_folder/`` if given, and return the zip's path.
    **overrides
        Top-level keys of capture.json (``DELETE`` removes the key).
    """
    root = Path(tmp_path) / name
    root.mkdir(parents=True, exist_ok=True)
    bit_depth = overrides.get("bit_depth", 16)
    peak = float(
        2 ** (bit_depth if isinstance(bit_depth, int) and 8 <= bit_depth <= 16 else 16) - 1
    )
    dtype = np.uint8 if peak <= 255 else np.uint16

    dirs = light_ring(n_lights)
    stack = sphere_images(dirs, width, height, peak=peak, seed=seed)
    out = {
        f"ps_{k:02d}.png": np.clip(np.rint(img), 0, peak).astype(dtype)
        for k, img in enumerate(stack)
    }
    rng = np.random.default_rng(seed + 1)
    if with_dark:
        out["dark.png"] = np.clip(
            rng.normal(0.01 * peak, 0.002 * peak, (height, width)), 0, peak
        ).astype(dtype)
    if with_stereo:
        texture = rng.uniform(0.1 * peak, 0.9 * peak, (height, width))
        out["stereo_left.png"] = texture.astype(dtype)
        out["stereo_right.png"] = np.roll(texture, -3, axis=1).astype(dtype)
    out.update(files or {})

    cal = calibration_doc(width, height)
    doc = {
        "format": "plate-capture/1",
        "plate_id": "TEST-P01",
        "captured_at": "2026-11-20T10:31:00Z",
        "calibration": cal if inline_calibration else "calibration.json",
        "bit_depth": 16 if dtype == np.uint16 else 8,
        "photometric": {
            "lights": [{"direction": d.tolist(), "intensity": 1.0} for d in dirs],
            "images": [f"ps_{k:02d}.png" for k in range(n_lights)],
        },
        "working_distance_mm": 1000.0,
    }
    if with_dark:
        doc["photometric"]["dark"] = "dark.png"
    if with_stereo:
        doc["stereo"] = {"left": "stereo_left.png", "right": "stereo_right.png"}
    doc = _apply(doc, overrides)
    if mutate is not None:
        mutate(doc)

    omit = set(omit)
    if not inline_calibration and "calibration.json" not in omit:
        out.setdefault("calibration.json", json.dumps(cal).encode())
    for fname, content in out.items():
        if fname not in omit:
            write_image(root / fname, content)
    if "capture.json" not in omit and "capture.json" not in out:
        (root / "capture.json").write_text(json.dumps(doc, indent=1))

    if not as_zip:
        return root
    zpath = Path(tmp_path) / f"{name}.zip"
    zip_folder(root, zpath, top_folder=top_folder)
    return zpath


def zip_folder(root: Path, zpath: Path, *, top_folder: str | None = None) -> Path:
    """Pack the files of ``root`` into ``zpath`` (deflated), optionally under ``top_folder/``."""
    with zipfile.ZipFile(zpath, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for f in sorted(p for p in root.rglob("*") if p.is_file()):
            rel = f.relative_to(root).as_posix()
            zf.write(f, f"{top_folder}/{rel}" if top_folder else rel)
    return zpath


def _apply(doc: dict, overrides: dict) -> dict:
    doc = dict(doc)
    for key, value in overrides.items():
        if value is DELETE:
            doc.pop(key, None)
        else:
            doc[key] = value
    return doc


def before_segmentation(bundle: Path):
    """A (simulated) bundle as the inspection has it when it segments the plate: the capture, its
    preprocessing, the candidates (plate and lit surroundings) and the stereo depth matched over them."""
    from pipeline.io import load_capture
    from pipeline.preprocess import preprocess
    from pipeline.segmentation import candidate_mask
    from pipeline.surface import stereo

    cap = load_capture(bundle)
    pre = preprocess(cap)
    cand = candidate_mask(pre.brightness, seen=pre.seen)
    depth = stereo.stereo_depth(
        cap.stereo_left, cap.stereo_right, cap.rig, z_min_mm=1500.0, z_max_mm=6000.0, mask=cand
    ).depth_mm
    return cap, pre, cand, depth
