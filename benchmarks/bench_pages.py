"""What a person waits for at the screen: the result page and report.pdf of a dented plate.

Run from the project root:  .venv/bin/python benchmarks/bench_pages.py [--width 1224 --height 1024]
                            [--lights 12] [--repeat 3] [--keep DIR]

A fresh SQLite data directory, a plate target with drawing, hull and block and a machine, one
simulated dented inspection at the given size run by the job code (``app.jobs.execute_inspection``),
then ``--repeat`` requests of each page through the app (in process, no network). Prints a table:
each request's seconds and the median, against issue 26's budgets (result page 0.5 s, report.pdf
2 s, on a 2-core machine). The service refuses a simulated capture over 2 Mpx unless
``PLATE_INSPECT_MAX_SIMULATED_PIXELS`` is raised: at 2448x2048 run it with
``PLATE_INSPECT_MAX_SIMULATED_PIXELS=6000000``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastapi.testclient import TestClient

from app.jobs import execute_inspection
from app.main import create_app
from app.settings import Settings

TOKEN = "bench-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
BUDGETS_S = {"result page": 0.5, "report.pdf": 2.0}
TARGET = {
    "format": "plate-target/1",
    "shape": {"type": "cylinder", "radius_mm": 5000.0},
    "size_mm": [3000.0, 3000.0],
    "tolerance_mm": 2.0,
    "drawing": {"number": "DWG-H77-B21-0042", "revision": "C"},
    "hull": "H77",
    "block": "B21",
}


def inspected(client: TestClient, settings: Settings, sim: dict) -> int:
    """A dented plate's simulated inspection, run to the end by the job code; its id."""
    client.put("/api/v1/plates/H77-P1/target", json=TARGET, headers=AUTH).raise_for_status()
    body = {
        **sim,
        "radius_mm": 5000.0,
        "dents": [{"x_mm": 400.0, "y_mm": -200.0, "radius_mm": 200.0, "depth_mm": -8.0}],
    }
    r = client.post("/api/v1/plates/H77-P1/inspections/simulated", json=body, headers=AUTH)
    r.raise_for_status()
    inspection_id = r.json()["id"]
    state = client.app.state
    t0 = time.perf_counter()
    execute_inspection(
        inspection_id,
        settings=settings,
        session_factory=state.session_factory,
        storage=state.storage,
    )
    print(f"inspection {inspection_id}: job {time.perf_counter() - t0:.1f} s")
    return inspection_id


def timed(client: TestClient, path: str, repeat: int) -> list[float]:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        r = client.get(path, headers=AUTH)
        times.append(time.perf_counter() - t0)
        r.raise_for_status()
    return times


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, default=1224)
    ap.add_argument("--height", type=int, default=1024)
    ap.add_argument("--lights", type=int, default=12)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--keep", type=Path, default=None, help="data directory to keep")
    args = ap.parse_args()
    sim = {"width": args.width, "height": args.height, "n_lights": args.lights}
    with tempfile.TemporaryDirectory() as tmp:
        data = args.keep or Path(tmp)
        settings = Settings(data_dir=data, api_token=TOKEN)
        with TestClient(create_app(settings)) as client:
            job = inspected(client, settings, sim)
            pages = {
                "result page": f"/inspections/{job}",
                "report.pdf": f"/api/v1/inspections/{job}/report.pdf",
            }
            print(f"{'page':<12} {'requests, s':<24} {'median':>7} {'budget':>7}")
            for name, path in pages.items():
                times = timed(client, path, args.repeat)
                runs = " ".join(f"{t:.3f}" for t in times)
                median = statistics.median(times)
                print(f"{name:<12} {runs:<24} {median:7.3f} {BUDGETS_S[name]:7.1f}")


if __name__ == "__main__":
    main()
