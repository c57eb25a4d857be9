"""Where a plate fails: each defect's position in the target's frame and its depth, against the dent
the simulator rendered (the frame of target.json is the plate's own: dents are placed in it)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.run import inspect
from pipeline.simulate import CaptureSpec, Dent, PlateSpec, simulate_capture


@pytest.mark.parametrize(
    ("shape", "size_mm", "dent"),
    [
        (
            "cylinder",
            (3000.0, 2000.0),
            Dent(x_mm=-600.0, y_mm=300.0, radius_mm=150.0, depth_mm=-6.0),
        ),
        (
            "sphere",
            (3000.0, 3000.0),
            Dent(x_mm=-500.0, y_mm=-300.0, radius_mm=150.0, depth_mm=-5.0),
        ),
        ("plane", (2500.0, 2000.0), Dent(x_mm=700.0, y_mm=450.0, radius_mm=180.0, depth_mm=5.0)),
    ],
)
def test_a_dent_is_found_where_it_is_with_its_depth(tmp_path, shape, size_mm, dent):
    plate = PlateSpec(
        shape=shape, radius_mm=8000.0, size_mm=size_mm, dents=(dent,), tilt_deg=(2.0, -1.0)
    )
    bundle = simulate_capture(
        tmp_path / "bundle", plate=plate, capture=CaptureSpec(width=612, height=512), seed=21
    )
    result = inspect(bundle, bundle / "target.json", out_dir=tmp_path / "out")
    details = json.loads((tmp_path / "out" / "details.json").read_text())
    assert result.document["verdict"] == "fail"
    assert len(details["defects"]) == 1, details["defects"]
    found = details["defects"][0]
    # depth_mm > 0 presses the plate away from the cameras: a negative deviation
    assert found["peak_deviation_mm"] == pytest.approx(-dent.depth_mm, abs=1.0)
    assert np.sign(found["mean_deviation_mm"]) == np.sign(-dent.depth_mm)
    assert abs(found["mean_deviation_mm"]) < abs(found["peak_deviation_mm"])
    assert np.hypot(found["centroid_mm"][0] - dent.x_mm, found["centroid_mm"][1] - dent.y_mm) < 20.0
