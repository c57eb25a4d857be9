"""Helpers of the service tests (constants, the consumer process, bundles and targets, waiting for
a job); the fixtures are in conftest.py.
"""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np

from app.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
FAKE_INSPECT = "tests.api.fake_pipeline:inspect"


def child_env(settings: Settings, **extra: str) -> dict[str, str]:
    """The environment of a child process of the service run with ``settings``: the tree's root on
    its import path, since the settings may name the test double of the pipeline
    (``tests.api.fake_pipeline``), which a console script (``plate-inspect serve``) would not find."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, **settings.to_env(), "PYTHONPATH": path, **extra}


class Consumer:
    """``python -m app.worker`` in a child process, with the test's settings.

    ``invocations`` (a file) is where the test double of the pipeline records its calls
    (:func:`invocations`); ``args`` are extra command-line arguments (e.g. ``--parent-pid``).
    """

    def __init__(
        self,
        settings: Settings,
        *,
        stage_delay_s: float = 0.0,
        invocations: Path | None = None,
        args: tuple[str, ...] = (),
        log_name: str = "consumer.log",
    ):
        self.env = child_env(settings, PLATE_INSPECT_TEST_STAGE_DELAY_S=str(stage_delay_s))
        if invocations is not None:
            self.env["PLATE_INSPECT_TEST_INVOCATIONS"] = str(invocations)
        self.args = tuple(args)
        self.log = settings.data_dir / log_name
        self.proc: subprocess.Popen | None = None

    def start(self) -> Consumer:
        self.log.parent.mkdir(parents=True, exist_ok=True)
        fh = open(self.log, "ab")  # noqa: SIM115 (the consumer process holds it)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "app.worker", *self.args],
            env=self.env,
            cwd=ROOT,
            stdout=fh,
            stderr=fh,
        )
        fh.close()
        return self

    def wait_ready(self, timeout_s: float = 60.0) -> Consumer:
        """Wait until the consumer logs that it runs its queue (it holds the consumer lock)."""
        wait_until(
            lambda: "consumer ready" in self.output(),
            timeout_s,
            lambda: f"consumer not ready\n{self.output()}",
        )
        return self

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def output(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""


def wait_until(condition, timeout_s: float, message=lambda: "condition not met"):
    """Poll ``condition()`` every 50 ms until it is truthy (returned); AssertionError with ``message()`` after the timeout."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"after {timeout_s} s: {message()}")
        time.sleep(0.05)


def invocations(path: Path) -> list[tuple[str, int, int]]:
    """The test double's calls recorded in ``path``: ``(event, inspection id, pid)``, event ``start`` or ``end``."""
    if not path.exists():
        return []
    rows = []
    for line in path.read_text(encoding="ascii").splitlines():
        event, inspection_id, pid = line.split()
        rows.append((event, int(inspection_id), int(pid)))
    return rows


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def wait_for(
    client,
    inspection_id: int,
    *,
    statuses=("done", "error"),
    timeout_s: float = 60.0,
    consumer=None,
) -> dict:
    """Poll GET /api/v1/inspections/{id} until its status is one of ``statuses``."""
    deadline = time.monotonic() + timeout_s
    while True:
        body = client.get(f"/api/v1/inspections/{inspection_id}").json()
        if body["status"] in statuses:
            return body
        if time.monotonic() > deadline:
            log = consumer.output() if consumer is not None else ""
            raise AssertionError(
                f"inspection {inspection_id} still {body['status']} after {timeout_s} s\n{log}"
            )
        time.sleep(0.05)


def zip_folder(folder: Path, *, skip=()) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for path in sorted(folder.iterdir()):
            if path.is_file() and path.name not in skip and path.name != "truth.npz":
                zf.write(path, path.name)
    return buf.getvalue()


def rezip(data: bytes, *, replace: dict[str, bytes] | None = None, drop=()) -> bytes:
    """A copy of a zip with some members replaced or dropped."""
    replace = replace or {}
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as src, zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            if info.filename in drop:
                continue
            dst.writestr(info.filename, replace.get(info.filename, src.read(info.filename)))
    return out.getvalue()


def target_json(**over) -> bytes:
    import json

    doc = {
        "format": "plate-target/1",
        "shape": {"type": "cylinder", "radius_mm": 5000.0},
        "size_mm": [3000.0, 3000.0],
        "tolerance_mm": 2.0,
    }
    doc.update(over)
    return json.dumps(doc).encode()


