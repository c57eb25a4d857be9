"""Camera models of the binocular head.

Frames follow OpenCV: x right, y down, z forward into the scene. The left
camera is the reference frame of everything; the stereo extrinsics follow
``cv2.stereoCalibrate``: ``X_right = R @ X_left + T`` (mm).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import cv2
import numba
import numpy as np
import numpy.typing as npt


def _as_matrix(name: str, value: npt.ArrayLike, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite values, got {arr.tolist()}")
    return arr


def check_camera_matrix(value: npt.ArrayLike, name: str = "K") -> np.ndarray:
    """A pinhole camera matrix checked: finite (3, 3) float64 ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``
    with fx, fy > 0 (the one check of K; ``name`` is the argument's name in the error)."""
    K = np.asarray(value, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"{name}: expected a finite (3, 3) matrix, got shape {K.shape}")
    if (
        K[0, 0] <= 0
        or K[1, 1] <= 0
        or K[2, 2] != 1.0
        or K[1, 0] != 0
        or K[2, 0] != 0
        or K[2, 1] != 0
    ):
        raise ValueError(
            f"{name}: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {K.tolist()}"
        )
    return K


@dataclass(frozen=True)
class CameraModel:
    """A calibrated pinhole camera with Brown-Conrady distortion.

    Parameters
    ----------
    K : (3, 3) float64
        Intrinsic matrix, pixels.
    dist : (5,) float64
        Distortion coefficients ``k1 k2 p1 p2 k3`` (OpenCV order).
    image_size : (int, int)
        ``(width, height)`` in pixels.
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        K = check_camera_matrix(self.K)
        dist = np.asarray(self.dist, dtype=np.float64).ravel()
        if dist.shape != (5,):
            raise ValueError(f"dist: expected 5 coefficients k1 k2 p1 p2 k3, got {dist.shape[0]}")
        dist = _as_matrix("dist", dist, (5,))
        w, h = (int(v) for v in self.image_size)
        if w <= 0 or h <= 0:
            raise ValueError(
                f"image_size: expected positive (width, height), got {self.image_size}"
            )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "image_size", (w, h))

    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]

    def resized(self, image_size: tuple[int, int]) -> CameraModel:
        """The same camera seen on its image resized to ``(width, height)`` px (as ``cv2.resize`` does).

        Pixel centres map as ``u' = sx (u + 0.5) - 0.5`` with ``sx = width' / width``
        (likewise v); the distortion of normalised coordinates is unchanged.
        """
        w, h = (int(v) for v in image_size)
        if w <= 0 or h <= 0:
            raise ValueError(f"image_size: expected positive (width, height), got {image_size}")
        sx, sy = w / self.width, h / self.height
        K = self.K.copy()
        K[0, :2] *= sx
        K[1, 1] *= sy
        K[0, 2] = sx * (K[0, 2] + 0.5) - 0.5
        K[1, 2] = sy * (K[1, 2] + 0.5) - 0.5
        return CameraModel(K=K, dist=self.dist, image_size=(w, h))

    def pixel_rays(self) -> np.ndarray:
        """Rays through the pixel centres of the *undistorted* image.

        Returns
        -------
        rays : (H, W, 3) float64
            ``(x, y, 1)`` with ``x = (u - cx) / fx`` etc. (left-camera frame,
            not normalised: a point at depth ``z`` mm is ``z * rays``).
        """
        return undistorted_rays(self.K, self.image_size)

    def undistort_image(
        self, image: np.ndarray, *, interpolation: int = cv2.INTER_LINEAR
    ) -> np.ndarray:
        """Resample a distorted image onto the undistorted grid with the same K.

        Parameters
        ----------
        image : (H, W) or (H, W, C) array, as the camera gives it.

        Returns
        -------
        (H, W) or (H, W, C) array of the same dtype, pixel ``(u, v)`` of which
        sees the ray ``K^-1 (u, v, 1)``.
        """
        map1, map2 = self.undistort_maps()
        return cv2.remap(
            image, map1, map2, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.remap`` maps from the undistorted grid (same K) to the raw image (read-only: the last few
        cameras' maps are kept, a cell inspects plate after plate with one calibration)."""
        return _undistort_maps(self.K.tobytes(), self.dist.tobytes(), self.image_size)

    def project(self, points_mm: np.ndarray) -> np.ndarray:
        """Project points of this camera's frame into its raw (distorted) image.

        Parameters
        ----------
        points_mm : (M, 3) float, camera frame, mm, z > 0.

        Returns
        -------
        (M, 2) float64 pixel coordinates ``(u, v)``.
        """
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 1, 3)
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(-1, 2)


