"""Light calibration against the simulator's truth at full size.

Run: ``.venv/bin/python benchmarks/bench_light_calibration.py [--sizes 1224x1024 2448x2048] [--seeds 101 102 103]``

For each size, cell and seed: a flat, rusty 3 x 3 m plate (tilted a few degrees, the tilt drawn
from the seed) under 12 LEDs (cos^1.5 beams, aimed at the plate's centre, 30 deg from the optical
axis seen from there), the capture giving only nominal directions bumped by 5 deg (a cell without a
light calibration); ``calibrate_lights`` on the loaded bundle. One row per run: load and calibrate
times (s), the fit's rms (fraction of the mean sample), each light's position error (mm), the
largest position standard error (mm), the largest error of the relative intensities (%) and of
mu. The acceptance: every light within 40 mm, relative intensities within 3 %.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.io import load_capture
from pipeline.lights.calibration import calibrate_lights
from pipeline.parallel import configure_process
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture

#: (plate distance from the camera, LED height above the plate), mm
CELLS = ((3000.0, 2800.0), (4000.0, 2800.0), (4000.0, 3800.0))
POSITION_TOL_MM = 40.0
INTENSITY_TOL = 0.03


def main() -> None:
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["1224x1024", "2448x2048"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[101, 102, 103])
    parser.add_argument("--keep", type=Path, default=None, help="write bundles under this folder")
    args = parser.parse_args()

    print(
        f"{'size':>10} {'plate m':>7} {'LEDs m':>6} {'seed':>5} {'load s':>6} {'fit s':>6} {'rms':>8} "
        f"{'max mm':>7} {'med mm':>7} {'std mm':>7} {'int %':>6} {'mu':>6}  position error per light, mm"
    )
    worst_pos, worst_int, failures = 0.0, 0.0, 0
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for size in args.sizes:
            w, h = (int(v) for v in size.lower().split("x"))
            for distance, height in CELLS:
                for seed in args.seeds:
                    tilt = tuple(np.random.default_rng(seed).uniform(-4.0, 4.0, 2))
                    out = root / f"{size}_{int(distance)}_{int(height)}_{seed}"
                    simulate_capture(
                        out,
                        plate=PlateSpec(
                            shape="plane", radius_mm=None, distance_mm=distance, tilt_deg=tilt
                        ),
                        capture=CaptureSpec(
                            near_field_mm=height,
                            light_elevation_deg=30.0,
                            led_mu=1.5,
                            manifest_lights="nominal",
                            light_error_deg=5.0,
                            working_distance_mm=distance,
                            width=w,
                            height=h,
                        ),
                        seed=seed,
                    )
                    t0 = time.perf_counter()
                    cap = load_capture(out)
                    load_s = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    cal = calibrate_lights([cap])
                    fit_s = time.perf_counter() - t0
                    with np.load(out / "truth.npz") as z:
                        pos, e_true, mu_true = (
                            z["light_positions_mm"],
                            z["light_intensity"],
                            z["light_mu"],
                        )
                    err = np.linalg.norm(cal.lights.positions_mm - pos, axis=1)
                    rel = (cal.lights.intensity / cal.lights.intensity.mean()) / (
                        e_true / e_true.mean()
                    ) - 1
                    int_err = float(np.abs(rel).max())
                    worst_pos, worst_int = max(worst_pos, float(err.max())), max(worst_int, int_err)
                    failures += int(err.max() > POSITION_TOL_MM or int_err > INTENSITY_TOL)
                    print(
                        f"{size:>10} {distance / 1000:7.1f} {height / 1000:6.1f} {seed:5d} {load_s:6.2f} {fit_s:6.2f} "
                        f"{cal.rms:8.5f} {err.max():7.1f} {np.median(err):7.1f} {cal.position_std_mm.max():7.1f} "
                        f"{100 * int_err:6.2f} {np.abs(cal.lights.mu - mu_true).max():6.3f}  "
                        + " ".join(f"{e:.0f}" for e in err),
                        flush=True,
                    )
    print(
        f"worst position error {worst_pos:.1f} mm (acceptance {POSITION_TOL_MM:.0f}), worst relative intensity "
        f"error {100 * worst_int:.2f} % (acceptance {100 * INTENSITY_TOL:.0f} %), {failures} run(s) outside"
    )


if __name__ == "__main__":
    main()
