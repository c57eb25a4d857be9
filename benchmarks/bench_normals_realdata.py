"""Photometric normals: accuracy on real benchmark data and speed at the camera's full size.

Run from the project root:

    .venv/bin/python benchmarks/bench_normals_realdata.py [--no-speed] [--repeat 3]

Prints (1) mean angular error of ``estimate_normals`` (lstsq and robust) on DiLiGenT
ball16 / crop8 ball, cat, pot1 and the UW grey sphere next to the published figures
(each dataset's SOURCE.txt under ``tests.realdata.DATA_ROOT``, docs/data.md), and (2) the time of each method at 2448x2048 with
12 lights on a synthetic curved plate (best of ``--repeat`` runs; numba compiled first).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the project root, for tests.realdata

from pipeline.parallel import configure_process
from pipeline.surface.normals import estimate_normals
from tests import realdata as rd


def accuracy_table() -> None:
    rows = [
        ("DiLiGenT ball16 (16-bit)", rd.load_diligent_ball16, 4.10, None),
        ("DiLiGenT crop8 ball", lambda: rd.load_diligent_crop8("ball"), 4.41, None),
        ("DiLiGenT crop8 cat", lambda: rd.load_diligent_crop8("cat"), 8.76, None),
        ("DiLiGenT crop8 pot1", lambda: rd.load_diligent_crop8("pot1"), 9.83, None),
        ("UW grey sphere, 0.9 R", rd.load_uw_gray_sphere, 4.7, 0.9),
    ]
    warm = rd.load_diligent_crop8("ball")  # compile / load the numba kernels outside the timings
    for method in ("lstsq", "robust"):
        estimate_normals(
            warm.images[:, :40, :40], warm.light_dirs, np.ones((40, 40), bool), method=method
        )
    print("Mean angular error, deg (published = plain least squares, see SOURCE.txt)")
    print(
        f"{'dataset':<26} {'N':>3} {'pixels':>7} {'published':>9} {'lstsq':>7} {'robust':>7} {'gain':>6} "
        f"{'filled':>6} {'t_lstsq':>8} {'t_robust':>8}"
    )
    for name, load, published, disc in rows:
        data = load()
        region = data.mask if disc is None else rd.uw_sphere_disc(data, disc)
        out = {}
        for method in ("lstsq", "robust"):
            t0 = time.perf_counter()
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                field = estimate_normals(data.images, data.light_dirs, data.mask, method=method)
            dt = time.perf_counter() - t0
            err = rd.angular_error_deg(field.normals, data.normals_gt, region)
            out[method] = (np.nanmean(err), dt, field.n_filled, len(caught))
        gain = 100.0 * (1.0 - out["robust"][0] / out["lstsq"][0])
        print(
            f"{name:<26} {data.images.shape[0]:>3} {int(region.sum()):>7} {published:>9.2f} "
            f"{out['lstsq'][0]:>7.3f} {out['robust'][0]:>7.3f} {gain:>5.1f}% "
            f"{out['robust'][2]:>6d} {out['lstsq'][1]:>7.3f}s {out['robust'][1]:>7.3f}s"
        )


def synthetic_plate(
    h: int, w: int, n_lights: int, rng
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A curved plate filling the view: (N, H, W) float32 images (Lambertian + a small specular
    lobe + noise, clipped at 1), (N, 3) lights, (H, W) mask, (N, H, W) valid (not clipped)."""
    phi = np.linspace(0, 2 * np.pi, n_lights, endpoint=False)
    polar = np.radians(30.0)
    lights = np.stack(
        [
            np.sin(polar) * np.cos(phi),
            np.sin(polar) * np.sin(phi),
            -np.full(n_lights, np.cos(polar)),
        ],
        1,
    )
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    p = 0.3 * (u - w / 2) / w
    q = 0.1 * np.sin(2 * np.pi * v / h, dtype=np.float32)
    n = np.stack([p, q, -np.ones_like(p)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    images = np.empty((n_lights, h, w), dtype=np.float32)
    view = np.array([0.0, 0.0, -1.0])
    for k, light in enumerate(lights.astype(np.float32)):
        shade = n @ light
        half = (light + view) / np.linalg.norm(light + view)
        spec = np.maximum(n @ half.astype(np.float32), 0) ** 40
        images[k] = (
            0.7 * np.maximum(shade, 0)
            + 0.6 * spec
            + rng.normal(0, 0.004, (h, w)).astype(np.float32)
        )
    valid = images < 1.0
    np.minimum(images, 1.0, out=images)
    mask = np.zeros((h, w), dtype=bool)
    mask[h // 20 : -h // 20, w // 20 : -w // 20] = True
    return images, lights, mask, valid


def speed_table(repeat: int) -> None:
    h, w, n = 2048, 2448, 12
    rng = np.random.default_rng(0)
    images, lights, mask, valid = synthetic_plate(h, w, n, rng)
    estimate_normals(
        images[:, :64, :64], lights, mask[:64, :64] | True, method="robust"
    )  # compile / load cache
    print(
        f"\nSpeed at {w}x{h}, {n} lights, mask {mask.mean():.0%} of the frame, "
        f"{(~valid).mean():.2%} samples invalid (best of {repeat})"
    )
    print(
        "wall = elapsed time (the machine is shared: see the load); cpu = process CPU time, all threads"
    )
    print(f"{'method':<12} {'valid':<6} {'wall':>7} {'cpu':>7} {'filled':>7}")
    view = np.array([0.0, 0.0, -1.0])
    for method in ("lstsq", "robust", "robust+view"):
        for use_valid in (False, True):
            walls, cpus = [], []
            kw = (
                dict(method="robust", view_dirs=view)
                if method == "robust+view"
                else dict(method=method)
            )
            for _ in range(repeat):
                t0, c0 = time.perf_counter(), time.process_time()
                field = estimate_normals(
                    images, lights, mask, valid=valid if use_valid else None, **kw
                )
                walls.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            print(
                f"{method:<12} {use_valid!s:<6} {min(walls):>6.3f}s {min(cpus):>6.3f}s {field.n_filled:>7d}"
            )
    print(
        f"load average while measuring: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores, "
        f"numba threads: {numba.get_num_threads()}"
    )


def main() -> None:
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--no-speed", action="store_true", help="skip the full-size timing")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    if rd.data_available("diligent") and rd.data_available("uw_spheres"):
        accuracy_table()
    else:
        print(f"real data not found under {rd.DATA_ROOT}: accuracy table skipped")
    if not args.no_speed:
        speed_table(args.repeat)


if __name__ == "__main__":
    main()
