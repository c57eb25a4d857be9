"""plate-inspect acquire against Aravis' fake cameras, a TCP light controller, and the demo cell."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from pipeline.acquisition import acquire, write_demo_cell
from pipeline.cli import EXIT_BAD_INPUT, EXIT_HARDWARE, EXIT_NOT_MEASURABLE, EXIT_OK, main
from pipeline.formats import AcquisitionError, InputError
from pipeline.io import load_capture
from tests.acquisition.devices import FakeGigECamera
from tests.acquisition.helpers import HEIGHT, WIDTH, tcp_lights, write_cell

N = 6
FAKE_1 = {"driver": "aravis", "device_id": "Fake_1"}
SIMULATED = {"driver": "simulated"}
#: Configured exposures: no auto-exposure pre-shots.
FIXED_FAKE_1 = {**FAKE_1, "exposure_us": 5000.0}
FIXED_SIMULATED = {**SIMULATED, "exposure_us": 5000.0}
SIMULATED_LIGHTS = {"driver": "simulated"}


def _all(verb: str) -> list[str]:
    return [f"L{k} {verb}" for k in range(N)]


#: Light by light in image order: on, frame, off.
SEQUENCE = [c for k in range(N) for c in (f"L{k} ON", f"L{k} OFF")]


def _nothing_left(tmp_path) -> bool:
    return not (tmp_path / "bundle").exists() and not (tmp_path / "bundle.partial").exists()


def test_acceptance_gige_and_fake_cameras_tcp_lights(tmp_path, fake_gv, light_server, capsys):
    """Left on arv-fake-gv-camera (GigE Vision over loopback), right Fake_1, TCP lights, 6 lights."""
    server = light_server()
    left = {"driver": "aravis", "device_id": fake_gv.device_id}
    config = write_cell(
        tmp_path / "cell", left=left, right=FAKE_1, lights=tcp_lights(server), n_lights=N
    )
    out = tmp_path / "bundle"

    assert main(["acquire", str(config), "--plate-id", "ACC-0001", "--out", str(out)]) == EXIT_OK
    assert "9 frames (6 photometric, dark, stereo pair)" in capsys.readouterr().out

    capture = load_capture(out)  # a valid plate-capture/1 bundle
    assert capture.plate_id == "ACC-0001" and capture.n_lights == N and capture.bit_depth == 16
    assert capture.images.shape == (N, HEIGHT, WIDTH)
    assert (
        capture.dark.shape
        == capture.stereo_left.shape
        == capture.stereo_right.shape
        == (HEIGHT, WIDTH)
    )
    assert capture.working_distance_mm == 3000.0
    assert capture.images.max() > 0  # the fake cameras' pattern, exposed

    record = json.loads((out / "capture.json").read_text())["acquisition"]
    gv, fake = record["cameras"]["left"], record["cameras"]["right"]
    assert (gv["vendor"], gv["model"], gv["serial"], gv["protocol"]) == (
        "Aravis",
        "Fake",
        fake_gv.serial,
        "GigE Vision",
    )
    assert (fake["vendor"], fake["model"], fake["device_id"]) == ("Aravis", "Fake", "Fake_1")
    for cam in (gv, fake):
        assert cam["pixel_format"] == "Mono16" and cam["region"][2:] == [WIDTH, HEIGHT]
        assert cam["exposure_source"] == "auto-exposure" and cam["gain_db"] == 0.0
    assert record["light_controller"] == {
        "driver": "tcp",
        "address": server.address,
        "n_lights": N,
        "replies": True,
        "stereo_light": False,
    }
    assert record["stereo_trigger"] == "together" and record["total_s"] > 0
    files = [frame["file"] for frame in record["frames"]]
    # the stereo pair first, then the dark frame and the photometric images: the last frame is one
    assert files == ["stereo_left.png", "stereo_right.png", "dark.png"] + [
        f"ps_{k:02d}.png" for k in range(N)
    ]
    assert [frame["lights"] for frame in record["frames"][2:]] == [[]] + [[k] for k in range(N)]
    times = [frame["t_s"] for frame in record["frames"]]
    assert times == sorted(times)

    # the auto-exposure pre-shots under all lights, then one per light (the photometric exposure is
    # set for a single light's frame), then the stereo pair under all lights, then light by light
    assert server.commands == (
        _all("ON") + _all("OFF") + SEQUENCE + _all("ON") + _all("OFF") + SEQUENCE
    )

    target = tmp_path / "cell" / "target.json"
    target.write_text(
        json.dumps(
            {
                "format": "plate-target/1",
                "shape": {"type": "cylinder", "radius_mm": 5000.0},
                "size_mm": [3000.0, 3000.0],
                "tolerance_mm": 2.0,
            }
        )
    )
    code = main(
        [
            "inspect",
            str(out),
            "--target",
            str(target),
            "--out",
            str(tmp_path / "result"),
            "--no-warm-up",
        ]
    )
    assert code in (EXIT_OK, EXIT_NOT_MEASURABLE)  # the fake cameras' pattern is no plate


def test_configured_exposure_takes_no_pre_shots_and_a_flood_light(tmp_path, light_server):
    server = light_server()
    lights = tcp_lights(server, stereo_on="FLOOD ON\n", stereo_off="FLOOD OFF\n")
    left = {**FAKE_1, "exposure_us": 4000.0, "gain_db": 2.0}
    config = write_cell(
        tmp_path / "cell", left=left, right={**SIMULATED, "exposure_us": 3000.0}, lights=lights
    )

    out = acquire(config, "P-2", tmp_path / "bundle")

    assert server.commands == ["FLOOD ON", "FLOOD OFF", *SEQUENCE]
    record = json.loads((out / "capture.json").read_text())["acquisition"]
    assert record["pre_shots"] == 0 and record["stereo_lighting"] == "stereo light"
    assert record["cameras"]["left"]["exposure_us"] == {"photometric": 4000.0, "stereo": 4000.0}
    assert record["cameras"]["left"]["gain_db"] == 2.0
    assert record["cameras"]["right"]["exposure_us"] == {"stereo": 3000.0}
    assert [f["lights"] for f in record["frames"][:2]] == ["stereo light", "stereo light"]


def test_configured_exposure_is_divided_among_all_lights_for_the_stereo_pair(tmp_path):
    config = write_cell(
        tmp_path / "cell",
        left={**SIMULATED, "exposure_us": 6000.0},
        right={**SIMULATED, "exposure_us": 3000.0},
        lights=SIMULATED_LIGHTS,
    )
    record = json.loads((acquire(config, "P-3", tmp_path / "bundle") / "capture.json").read_text())[
        "acquisition"
    ]
    assert record["cameras"]["left"]["exposure_us"] == {"photometric": 6000.0, "stereo": 1000.0}
    assert record["cameras"]["right"]["exposure_us"] == {"stereo": 500.0}


def test_demo_cell_renders_the_plate_light_by_light_and_inspects(tmp_path):
    config = write_demo_cell(tmp_path / "cell", n_lights=6, width=WIDTH, height=HEIGHT)
    out = acquire(config, "DEMO-1", tmp_path / "bundle")
    capture = load_capture(out)

    full = 2**16 - 1
    lit = capture.images - capture.dark
    assert (
        capture.images.max() <= 0.9 * full * 1.05
    )  # auto-exposure keeps the brightest samples near 90 %
    assert np.percentile(capture.stereo_left, 99.9) <= 0.9 * full
    # each image is lit by its own light: the images differ, each brightest on another part of the plate
    brightest = [np.unravel_index(np.argmax(cv_blur(img)), img.shape) for img in lit]
    assert len(set(brightest)) == len(brightest)

    result = tmp_path / "result"
    assert (
        main(
            [
                "inspect",
                str(out),
                "--target",
                str(tmp_path / "cell" / "target.json"),
                "--out",
                str(result),
                "--no-warm-up",
            ]
        )
        == EXIT_OK
    )
    doc = json.loads((result / "result.json").read_text())
    assert doc["radius_mm"] == pytest.approx(5000.0, rel=0.01)


def test_frames_handed_over_in_memory_load_as_the_files_do(tmp_path):
    """The job's inspection takes the frames an acquisition has just written from memory: the same
    capture, to the bit, as reading the files; a frame the files could not hold is refused as they
    would be, naming the image and its field."""
    config = write_demo_cell(tmp_path / "cell", n_lights=4, width=WIDTH, height=HEIGHT)
    frames: dict[str, np.ndarray] = {}
    out = acquire(config, "DEMO-2", tmp_path / "bundle", frames=frames)
    assert sorted(frames) == sorted(p.name for p in out.glob("*.png"))
    from_files, from_memory = load_capture(out), load_capture(out, frames=frames)
    for name in ("images", "dark", "stereo_left", "stereo_right"):
        assert np.array_equal(getattr(from_memory, name), getattr(from_files, name)), name
    assert from_memory.source == from_files.source == out

    too_bright = frames["ps_01.png"].astype(np.uint32) + 2**16
    with pytest.raises(
        InputError, match=r"photometric\.images\[1\].*'ps_01\.png': expected 8- or 16-bit"
    ):
        load_capture(out, frames={**frames, "ps_01.png": too_bright})
    cropped = frames["stereo_right.png"][:-2]
    with pytest.raises(
        InputError, match=r"stereo\.right.*'stereo_right\.png' \(.*\) is \d+x\d+ px, expected"
    ):
        load_capture(out, frames={**frames, "stereo_right.png": cropped})


def cv_blur(image: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.blur(image, (31, 31))


# --------------------------------------------------------------------------- failures


def test_missing_camera_is_a_hardware_failure_naming_it(tmp_path, light_server, capsys):
    server = light_server()
    missing = {"driver": "aravis", "device_id": "Nobody-0000"}
    config = write_cell(tmp_path / "cell", left=missing, right=FAKE_1, lights=tcp_lights(server))

    assert (
        main(["acquire", str(config), "--plate-id", "P", "--out", str(tmp_path / "bundle")])
        == EXIT_HARDWARE
    )
    err = capsys.readouterr().err
    assert "left camera Nobody-0000: opening:" in err and "not found" in err
    assert server.commands == [] and _nothing_left(tmp_path)


def test_light_controller_refusing_stops_the_acquisition_and_switches_the_light_off(
    tmp_path, light_server
):
    server = light_server(refuse="L2 ON")
    # a flood light for the stereo pair: "L2 ON" comes only with photometric image 2
    lights = tcp_lights(server, stereo_on="FLOOD ON\n", stereo_off="FLOOD OFF\n")
    config = write_cell(tmp_path / "cell", left=FIXED_FAKE_1, right=FIXED_SIMULATED, lights=lights)

    with pytest.raises(
        AcquisitionError, match=re.escape(f"light controller {server.address}: photometric image 2")
    ) as err:
        acquire(config, "P", tmp_path / "bundle")

    assert "refused 'L2 ON': answered 'ERR refused'" in str(err.value)
    # the stereo pair first, then light by light: L2 switched off again after the refusal
    assert server.commands == ["FLOOD ON", "FLOOD OFF", *SEQUENCE[:6]]
    assert _nothing_left(tmp_path)


def test_light_controller_that_stops_answering_times_out(tmp_path, light_server, capsys):
    server = light_server(stall_after=2 * N + 3)  # the stereo pair's 2 N, then L0 on and off, L1 on
    config = write_cell(
        tmp_path / "cell", left=FIXED_FAKE_1, right=FIXED_SIMULATED, lights=tcp_lights(server)
    )

    assert (
        main(["acquire", str(config), "--plate-id", "P", "--out", str(tmp_path / "bundle")])
        == EXIT_HARDWARE
    )
    assert (
        f"light controller {server.address}: photometric image 1 (ps_01.png): no answer to 'L1 OFF' within 2 s"
        in capsys.readouterr().err
    )
    assert _nothing_left(tmp_path)


def test_light_controller_not_listening_is_a_hardware_failure(tmp_path, light_server, capsys):
    server = light_server()
    server.close()  # nothing listens on its port any more
    config = write_cell(tmp_path / "cell", left=FAKE_1, right=SIMULATED, lights=tcp_lights(server))

    assert (
        main(["acquire", str(config), "--plate-id", "P", "--out", str(tmp_path / "bundle")])
        == EXIT_HARDWARE
    )
    assert (
        f"light controller {server.address}: connecting: Connection refused"
        in capsys.readouterr().err
    )
    assert _nothing_left(tmp_path)


def test_silent_light_controller_is_used_without_answers(tmp_path, light_server):
    server = light_server(reply=None)
    config = write_cell(
        tmp_path / "cell", left=FIXED_FAKE_1, right=FIXED_SIMULATED, lights=tcp_lights(server)
    )
    record = json.loads((acquire(config, "P", tmp_path / "bundle") / "capture.json").read_text())[
        "acquisition"
    ]
    assert record["light_controller"]["replies"] is False
    assert server.settled() == _all("ON") + _all("OFF") + SEQUENCE  # no pre-shots


@pytest.mark.parametrize(("reply", "answering"), [("OK", True), (None, False)])
def test_echoed_commands_are_skipped(tmp_path, light_server, reply, answering):
    server = light_server(echo=True, reply=reply)  # "L0 ON" back, then "OK" (or nothing)
    config = write_cell(
        tmp_path / "cell", left=FIXED_FAKE_1, right=FIXED_SIMULATED, lights=tcp_lights(server)
    )
    record = json.loads((acquire(config, "P", tmp_path / "bundle") / "capture.json").read_text())[
        "acquisition"
    ]
    assert record["light_controller"]["replies"] is answering
    assert server.settled() == _all("ON") + _all("OFF") + SEQUENCE


@pytest.mark.slow
def test_camera_vanishing_mid_sequence_leaves_no_bundle(tmp_path, light_server):
    camera = FakeGigECamera()
    try:
        server = light_server(
            on_command=lambda command: camera.stop() if command == "L2 ON" else None
        )
        left = {"driver": "aravis", "device_id": camera.device_id, "exposure_us": 5000.0}
        # a flood light for the stereo pair: "L2 ON" comes only with photometric image 2
        lights = tcp_lights(server, stereo_on="FLOOD ON\n", stereo_off="FLOOD OFF\n")
        config = write_cell(tmp_path / "cell", left=left, right=FIXED_FAKE_1, lights=lights)
        with pytest.raises(
            AcquisitionError,
            match=re.escape("left camera 127.0.0.1: photometric image 2 (ps_02.png): "),
        ):
            acquire(config, "P", tmp_path / "bundle", frame_timeout_s=1.0)
    finally:
        camera.close()
    assert server.commands == ["FLOOD ON", "FLOOD OFF", *SEQUENCE[:6]]
    assert _nothing_left(tmp_path)


def test_incomplete_frames_are_a_hardware_failure(tmp_path):
    camera = FakeGigECamera(lost_packets_per_thousand=900)
    try:
        left = {"driver": "aravis", "device_id": camera.device_id, "exposure_us": 5000.0}
        config = write_cell(
            tmp_path / "cell", left=left, right=FIXED_SIMULATED, lights=SIMULATED_LIGHTS
        )
        with pytest.raises(
            AcquisitionError,
            # the stereo pair is the first frame taken
            match=r"left camera 127\.0\.0\.1: stereo pair .*: incomplete frame",
        ):
            acquire(config, "P", tmp_path / "bundle")
    finally:
        camera.close()
    assert _nothing_left(tmp_path)


def test_sensor_smaller_than_the_calibration_is_refused(tmp_path, capsys):
    config = write_cell(
        tmp_path / "cell", left=FAKE_1, right=SIMULATED, lights=SIMULATED_LIGHTS, size=(4096, 2160)
    )
    assert (
        main(["acquire", str(config), "--plate-id", "P", "--out", str(tmp_path / "bundle")])
        == EXIT_BAD_INPUT
    )
    err = capsys.readouterr().err
    assert (
        "calibration.json: image_size: 4096x2160 px is larger than the left camera Fake_1's sensor (2048x2048 px)"
        in err
    )
    assert _nothing_left(tmp_path)


def test_exposure_out_of_the_cameras_range_names_the_field(tmp_path, capsys):
    config = write_cell(
        tmp_path / "cell",
        left={**FAKE_1, "exposure_us": 1e9},
        right=SIMULATED,
        lights=SIMULATED_LIGHTS,
    )
    assert (
        main(["acquire", str(config), "--plate-id", "P", "--out", str(tmp_path / "bundle")])
        == EXIT_BAD_INPUT
    )
    assert (
        "cell.json: cameras.left.exposure_us: expected within the left camera Fake_1's range 10-1e+07 us, got 1e+09"
        in capsys.readouterr().err
    )


def test_existing_bundle_is_not_overwritten_and_a_stale_partial_is_replaced(tmp_path, capsys):
    config = write_cell(tmp_path / "cell", left=SIMULATED, right=SIMULATED, lights=SIMULATED_LIGHTS)
    (tmp_path / "bundle.partial").mkdir()
    (tmp_path / "bundle.partial" / "stale.png").write_bytes(b"x")
    out = acquire(config, "P", tmp_path / "bundle")
    assert not (out / "stale.png").exists() and not (tmp_path / "bundle.partial").exists()

    assert main(["acquire", str(config), "--plate-id", "P", "--out", str(out)]) == EXIT_BAD_INPUT
    assert "bundle: already exists" in capsys.readouterr().err
