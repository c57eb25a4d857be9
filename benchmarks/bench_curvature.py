"""Timing and accuracy of the curvature and deviation stages at camera sizes.

Run from the project root:  .venv/bin/python benchmarks/bench_curvature.py [--sizes 1224x1024,2448x2048] [--repeat 3]

Plates: ray-cast analytic surfaces (tests/pipeline/surfaces.plate_grid), 3000 x 3000 mm at 3000 mm,
tilted, 0.2 mm noise along the rays. Times are the best of ``--repeat`` runs (the machine is shared).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.io import Target
from pipeline.judge.curvature import principal_curvatures
from pipeline.judge.deviation import deviation_map
from pipeline.judge.registration import fitted_target_radius, register_to_target
from pipeline.judge.verdict import judge
from pipeline.parallel import configure_process
from tests.pipeline.surfaces import cylinder, dented, plate_grid, saddle, sphere


def best_time(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def mesh_target(height, half=1650.0, n=67):
    g = np.linspace(-half, half, n)
    gx, gy = np.meshgrid(g, g)
    V = np.stack([gx.ravel(), gy.ravel(), height(gx, gy).ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    return Target("mesh", None, (3000.0, 3000.0), 2.0, mesh_vertices_mm=V, mesh_faces=F)


def main():
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="1224x1024,2448x2048")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cases = [
        (
            "cylinder R5000 convex",
            cylinder(5000.0),
            Target("cylinder", 5000.0, (3000.0, 3000.0), 2.0),
            5000.0,
        ),
        (
            "cylinder R20000 concave",
            cylinder(20000.0, -1),
            Target("cylinder", 20000.0, (3000.0, 3000.0), 2.0),
            20000.0,
        ),
        (
            "cyl R5000 + 6 mm dent",
            dented(cylinder(5000.0)),
            Target("cylinder", 5000.0, (3000.0, 3000.0), 2.0),
            5000.0,
        ),
        (
            "sphere R8000 convex",
            sphere(8000.0),
            Target("sphere", 8000.0, (3000.0, 3000.0), 2.0),
            8000.0,
        ),
        ("plane", lambda x, y: 0 * x, Target("plane", None, (3000.0, 3000.0), 2.0), None),
        (
            "saddle mesh 4000/6000",
            saddle(4000.0, 6000.0),
            mesh_target(saddle(4000.0, 6000.0)),
            None,
        ),
    ]
    print(
        f"{'grid':>10} {'plate':<24} {'pixels':>8} {'principal':>9} {'radius':>7} {'register':>8} {'deviat.':>7} "
        f"{'judge':>6} | {'radius err %':>12} {'r1, r2 (mm)':>20} {'dev rms':>7} {'verdict':>7}"
    )
    for size in args.sizes.split(","):
        W, H = (int(v) for v in size.split("x"))
        for name, height, tgt, R_true in cases:
            rng = np.random.default_rng(1)
            pts, m, _, _ = plate_grid(height, shape=(H, W), noise_mm=0.2, rng=rng)
            area = 3000.0 * 3000.0 / m.sum()
            t_pc, pc = best_time(lambda: principal_curvatures(pts, m), args.repeat)
            t_r, radius = best_time(lambda: fitted_target_radius(pts, m, tgt), args.repeat)
            t_reg, reg = best_time(lambda: register_to_target(pts, m, tgt), args.repeat)
            t_dev, dev = best_time(lambda: deviation_map(pts, m, tgt, reg), args.repeat)
            t_j, j = best_time(
                lambda: judge(dev, m, tgt.tolerance_mm, pixel_area_mm2=area), args.repeat
            )
            err = f"{100 * (radius - R_true) / R_true:+.4f}" if radius is not None else "-"
            radii = ", ".join("-" if r is None else f"{r:.0f}" for r in pc.principal_radii_mm)
            print(
                f"{size:>10} {name:<24} {int(m.sum()):>8} {t_pc:>9.3f} {t_r:>7.3f} {t_reg:>8.3f} {t_dev:>7.3f} "
                f"{t_j:>6.3f} | {err:>12} {radii:>20} {j.rms_mm:>7.3f} {j.verdict:>7}"
            )


if __name__ == "__main__":
    main()
