"""Where the real datasets are (docs/data.md), and loaders of them for tests and benchmarks.

Each loader converts the dataset's conventions to the project's AT LOADING, so the
algorithms never see a foreign convention:

- frame: DiLiGenT and the UW sphere set use x right, y up, z towards the camera;
  ours (OpenCV) is x right, y down, z forward. A vector converts as
  ``(x, y, z) -> (x, -y, -z)`` (a rotation by pi about x, so angles are preserved);
- images: divided by each light's intensity and converted to grey exactly as the
  dataset's published baseline did (see each SOURCE.txt), so that the published
  least-squares figures can be reproduced.

The data are read-only and not part of the repository: :data:`DATA_ROOT` is the folder
``$PLATE_INSPECT_DATA`` names, else ``shared/data`` beside the checkout (docs/data.md); every test and
benchmark finds the data through it. Callers skip when :func:`data_available` is False.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import scipy.io

DATA_ROOT = Path(
    os.environ.get("PLATE_INSPECT_DATA")
    or Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
)

#: Grey conversion of the DiLiGenT baseline (MATLAB rgb2gray weights), for R, G, B.
RGB2GRAY = np.array([0.2989, 0.5870, 0.1140])

#: DiLiGenT / UW frame (x right, y up, z towards camera) -> OpenCV camera frame.
_FLIP_YZ = np.array([1.0, -1.0, -1.0])

#: ball16 frames were cropped at these rows / cols of the 512x612 originals (SOURCE.txt).
_BALL16_ROWS = slice(177, 351)
_BALL16_COLS = slice(221, 395)

CROP8_OBJECTS = ("ball", "cat", "pot1")

#: BiNI's DiLiGenT normal maps, masks, intrinsics and depth (one folder per object).
BINI = DATA_ROOT / "bini_diligent_normals" / "Fig7_diligent"
#: Queau's synthetic vase gradient field.
VASE = DATA_ROOT / "queau_vase" / "vase.mat"
#: The Middlebury 2006 Aloe stereo pair.
ALOE = DATA_ROOT / "middlebury_aloe"
#: OpenCV's 13 chessboard pairs.
OPENCV_BOARDS = DATA_ROOT / "opencv_stereo_calib"


@dataclass(frozen=True)
class PhotometricSet:
    """One real photometric-stereo dataset in the project's conventions.

    Attributes
    ----------
    name : str
    images : (N, H, W) float32
        Grey images divided by each light's intensity (the model I_k = rho max(0, n.l_k)).
    light_dirs : (N, 3) float64
        Unit vectors from the surface towards light k, OpenCV camera frame (l_z < 0).
    mask : (H, W) bool
        Object pixels that have a ground-truth normal.
    normals_gt : (H, W, 3) float64
        Ground-truth unit normals, OpenCV camera frame (n_z < 0); NaN outside ``mask``.
    saturated : (N, H, W) bool
        Samples where any raw colour channel is at the sensor's maximum count.
    """

    name: str
    images: np.ndarray
    light_dirs: np.ndarray
    mask: np.ndarray
    normals_gt: np.ndarray
    saturated: np.ndarray


def data_available(*parts: str) -> bool:
    """True if ``DATA_ROOT / parts`` exists (tests skip otherwise)."""
    return (DATA_ROOT.joinpath(*parts)).exists()


def diligent_to_opencv(v: np.ndarray) -> np.ndarray:
    """Convert (..., 3) vectors from the DiLiGenT frame (y up, z to camera) to OpenCV's."""
    return np.asarray(v, dtype=np.float64) * _FLIP_YZ


