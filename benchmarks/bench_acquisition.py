"""Acquisition time per image with Aravis' fake cameras and a TCP light controller on loopback.

The left camera is ``arv-fake-gv-camera-0.8 -i 127.0.0.1`` (GigE Vision over loopback), the right
one Aravis' in-process ``Fake_1``; the light controller is the tests' TCP server answering ``OK``.
Both with configured exposures (no pre-shots) and with auto-exposure.

Run: .venv/bin/python benchmarks/bench_acquisition.py [--width 1224 --height 1024 --lights 6 --repeat 3]
Prints, per case, the best of ``--repeat`` runs: the whole ``acquire`` (connecting, pre-shots,
frames, PNG writing) and the sequence alone (first light on to the stereo pair), per image.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from pipeline.acquisition import acquire
from tests.acquisition.devices import FakeGigECamera, LightServer
from tests.acquisition.helpers import tcp_lights, write_cell


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, default=1224)
    ap.add_argument("--height", type=int, default=1024)
    ap.add_argument("--lights", type=int, default=6)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    camera, server = FakeGigECamera(serial="BENCH"), LightServer()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            n_images = args.lights + 3
            print(
                f"{n_images} images ({args.lights} photometric, dark, stereo pair) of {args.width}x{args.height} "
                f"Mono16; left {camera.device_id} (fake GigE Vision), right Fake_1, TCP lights; best of {args.repeat}"
            )
            print(
                f"{'exposure':<16}{'total s':>9}{'per image ms':>14}{'sequence s':>12}{'per image ms':>14}{'pre-shots':>11}"
            )
            for case, exposure in (("configured 5 ms", {"exposure_us": 5000.0}), ("auto", {})):
                config = write_cell(
                    Path(tmp) / case,
                    size=(args.width, args.height),
                    n_lights=args.lights,
                    lights=tcp_lights(server),
                    left={"driver": "aravis", "device_id": camera.device_id, **exposure},
                    right={"driver": "aravis", "device_id": "Fake_1", **exposure},
                )
                records = []
                for run in range(args.repeat):
                    out = acquire(config, "BENCH", Path(tmp) / f"{case}-{run}")
                    records.append(json.loads((out / "capture.json").read_text())["acquisition"])
                total = min(r["total_s"] for r in records)
                sequence = min(r["sequence_s"] for r in records)
                print(
                    f"{case:<16}{total:>9.3f}{1000 * total / n_images:>14.1f}{sequence:>12.3f}"
                    f"{1000 * sequence / n_images:>14.1f}{records[0]['pre_shots']:>11}"
                )
    finally:
        camera.stop()
        server.close()


if __name__ == "__main__":
    main()
