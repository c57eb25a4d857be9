"""Screenshots of the dashboard for docs/screenshots/ (README): every page at 1920x1080 and 1366x768.

    .venv/bin/python scripts/screenshots.py [--out docs/screenshots]

Starts the demo service (web process and worker, a fresh data dir) on a free port, inspects three
simulated plates through the real pipeline (one that passes, one with a dent that fails, one rolled
in two passes for its history), then photographs with Debian's Chromium (Playwright) the Cell page,
both results (and the failed one's 3D view), the plate history, the comparison of its two passes,
the Calibration page, and renders the first page of the failed
plate's PDF report (pdftoppm). Needs ``scripts/setup.sh --with-browser``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "screenshots-token"
SIZES = ((1920, 1080), (1366, 768))
MACHINE = {
    "kind": "three-roll-pyramid",
    "bottom_roll_spacing_mm": 1400,
    "bottom_roll_diameter_mm": 420,
    "top_roll_diameter_mm": 500,
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _api(base: str, method: str, path: str, body: dict | None = None) -> dict:
    request = urllib.request.Request(
        f"{base}{path}",
        data=None if body is None else json.dumps(body).encode(),
        method=method,
        headers={"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"},
    )
    with urllib.request.urlopen(request, timeout=60) as response:
        return json.loads(response.read())


def _inspect(base: str, plate_id: str, body: dict) -> int:
    """A simulated inspection, waited for; its id."""
    job = _api(base, "POST", f"/api/v1/plates/{plate_id}/inspections/simulated", body)
    deadline = time.monotonic() + 300
    while (doc := _api(base, "GET", f"/api/v1/inspections/{job['id']}"))["status"] not in (
        "done",
        "error",
    ):
        if time.monotonic() > deadline:
            raise RuntimeError(f"inspection {job['id']} did not finish")
        time.sleep(0.5)
    if doc["status"] != "done":
        raise RuntimeError(f"inspection {job['id']}: {doc['error']}")
    return int(job["id"])


def _seed(base: str) -> dict[str, int | str]:
    """The plates the screenshots show: a pass, a dented fail, a plate rolled in two passes."""
    size = {"n_lights": 12, "width": 612, "height": 512}
    dent = {"x_mm": -500.0, "y_mm": 350.0, "radius_mm": 180.0, "depth_mm": -7.0}
    ids: dict[str, int | str] = {
        "pass": _inspect(base, "HULL-P101", {**size, "seed": 3}),
        "fail": _inspect(base, "HULL-P102", {**size, "dents": [dent], "seed": 4}),
    }
    _api(base, "PUT", "/api/v1/machines/R3-01", MACHINE)
    target = {
        "format": "plate-target/1",
        "shape": {"type": "cylinder", "radius_mm": 5000.0},
        "size_mm": [3000.0, 3000.0],
        "tolerance_mm": 2.0,
        "material": {"grade": "AH36", "thickness_mm": 20, "yield_mpa": 355},
    }
    _api(base, "PUT", "/api/v1/plates/HULL-P103/target", target)
    for setting, radius in ((88.0, 6400.0), (96.5, 5150.0)):
        process = {
            "method": "roll-bending",
            "machine_id": "R3-01",
            "top_roll_displacement_mm": setting,
        }
        _inspect(base, "HULL-P103", {**size, "radius_mm": radius, "process": process})
    ids["history"] = "HULL-P103"
    return ids


def _photograph(base: str, ids: dict[str, int | str], out: Path) -> None:
    from playwright.sync_api import sync_playwright

    pages = {
        "cell": "/cell",
        "result-pass": f"/inspections/{ids['pass']}",
        "result-fail": f"/inspections/{ids['fail']}",
        "history": f"/plates/{ids['history']}",
        "compare": f"/plates/{ids['history']}/compare",
        "calibration": "/calibration",
    }
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox"])
        for w, h in SIZES:
            page = browser.new_page(viewport={"width": w, "height": h})
            for name, path in pages.items():
                page.goto(f"{base}{path}")
                page.wait_for_load_state("networkidle")
                time.sleep(3.0 if name.startswith("result") else 0.5)  # the 3D view draws
                page.screenshot(path=out / f"{name}-{w}x{h}.png")
                if name == "result-fail":  # the 3D view, below the map
                    view = page.locator(".view3d")
                    view.scroll_into_view_if_needed()
                    time.sleep(3.0)
                    view.screenshot(path=out / f"view3d-{w}x{h}.png")
            page.close()
        browser.close()


def _report_page(base: str, inspection_id: int | str, out: Path) -> None:
    with urllib.request.urlopen(f"{base}/api/v1/inspections/{inspection_id}/report.pdf") as r:
        pdf = r.read()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "report.pdf"
        path.write_bytes(pdf)
        subprocess.run(
            [
                "pdftoppm",
                "-r",
                "110",
                "-png",
                "-singlefile",
                "-f",
                "1",
                "-l",
                "1",
                str(path),
                str(out / "report-page1"),
            ],
            check=True,
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshots")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as data:
        port = _free_port()
        env = {
            **os.environ,
            "PLATE_INSPECT_DATA_DIR": data,
            "PLATE_INSPECT_DEMO": "1",
            "PLATE_INSPECT_API_TOKEN": TOKEN,
            "PYTHONPATH": str(ROOT),
        }
        web = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "uvicorn",
                "app.main:create_app",
                "--factory",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
            ],
            env=env,
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        worker = subprocess.Popen(
            [sys.executable, "-m", "app.worker"],
            env=env,
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        base = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 120
            while True:
                try:
                    urllib.request.urlopen(f"{base}/healthz", timeout=1)
                    break
                except OSError:
                    if time.monotonic() > deadline:
                        raise RuntimeError("the demo service did not start") from None
                    time.sleep(0.5)
            ids = _seed(base)
            _photograph(base, ids, args.out)
            _report_page(base, ids["fail"], args.out)
        finally:
            for proc in (worker, web):
                proc.terminate()
                proc.wait(20)
    print("\n".join(sorted(str(p) for p in args.out.glob("*.png"))))


if __name__ == "__main__":
    main()