def angular_error_deg(normals: np.ndarray, normals_gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Angle in degrees between estimated and true unit normals at ``mask`` pixels.

    Parameters
    ----------
    normals, normals_gt : (H, W, 3) float
    mask : (H, W) bool

    Returns
    -------
    (M,) float64, M = mask.sum(); NaN where ``normals`` is NaN.
    """
    a = np.asarray(normals, dtype=np.float64)[mask]
    b = np.asarray(normals_gt, dtype=np.float64)[mask]
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    cos = np.clip(np.sum(a * b, axis=1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(f"{path}: cannot read image")
    return img[..., ::-1]  # BGR -> RGB


def _read_lights(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    dirs = np.loadtxt(folder / "light_directions.txt", dtype=np.float64)
    ints = np.loadtxt(folder / "light_intensities.txt", dtype=np.float64)
    return dirs, ints


def _diligent_images(files: list[Path], intensities: np.ndarray, max_count: float):
    """Benchmark protocol: img / max_count, / intensity (per channel), negatives to 0, rgb2gray, grey > 1 to 1."""
    first = _read_rgb(files[0])
    n = len(files)
    images = np.empty((n, *first.shape[:2]), dtype=np.float32)
    saturated = np.empty((n, *first.shape[:2]), dtype=bool)
    for k, f in enumerate(files):
        raw = first if k == 0 else _read_rgb(f)
        saturated[k] = np.any(raw >= max_count, axis=2)
        rgb = raw.astype(np.float64) / max_count / intensities[k]
        rgb = np.maximum(rgb, 0.0)
        images[k] = np.minimum(rgb @ RGB2GRAY, 1.0)
    return images, saturated


def load_diligent_ball16() -> PhotometricSet:
    """DiLiGenT ball, 96 16-bit frames (174x174 crop), prepared as the benchmark's L2 baseline.

    Protocol (SOURCE.txt, reproduces ``ballPNG_Normal_l2.mat`` to 0.001 deg): raw / 65535,
    each channel divided by that light's RGB intensity, negatives set to 0, grey =
    0.2989 R + 0.5870 G + 0.1140 B, grey values above 1 set to 1 (the benchmark does this;
    it is part of the protocol being reproduced), mask = mask.png == 255.
    """
    folder = DATA_ROOT / "diligent" / "ball16"
    dirs, ints = _read_lights(folder)
    names = (folder / "filenames.txt").read_text().split()
    files = [folder / "images_crop16" / name for name in names]
    images, saturated = _diligent_images(files, ints, 65535.0)
    mask_full = cv2.imread(str(folder / "mask.png"), cv2.IMREAD_GRAYSCALE) == 255
    mask = mask_full[_BALL16_ROWS, _BALL16_COLS]
    gt = scipy.io.loadmat(folder / "Normal_gt.mat")["Normal_gt"][_BALL16_ROWS, _BALL16_COLS]
    return PhotometricSet(
        name="ball16",
        images=images,
        light_dirs=diligent_to_opencv(dirs),
        mask=mask,
        normals_gt=np.where(mask[..., None], diligent_to_opencv(gt), np.nan),
        saturated=saturated,
    )


def load_diligent_ball16_l2() -> np.ndarray:
    """The benchmark's own least-squares result for ball (``Normal_L2``), (174, 174, 3), OpenCV frame."""
    folder = DATA_ROOT / "diligent" / "ball16"
    l2 = scipy.io.loadmat(folder / "ballPNG_Normal_l2.mat")["Normal_L2"][_BALL16_ROWS, _BALL16_COLS]
    return diligent_to_opencv(l2)


def load_diligent_crop8(obj: str) -> PhotometricSet:
    """DiLiGenT ``obj`` ('ball', 'cat', 'pot1') from the 8-bit object crops, 96 lights.

    Protocol: as :func:`load_diligent_ball16` (raw / 255, each channel divided by that
    light's RGB intensity, negatives to 0, rgb2gray, grey above 1 set to 1), mask =
    mask.png == 255. With the grey clip, plain least squares gives the published crop
    figures ball 4.41, cat 8.76, pot1 9.83 deg (without it ball gives 4.49).
    """
    if obj not in CROP8_OBJECTS:
        raise ValueError(f"obj: expected one of {CROP8_OBJECTS}, got {obj!r}")
    folder = DATA_ROOT / "diligent" / "crop8" / f"{obj}PNG"
    dirs, ints = _read_lights(folder)
    names = (folder / "filenames.txt").read_text().split()
    images, saturated = _diligent_images([folder / n for n in names], ints, 255.0)
    mask = cv2.imread(str(folder / "mask.png"), cv2.IMREAD_GRAYSCALE) == 255
    gt = scipy.io.loadmat(folder / "Normal_gt.mat")["Normal_gt"]
    return PhotometricSet(
        name=f"crop8/{obj}",
        images=images,
        light_dirs=diligent_to_opencv(dirs),
        mask=mask,
        normals_gt=np.where(mask[..., None], diligent_to_opencv(gt), np.nan),
        saturated=saturated,
    )


def read_tga(path: Path) -> np.ndarray:
    """Read an uncompressed 24/32-bit true-colour TGA as (H, W, 3) uint8 RGB, top row first."""
    data = Path(path).read_bytes()
    id_len, cmap_type, img_type = data[0], data[1], data[2]
    width = int.from_bytes(data[12:14], "little")
    height = int.from_bytes(data[14:16], "little")
    bpp, descriptor = data[16], data[17]
    if img_type != 2 or cmap_type != 0 or bpp not in (24, 32):
        raise ValueError(
            f"{path}: expected an uncompressed 24/32-bit true-colour TGA, got type {img_type}, {bpp} bpp"
        )
    start = 18 + id_len
    px = np.frombuffer(data, dtype=np.uint8, count=width * height * (bpp // 8), offset=start)
    img = px.reshape(height, width, bpp // 8)[..., 2::-1]  # BGR(A) -> RGB
    if not descriptor & 0x20:  # origin at the bottom: first stored row is the image's last
        img = img[::-1]
    if descriptor & 0x10:  # origin at the right
        img = img[:, ::-1]
    return np.ascontiguousarray(img)


def load_uw_gray_sphere() -> PhotometricSet:
    """The UW CSE 576 matte grey sphere under 12 lights, with analytic sphere normals.

    Images: RGB / 255 -> grey with :data:`RGB2GRAY` (light intensities are not given: taken
    equal). Ground truth: a sphere whose centre and radius are the mask's centroid and
    equivalent-area radius (SOURCE.txt: centre row 144.5, col 244.5, R 108.2 px); the
    normal at (u, v) is ((u - cu) / R, (v - cv) / R, -sqrt(1 - ...)) in the OpenCV frame,
    defined inside the mask where the radicand is positive.
    """
    folder = DATA_ROOT / "uw_spheres"
    lines = (folder / "lights.txt").read_text().split("\n")
    count = int(lines[0])
    dirs = np.array([[float(x) for x in line.split()] for line in lines[1 : 1 + count]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    files = [folder / "gray" / f"gray.{k}.tga" for k in range(count)]
    rgb = [read_tga(f) for f in files]
    images = np.stack([im.astype(np.float64) / 255.0 @ RGB2GRAY for im in rgb]).astype(np.float32)
    saturated = np.stack([np.any(im >= 255, axis=2) for im in rgb])
    mask = np.any(read_tga(folder / "gray" / "gray.mask.tga") > 127, axis=2)
    rows, cols = np.nonzero(mask)
    cv, cu = rows.mean(), cols.mean()
    radius = np.sqrt(mask.sum() / np.pi)
    vv, uu = np.mgrid[0 : mask.shape[0], 0 : mask.shape[1]]
    nx, ny = (uu - cu) / radius, (vv - cv) / radius
    rad = 1.0 - nx**2 - ny**2
    inside = mask & (rad > 0)
    gt = np.stack([nx, ny, -np.sqrt(np.where(inside, rad, 0.0))], axis=-1)
    return PhotometricSet(
        name="uw_gray_sphere",
        images=images,
        light_dirs=diligent_to_opencv(dirs),
        mask=inside,
        normals_gt=np.where(inside[..., None], gt, np.nan),
        saturated=saturated,
    )


def uw_sphere_disc(data: PhotometricSet, fraction: float) -> np.ndarray:
    """Mask of the UW sphere pixels within ``fraction`` of the radius of the centre: (H, W) bool."""
    n = data.normals_gt
    r2 = n[..., 0] ** 2 + n[..., 1] ** 2
    return data.mask & (r2 <= fraction**2)


def load_bini(obj: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """BiNI's DiLiGenT ``obj``: normals (H, W, 3) in our frame (BGR->RGB, n = c / 65535 * 2 - 1 in DiLiGenT
    axes, converted to OpenCV's), mask (H, W) bool, K (3, 3) and the true depth (H, W) mm."""
    root = BINI / obj
    rgb = cv2.cvtColor(
        cv2.imread(str(root / "normal_map.png"), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB
    )
    n = (rgb.astype(np.float64) / 65535.0 * 2.0 - 1.0) * np.array([1.0, -1.0, -1.0])
    mask = cv2.imread(str(root / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    K = np.loadtxt(root / "K.txt")
    depth = np.load(root / "depth_gt.npz")["depth_gt"].astype(np.float64)
    return n, mask, K, depth


def made_after_median_scale(est: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """BiNI's protocol (evaluation_diligent.py): scale = median(gt / est); mean |scale est - gt|, mm."""
    scale = np.nanmedian(gt[mask] / est[mask])
    return float(np.nanmean(np.abs(scale * est[mask] - gt[mask])))
