"""Benchmark of pipeline.surface.integration: speed at the camera's sizes, accuracy on the analytic plate,
and the public datasets (BiNI's DiLiGenT depth maps, Queau's vase) next to their published figures.

Run from the project root:  .venv/bin/python benchmarks/bench_integration.py [--quick]

Wall time is the median of a few runs; CPU is the process time of the same runs, all threads (the
multigrid sweeps are single-threaded, the other kernels use both cores). The load average is
printed with each table: on a machine shared with other work, wall time varies.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import scipy.io

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.parallel import configure_process  # noqa: E402
from pipeline.surface.integration import integrate_gradient, integrate_normals  # noqa: E402
from tests.pipeline.surfaces import plate_camera, render_cylinder, sparse_least_squares  # noqa: E402
from tests.realdata import BINI, VASE, load_bini, made_after_median_scale  # noqa: E402

#: BiNI (k=2, perspective) MADE in mm, from the data's SOURCE.txt.
BINI_MADE_MM = {
    "bear": 0.334,
    "buddha": 1.098,
    "cat": 0.074,
    "cow": 0.058,
    "goblet": 9.018,
    "harvest": 1.838,
    "pot1": 0.635,
    "pot2": 0.220,
    "reading": 0.257,
}


def timed(fn, repeat):
    walls, cpus, out = [], [], None
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return out, float(np.median(walls)), float(np.median(cpus))


def rms(a):
    return float(np.sqrt(np.nanmean(np.square(a))))


def load():
    return "load avg {:.1f} {:.1f} {:.1f}".format(*os.getloadavg())


def speed_table(sizes, repeat):
    print(f"\n## Speed ({load()})")
    print(
        f"{'size':>10} {'mask':>8} {'fill':>5} {'mode':>9} {'wall s':>7} {'cpu s':>7} {'iter':>4} "
        f"{'residual':>9} {'rms mm':>9}"
    )
    rng = np.random.default_rng(0)
    for w, h, f in sizes:
        K = plate_camera(w, h, f)
        for mask_kind, plate_mm in (("full", (1e4, 1e4)), ("plate", (3000.0, 3000.0))):
            n, mask, depth = render_cylinder(K, (h, w), plate_mm=plate_mm)
            # stereo-like prior: 2 mm noise, 20 % of the plate unmatched (NaN)
            prior = depth + rng.normal(0.0, 2.0, depth.shape)
            prior[rng.random(depth.shape) < 0.2] = np.nan
            for mode, kw in (
                ("reference", {"reference_depth_mm": float(np.median(depth[mask]))}),
                ("prior", {"prior_depth_mm": prior}),
            ):
                integrate_normals(n, mask, K, **kw)  # warm-up (compilation is cached on disk)
                res, wall, cpu = timed(lambda: integrate_normals(n, mask, K, **kw), repeat)
                print(
                    f"{w:>5}x{h:<4} {mask_kind:>8} {mask.mean():5.2f} {mode:>9} {wall:7.3f} {cpu:7.3f} "
                    f"{res.iterations:4d} {res.residual:9.1e} {rms(res.depth_mm - depth):9.5f}"
                )


def accuracy_table():
    print(
        f"\n## Accuracy on the paper's plate: cylinder R 5 m, 3 x 3 m at 3 m, tilted (0.05, 0.08) rad, "
        f"1224x1024, fx 900 ({load()})"
    )
    K = plate_camera(1224, 1024, 900.0)
    n, mask, depth = render_cylinder(K, (1024, 1224))
    rng = np.random.default_rng(1)
    print(f"{'case':<52} {'rms mm':>9} {'max mm':>9} {'iter':>4}")

    def row(name, res):
        e = res.depth_mm - depth
        print(f"{name:<52} {rms(e):9.4f} {np.nanmax(np.abs(e)):9.4f} {res.iterations:4d}")

    ref = float(np.median(depth[mask]))
    row(
        "exact normals, reference = true median depth",
        integrate_normals(n, mask, K, reference_depth_mm=ref),
    )
    row(
        "exact normals, exact prior on every pixel",
        integrate_normals(n, mask, K, prior_depth_mm=depth),
    )
    sparse = np.where(rng.random(depth.shape) < 0.01, depth * 1.02, np.nan)
    res = integrate_normals(n, mask, K, prior_depth_mm=sparse)
    e = res.depth_mm / depth - 1.02
    print(
        f"{'exact normals, 1 % prior pixels scaled 1.02: rel err':<52} {rms(e):9.2e} {np.nanmax(abs(e)):9.2e} "
        f"{res.iterations:4d}"
    )
    for sigma in (1.0, 3.0):
        noisy_prior = depth + rng.normal(0.0, sigma, depth.shape)
        for wgt in (1e-3, 1e-2, 1e-1):
            row(
                f"exact normals, prior + N(0, {sigma:.0f} mm), weight {wgt:g}",
                integrate_normals(n, mask, K, prior_depth_mm=noisy_prior, prior_weight=wgt),
            )
    for sigma_n in (0.002, 0.005, 0.01):
        noisy = n + rng.normal(0.0, sigma_n, n.shape)
        noisy /= np.linalg.norm(noisy, axis=-1, keepdims=True)
        deg = np.degrees(np.arccos(np.clip(np.sum(noisy * n, -1), -1, 1)))[mask].mean()
        row(
            f"normals + noise ({deg:.2f} deg mean), reference",
            integrate_normals(noisy, mask, K, reference_depth_mm=ref),
        )
        noisy_prior = depth + rng.normal(0.0, 2.0, depth.shape)
        row(
            f"normals + noise ({deg:.2f} deg mean), prior 2 mm, w 1e-2",
            integrate_normals(noisy, mask, K, prior_depth_mm=noisy_prior),
        )


def exactness_table():
    print(
        f"\n## Same equations, direct sparse solve (scipy spsolve of the normal equations) ({load()})"
    )
    print(f"{'size':>10} {'ours s':>7} {'spsolve s':>9} {'max |dlog z|':>12}")
    rng = np.random.default_rng(2)
    for w, h, f in ((306, 256, 225.0), (612, 512, 450.0)):
        K = plate_camera(w, h, f)
        n, mask, depth = render_cylinder(K, (h, w))
        n = n + rng.normal(0.0, 0.005, n.shape)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        prior = np.where(
            rng.random(depth.shape) < 0.3, depth + rng.normal(0.0, 2.0, depth.shape), np.nan
        )
        res, wall, _ = timed(
            lambda: integrate_normals(n, mask, K, prior_depth_mm=prior, tol=1e-10), 3
        )
        ref, wall_ref, _ = timed(
            lambda: sparse_least_squares(n, mask, K, np.log(prior), np.float32(1e-2)), 1
        )
        diff = np.nanmax(np.abs(np.log(res.depth_mm) - ref))
        print(f"{w:>5}x{h:<4} {wall:7.3f} {wall_ref:9.3f} {diff:12.1e}")


def bini_table():
    if not BINI.is_dir():
        print(f"\n## BiNI DiLiGenT: skipped, {BINI} not found")
        return
    print(f"\n## DiLiGenT depth (BiNI's data and protocol: MADE after median scale, mm) ({load()})")
    print(f"{'object':<9} {'LS (ours)':>9} {'BiNI':>7} {'iter':>4} {'wall s':>7}")
    errs = []
    for obj, theirs in BINI_MADE_MM.items():
        n, mask, K, gt = load_bini(obj)
        res, wall, _ = timed(lambda: integrate_normals(n, mask, K, reference_depth_mm=1500.0), 1)
        err = made_after_median_scale(res.depth_mm, gt, mask)
        errs.append(err)
        print(f"{obj:<9} {err:9.3f} {theirs:7.3f} {res.iterations:4d} {wall:7.3f}")
    print(f"{'mean':<9} {np.mean(errs):9.3f} {np.mean(list(BINI_MADE_MM.values())):7.3f}")


def vase_table():
    if not VASE.is_file():
        print(f"\n## Vase: skipped, {VASE} not found")
        return
    m = scipy.io.loadmat(VASE)
    mask = m["mask"] > 0
    res, wall, _ = timed(lambda: integrate_gradient(m["q"], m["p"], mask), 3)
    truth = m["u"] - m["u"][mask].mean()
    err = float(np.sqrt(np.mean((res.height[mask] - truth[mask]) ** 2)))
    print(
        f"\n## Queau's vase, plain least squares: RMSE {err:.4f} (SOURCE.txt: 0.108 with spsolve), "
        f"{res.iterations} iterations, {wall:.3f} s"
    )


def main():
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the 2448x2048 size")
    args = ap.parse_args()
    sizes = [(612, 512, 450.0), (1224, 1024, 900.0)] + (
        [] if args.quick else [(2448, 2048, 1800.0)]
    )
    speed_table(sizes, repeat=3)
    accuracy_table()
    exactness_table()
    bini_table()
    vase_table()


if __name__ == "__main__":
    main()