def stored_files(data_dir: Path) -> list[str]:
    """Every file under the data dir except the database and queue files."""
    skip = ("plate_inspect.db", "huey.db", "consumer.")
    return sorted(
        str(p.relative_to(data_dir))
        for p in data_dir.rglob("*")
        if p.is_file() and not p.name.startswith(skip)
    )


def pdf_text(pdf: bytes, folder: Path) -> str:
    """The text of a PDF as ``pdftotext -layout`` reads it (poppler-utils)."""
    path = folder / "read.pdf"
    path.write_bytes(pdf)
    out = subprocess.run(
        ["pdftotext", "-layout", str(path), "-"], capture_output=True, text=True, check=True
    )
    return out.stdout


def rendered_page_ink(pdf: bytes, folder: Path, page: int = 1) -> float:
    """Share of the non-white pixels of a PDF page rendered by ``pdftoppm`` at 50 dpi (0: blank)."""
    from PIL import Image

    path = folder / "render.pdf"
    path.write_bytes(pdf)
    subprocess.run(
        [
            "pdftoppm",
            "-r",
            "50",
            "-png",
            "-f",
            str(page),
            "-l",
            str(page),
            str(path),
            str(folder / "page"),
        ],
        check=True,
    )
    [png] = sorted(folder.glob("page*.png"))
    with Image.open(png) as image:
        grey = np.asarray(image.convert("L"))
    return float(np.mean(grey < 240))


def capture_json_with_plate(bundle: bytes, plate_id: str) -> bytes:
    import io
    import json
    import zipfile

    with zipfile.ZipFile(io.BytesIO(bundle)) as zf:
        doc = json.loads(zf.read("capture.json"))
    doc["plate_id"] = plate_id
    return json.dumps(doc).encode()


MACHINE = {
    "kind": "three-roll-pyramid",
    "bottom_roll_spacing_mm": 1400,
    "bottom_roll_diameter_mm": 420,
    "top_roll_diameter_mm": 500,
}


MATERIAL = {
    "grade": "AH36",
    "thickness_mm": 20,
    "yield_mpa": 355,
    "youngs_mpa": 206000,
    "poisson": 0.3,
}


def process(
    displacement_mm: float = 97.0, machine_id: str = "R3-01", flipped: bool = False
) -> dict:
    body = {
        "method": "roll-bending",
        "machine_id": machine_id,
        "top_roll_displacement_mm": displacement_mm,
    }
    return {**body, "flipped": True} if flipped else body


#: The stations of a long plate the service tests upload: 3 stations, 2400 mm apart, of a 3000 x 7500 mm
#: plate, at 320 x 256 px and 6 lights (measured in seconds; tests/pipeline/test_stations.py measures
#: the method at 480 x 384).
STATIONS_PLATE = "LONG-1"


def render_stations(folder: Path) -> list[Path]:
    """The station bundles of :data:`STATIONS_PLATE` rendered by the simulator into ``folder``
    (``station_00``, ... and the whole plate's ``target.json``)."""
    from pipeline.simulate import CaptureSpec, PlateSpec, simulate_stations

    return simulate_stations(
        folder,
        n_stations=3,
        spacing_mm=2400.0,
        plate=PlateSpec(size_mm=(3000.0, 7500.0)),
        capture=CaptureSpec(width=320, height=256, n_lights=6),
        plate_id=STATIONS_PLATE,
        seed=5,
    )


def zip_stations(bundles: list[Path], *, top: str = "") -> bytes:
    """One zip of station folders (``<top>station_00/capture.json``, ...), as a client sends them."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for bundle in bundles:
            for path in sorted(bundle.iterdir()):
                if path.is_file() and path.name != "truth.npz":
                    zf.write(path, f"{top}{bundle.name}/{path.name}")
    return buf.getvalue()


def edit_capture_json(bundle: bytes, change) -> bytes:
    """A bundle zip whose capture.json ``change(doc)`` edited."""
    import json

    with zipfile.ZipFile(io.BytesIO(bundle)) as zf:
        doc = json.loads(zf.read("capture.json"))
    change(doc)
    return rezip(bundle, replace={"capture.json": json.dumps(doc).encode()})
