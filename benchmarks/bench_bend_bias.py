"""The radius's small negative bias: how noise in the normals bends the integrated plate.

The integration takes each pixel's log-depth gradient as a ratio of the normal's components
(``p = -(n . K^-1 e_u) / (n . ray)``, :mod:`pipeline.surface.integration`). Zero-mean noise in the
normal then biases the ratio (its denominator's variance, and the numerator's covariance with it:
an error in variables), by an amount that grows with the pixel's distance from the principal point
and with the noise's variance: the plate reads slightly more curved than it is. This prints it on the
simulated ideal cell (cylinder R5000, 1224x1024): the true normals with white noise of ``sigma`` per
component added (then renormalised), integrated and fused with the capture's own stereo depth as the
inspection does (its stereo weight, and a negligible one, where the normals alone set the bend), the
radius fitted by the registration; then the per-component error of the normals the inspection
estimates on the same captures, for the scale of the noise it actually meets.

    .venv/bin/python benchmarks/bench_bend_bias.py [--seeds 0 1 2 3]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import numpy as np

from pipeline.io import Capture, Target, load_capture, load_target
from pipeline.judge import registration
from pipeline.preprocess import plate_found, undistorted
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture
from pipeline.stages import InspectOptions, _stereo_depth, stereo_weight_on_grid
from pipeline.surface import reconstruct
from pipeline.surface.normals import NormalField, estimate_normals

SIGMAS = (0.0, 0.0025, 0.005, 0.01)
#: A stereo weight that leaves the plate's bend to the normals (the fusion still sets scale and tilt).
NEGLIGIBLE_WEIGHT = 1e-9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    args = parser.parse_args()
    errors: dict[tuple[float, str], list[float]] = {}
    estimated: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            bundle = simulate_capture(
                Path(tmp) / "capture",
                plate=PlateSpec(),
                capture=CaptureSpec(width=1224, height=1024),
                seed=seed,
            )
            cap, tgt = load_capture(bundle), load_target(bundle / "target.json")
            truth = np.load(bundle / "truth.npz")
            mask = truth["mask"].astype(bool) & np.isfinite(truth["depth_mm"])
            stereo, _, _ = _stereo_depth(cap, mask, InspectOptions())
            weight = stereo_weight_on_grid(
                InspectOptions().stereo_weight, cap.rig.left.K, float(np.median(stereo[mask]))
            )
            rng = np.random.default_rng(seed)
            for sigma in SIGMAS:
                normals = _noisy(truth["normals"], mask, sigma, rng)
                for label, w in (("stereo weight", weight), ("normals alone", NEGLIGIBLE_WEIGHT)):
                    errors.setdefault((sigma, label), []).append(
                        _radius_error_pct(normals, mask, stereo, w, cap, tgt)
                    )
            lit = undistorted(cap)
            field = estimate_normals(
                plate_found(lit).images, cap.light_dirs, mask, camera_matrix=cap.rig.left.K
            )
            ok = mask & field.mask
            estimated.append(float(np.std(field.normals[ok][:, :2] - truth["normals"][ok][:, :2])))
    print(f"\n## Radius error (%) of the true normals with noise, seeds {args.seeds}\n")
    print(
        "| noise sd per component | with the inspection's stereo weight | normals alone set the bend |"
    )
    print("|---|---|---|")
    for sigma in SIGMAS:
        cells = [_mean_sd(errors[(sigma, label)]) for label in ("stereo weight", "normals alone")]
        print(f"| {sigma:g} | {cells[0]} | {cells[1]} |")
    print(
        "\nThe inspection's own normals on these captures: per-component error sd "
        f"{min(estimated):.4f}-{max(estimated):.4f} (x and y, against the truth)."
    )


def _noisy(
    normals: np.ndarray, mask: np.ndarray, sigma: float, rng: np.random.Generator
) -> NormalField:
    n = normals.astype(np.float64) + sigma * rng.standard_normal(normals.shape)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n = n.astype(np.float32)
    n[~mask] = np.nan
    albedo = np.where(mask, 1.0, np.nan).astype(np.float32)
    return NormalField(n, albedo, mask, np.zeros_like(mask), 0)


def _radius_error_pct(
    field: NormalField,
    mask: np.ndarray,
    stereo: np.ndarray,
    weight: float,
    cap: Capture,
    tgt: Target,
) -> float:
    K = cap.rig.left.K
    depth, surface_mask, _, _, _ = reconstruct.integrate_and_fuse(
        field, K, prior_mm=stereo, working_distance_mm=None, stereo_weight=weight, tol=1e-6
    )
    h, w = mask.shape
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((h, w))], -1)
    points = rays * depth[..., None]
    points[~surface_mask] = np.nan
    pose = registration.register_to_target(points, surface_mask, tgt)
    assert tgt.radius_mm is not None and pose.fitted_radius_mm is not None
    return 100.0 * (float(pose.fitted_radius_mm) / tgt.radius_mm - 1.0)


def _mean_sd(values: list[float]) -> str:
    sd = statistics.stdev(values) if len(values) > 1 else 0.0
    return (
        f"{statistics.mean(values):+.4f} (sd {sd:.4f}; "
        + ", ".join(f"{v:+.4f}" for v in values)
        + ")"
    )


if __name__ == "__main__":
    main()
