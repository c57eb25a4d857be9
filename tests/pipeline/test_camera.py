import cv2
import numpy as np
import pytest

from pipeline.camera import CameraModel, StereoRig


def make_camera(size=(320, 256)):
    K = np.array([[250.0, 0, 161.3], [0, 251.0, 127.9], [0, 0, 1]])
    return CameraModel(K=K, dist=np.array([-0.08, 0.05, 1e-4, -2e-4, 0.0]), image_size=size)


def test_rays_reproject_through_the_distorted_model():
    cam = make_camera()
    rays = cam.pixel_rays()
    assert rays.shape == (256, 320, 3)
    # a point on the ray of undistorted pixel (u, v) projects (with distortion) to where the undistortion map samples it
    map1, map2 = cam.undistort_maps()
    pts = rays[::37, ::41].reshape(-1, 3) * 3000.0
    uv = cam.project(pts)
    np.testing.assert_allclose(
        uv[:, 0], map1[::37, ::41].ravel(), atol=0.02
    )  # remap maps agree to ~1/50 px
    np.testing.assert_allclose(uv[:, 1], map2[::37, ::41].ravel(), atol=0.02)


def test_undistort_image_keeps_dtype_and_shape():
    cam = make_camera()
    img = np.random.default_rng(0).integers(0, 65535, (256, 320), dtype=np.uint16)
    out = cam.undistort_image(img)
    assert out.shape == img.shape and out.dtype == img.dtype


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"K": np.eye(2)}, r"K: expected a finite \(3, 3\) matrix, got shape \(2, 2\)"),
        ({"K": np.array([[0.0, 0, 1], [0, 1, 1], [0, 0, 1]])}, "fx, fy > 0"),
        ({"dist": np.zeros(4)}, "dist: expected 5 coefficients"),
        ({"image_size": (0, 10)}, "image_size: expected positive"),
        ({"dist": np.array([np.nan, 0, 0, 0, 0])}, "dist: expected finite"),
    ],
)
def test_camera_rejects_bad_values(kwargs, match):
    base = dict(
        K=np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]]),
        dist=np.zeros(5),
        image_size=(100, 80),
    )
    with pytest.raises(ValueError, match=match):
        CameraModel(**(base | kwargs))


def test_rig_checks_rotation_and_sizes():
    cam = make_camera()
    R, _ = cv2.Rodrigues(np.array([0.0, -0.1, 0.0]))
    rig = StereoRig(left=cam, right=cam, R=R, T=[-800.0, 0.0, 0.0])
    assert rig.baseline_mm == pytest.approx(800.0)
    with pytest.raises(ValueError, match="R: expected a proper rotation"):
        StereoRig(left=cam, right=cam, R=2 * np.eye(3), T=[1.0, 0, 0])
    with pytest.raises(ValueError, match="image_size: left"):
        StereoRig(left=cam, right=make_camera((640, 480)), R=np.eye(3), T=[1.0, 0, 0])


def test_rays_are_the_inverse_intrinsics_with_skew():
    from pipeline.camera import undistorted_rays

    K = np.array([[900.0, 2.5, 611.7], [0, 905.0, 512.2], [0, 0, 1]])
    rays = undistorted_rays(K, (40, 30))
    v, u = np.mgrid[0:30, 0:40]
    expected = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    np.testing.assert_allclose(rays, expected, atol=1e-12)


def test_scaled_camera_sees_the_same_rays_at_half_size():
    cam = make_camera((320, 256))
    half = cam.resized((160, 128))
    assert half.image_size == (160, 128)
    # the centre of half-size pixel (u', v') is full-size (2u' + 0.5, 2v' + 0.5): same ray
    full_rays = cam.pixel_rays()
    half_rays = half.pixel_rays()
    u, v = 37, 51
    full_ray = np.linalg.inv(cam.K) @ np.array([2 * u + 0.5, 2 * v + 0.5, 1.0])
    np.testing.assert_allclose(half_rays[v, u], full_ray, atol=1e-12)
    assert full_rays.shape == (256, 320, 3)