@functools.lru_cache(maxsize=4)
def _undistort_maps(
    K: bytes, dist: bytes, image_size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`CameraModel.undistort_maps` of the camera whose ``K`` (3, 3) and ``dist`` (5,) float64 have
    these bytes."""
    camera = np.frombuffer(K).reshape(3, 3)
    maps: tuple[np.ndarray, np.ndarray] = cv2.initUndistortRectifyMap(
        camera, np.frombuffer(dist), np.eye(3), camera, image_size, cv2.CV_32FC1
    )
    for m in maps:
        m.setflags(write=False)
    return maps


def undistorted_rays(K: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Rays ``K^-1 (u, v, 1)`` for every pixel of a ``(width, height)`` grid.

    Returns
    -------
    (H, W, 3) float64, unit z component.
    """
    w, h = image_size
    K = np.asarray(K, dtype=np.float64)
    rays = np.empty((h, w, 3), dtype=np.float64)
    _fill_rays(float(K[0, 0]), float(K[0, 1]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2]), rays)
    return rays


@numba.njit(nogil=True, cache=True)
def _fill_rays(
    fx: float, skew: float, cx: float, fy: float, cy: float, rays: npt.NDArray[Any]
) -> None:  # pragma: no cover - compiled
    """rays[v, u] = ``((u - cx - skew y) / fx, y, 1)`` with ``y = (v - cy) / fy`` (K is upper
    triangular: solved from the bottom row up), in one pass; single-threaded (a worker computes
    them beside the preprocessing)."""
    h, w = rays.shape[0], rays.shape[1]
    for i in range(h):
        y = (np.float64(i) - cy) / fy
        for j in range(w):
            rays[i, j, 0] = (np.float64(j) - cx - skew * y) / fx
            rays[i, j, 1] = y
            rays[i, j, 2] = 1.0


def points_on_rays(depth_mm: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """The points ``depth_mm[..., None] * rays`` (H, W, 3) float64 (NaN where the depth is), in one
    compiled pass: the same values as the array expression, without its broadcast's slower loop.

    Parameters
    ----------
    depth_mm : (H, W) float64
        Depth along the optical axis.
    rays : (H, W, 3) float64
        :func:`undistorted_rays`.
    """
    points = np.empty(rays.shape)
    _scale_rays(
        np.ascontiguousarray(depth_mm, dtype=np.float64),
        np.ascontiguousarray(rays, dtype=np.float64),
        points,
    )
    return points


@numba.njit(nogil=True, cache=True)
def _scale_rays(
    depth: npt.NDArray[Any], rays: npt.NDArray[Any], out: npt.NDArray[Any]
) -> None:  # pragma: no cover - compiled
    """out = depth[..., None] * rays; single-threaded."""
    h, w = depth.shape
    for i in range(h):
        for j in range(w):
            d = depth[i, j]
            out[i, j, 0] = d * rays[i, j, 0]
            out[i, j, 1] = d * rays[i, j, 1]
            out[i, j, 2] = d * rays[i, j, 2]


@dataclass(frozen=True)
class StereoRig:
    """Two calibrated cameras; the left one is the reference frame.

    ``X_right = R @ X_left + T`` with ``T`` in mm (``cv2.stereoCalibrate``).
    """

    left: CameraModel
    right: CameraModel
    R: np.ndarray
    T: np.ndarray
    rms_px: float | None = None
    board: dict[str, Any] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        R = _as_matrix("R", self.R, (3, 3))
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
            raise ValueError("R: expected a proper rotation matrix (orthonormal, det +1)")
        T = _as_matrix("T", np.asarray(self.T, dtype=np.float64).ravel(), (3,))
        if self.left.image_size != self.right.image_size:
            raise ValueError(
                f"image_size: left {self.left.image_size} and right {self.right.image_size} differ"
            )
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "T", T)

    @property
    def image_size(self) -> tuple[int, int]:
        return self.left.image_size

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.T))
