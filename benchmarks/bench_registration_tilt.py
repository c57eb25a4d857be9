"""Where the target sits on a tilted plate: the registration's origin against the plate's true middle.

A cylinder R5000 (3000 x 3000 mm at 3 m, the whole plate in view, 5 mm pixels), its true points ray-cast
into the camera grid, rolled about its straight axis or tilted (``tests/pipeline/surfaces.plate_grid``).
Prints the registered origin's offset from the plate's middle, in the plate's own x (along the arc) and
y (along the axis), mm. Run it with ``PYTHONPATH=<an older checkout>`` to read that tree's.

    .venv/bin/python benchmarks/bench_registration_tilt.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1]))

from pipeline.io import Target
from pipeline.judge.registration import register_to_target
from tests.pipeline.surfaces import plate_grid

TILTS = (
    (3.0, -2.0, 0.0),
    (0.0, 15.0, 0.0),
    (0.0, 25.0, 0.0),
    (12.0, 0.0, 0.0),
    (20.0, 0.0, 0.0),
    (10.0, 10.0, 0.0),
)


def main() -> None:
    target = Target(shape="cylinder", radius_mm=5000.0, size_mm=(3000.0, 3000.0), tolerance_mm=2.0)
    print("\n| tilt about x, y, z (deg) | offset along the arc mm | along the axis mm |")
    print("|---|---|---|")
    for tilt in TILTS:
        pts, mask, _, R = plate_grid(
            lambda x, y: 5000.0 - np.sqrt(5000.0**2 - x * x), shape=(720, 720), tilt_deg=tilt
        )
        pose = register_to_target(pts, mask, target)
        offset = R.T @ (np.asarray(pose.T_cam_target)[:3, 3] - np.array([30.0, -20.0, 3000.0]))
        print(f"| {tilt[0]:g}, {tilt[1]:g}, {tilt[2]:g} | {offset[0]:+.2f} | {offset[1]:+.2f} |")


if __name__ == "__main__":
    main()
