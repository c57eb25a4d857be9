"""GenICam cameras (GigE Vision, USB3 Vision) through Aravis 0.8 and PyGObject.

Aravis is imported on first use only (``gi.require_version("Aravis", "0.8")``), so the rest of
the product runs where it is not installed. A ``device_id`` is what Aravis opens a camera by: its
IP address, ``VENDOR-SERIAL`` id, or physical id (``arv-tool-0.8`` lists them); one beginning with
``Fake`` is Aravis' built-in fake camera (``Fake_1``).

Frames are taken with the camera in software-trigger mode (TriggerSelector FrameStart, TriggerMode
On, TriggerSource Software) and acquisition started once; a camera without a software trigger
takes each frame as a single-frame acquisition. A frame exposed before the lights were switched
must not be taken for the next one: before each trigger the stream's queue is emptied, and a frame
that Aravis received before the trigger (its system time stamp) is put back, not taken.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from typing import Any

import numpy as np

from ..formats import AcquisitionError, CellCamera
from .cameras import PIXEL_FORMATS, Camera, Frame, Side

#: Buffers queued on a camera's stream.
N_BUFFERS = 4


def _aravis(device: str) -> tuple[Any, Any]:
    """The Aravis and GLib modules, or an error saying how to install them."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ImportError, ValueError) as exc:
        raise AcquisitionError(
            device,
            "loading Aravis",
            f"Aravis 0.8 with PyGObject is not installed ({exc}); scripts/setup.sh installs "
            "Debian's gir1.2-aravis-0.8 and PyGObject (pip install '.[camera]')",
        ) from None
    return Aravis, GLib


class AravisCamera(Camera):
    """A GenICam camera opened through Aravis (driver ``aravis``).

    Parameters
    ----------
    side : {"left", "right"}
    config : pipeline.formats.CellCamera

    Raises
    ------
    AcquisitionError
        Aravis missing, or no camera answers to ``config.device_id``.
    """

    def __init__(self, side: Side, config: CellCamera) -> None:
        super().__init__(side, config)
        self._Aravis, self._GLib = _aravis(self.device)
        device_id = config.device_id
        if device_id is None:  # impossible: CellCamera requires it of an aravis camera
            raise AcquisitionError(self.device, "opening", "no device_id in the configuration")
        if device_id.startswith("Fake"):
            self._Aravis.enable_interface("Fake")
        with self._errors("opening"):
            self._cam = self._Aravis.Camera.new(device_id)
            self._format = self._cam.get_pixel_format_as_string()
            region = self._cam.get_region()
        self._region = [int(region.x), int(region.y), int(region.width), int(region.height)]
        self._stream: Any = None  # an Aravis stream once started
        self._trigger_ns = 0
        self._started = False
        self._can_trigger = False

    @contextmanager
    def _errors(self, step: str) -> Iterator[None]:
        """GLib errors from Aravis as :class:`AcquisitionError` naming this camera and ``step``."""
        try:
            yield
        except self._GLib.Error as err:
            raise AcquisitionError(self.device, step, err.message) from None

    @property
    def can_trigger(self) -> bool:
        return self._can_trigger

    def sensor_size(self) -> tuple[int, int]:
        with self._errors("reading the sensor size"):
            w, h = self._cam.get_sensor_size()
        return int(w), int(h)

    def pixel_formats(self) -> list[str]:
        with self._errors("reading the pixel formats"):
            return list(self._cam.dup_available_pixel_formats_as_strings())

    def configure(self, *, pixel_format: str, width: int, height: int) -> None:
        cam = self._cam
        with self._errors("setting the pixel format"):
            cam.set_pixel_format_from_string(pixel_format)
            self._format = cam.get_pixel_format_as_string()
        if self._format != pixel_format:
            raise AcquisitionError(
                self.device,
                "setting the pixel format",
                f"asked for {pixel_format}, got {self._format}",
            )
        with self._errors("setting the region"):
            sw, sh = cam.get_sensor_size()
            x_step, y_step = (
                max(cam.get_x_offset_increment(), 1),
                max(cam.get_y_offset_increment(), 1),
            )
            x, y = (sw - width) // 2 // x_step * x_step, (sh - height) // 2 // y_step * y_step
            cam.set_region(x, y, width, height)
            region = cam.get_region()
        if (region.width, region.height) != (width, height):
            raise AcquisitionError(
                self.device,
                "setting the region",
                f"asked for {width}x{height} px (the calibration's image_size), the camera took "
                f"{region.width}x{region.height} (width step {cam.get_width_increment()}, height step "
                f"{cam.get_height_increment()})",
            )
        self._region = [int(region.x), int(region.y), int(region.width), int(region.height)]
        with self._errors("setting the trigger"):
            self._can_trigger = bool(cam.is_software_trigger_supported())
            if self._can_trigger:
                cam.set_acquisition_mode(self._Aravis.AcquisitionMode.CONTINUOUS)
                cam.set_trigger("Software")
            else:
                cam.clear_triggers()
                cam.set_acquisition_mode(self._Aravis.AcquisitionMode.SINGLE_FRAME)
            if cam.is_gv_device():
                cam.gv_auto_packet_size()

    def exposure_bounds_us(self) -> tuple[float, float]:
        with self._errors("reading the exposure range"):
            lo, hi = self._cam.get_exposure_time_bounds()
        return float(lo), float(hi)

    def set_exposure(self, exposure_us: float, *, step: str) -> float:
        with self._errors(step):
            self._cam.set_exposure_time(exposure_us)
            return float(self._cam.get_exposure_time())

    def gain_bounds_db(self) -> tuple[float, float] | None:
        with self._errors("reading the gain range"):
            if not self._cam.is_gain_available():
                return None
            lo, hi = self._cam.get_gain_bounds()
        return float(lo), float(hi)

    def set_gain(self, gain_db: float) -> float:
        with self._errors("setting the gain"):
            self._cam.set_gain(gain_db)
            return float(self._cam.get_gain())

    def start(self) -> None:
        with self._errors("starting the stream"):
            self._stream = self._cam.create_stream(None, None)
            payload = self._cam.get_payload()
            for _ in range(N_BUFFERS):
                self._stream.push_buffer(self._Aravis.Buffer.new_allocate(payload))
            if self._can_trigger:
                self._cam.start_acquisition()
                self._started = True

    def _drain(self) -> None:
        while (buffer := self._stream.try_pop_buffer()) is not None:
            self._stream.push_buffer(buffer)

    def trigger(self, *, step: str) -> None:
        with self._errors(step):
            self._drain()
            self._trigger_ns = time.time_ns()  # Aravis' system time stamps are wall-clock ns
            if self._can_trigger:
                self._cam.software_trigger()
            else:
                self._cam.start_acquisition()
                self._started = True

    def fetch(self, *, step: str, timeout_s: float) -> Frame:
        deadline = time.monotonic() + timeout_s
        while True:
            left_us = int((deadline - time.monotonic()) * 1e6)
            buffer = self._stream.timeout_pop_buffer(left_us) if left_us > 0 else None
            if buffer is None:
                raise AcquisitionError(
                    self.device,
                    step,
                    f"no frame within {timeout_s:.1f} s (camera gone or not triggered?)",
                )
            cleared = buffer.get_status() == self._Aravis.BufferStatus.CLEARED
            if not cleared and (
                not 0 < buffer.get_system_timestamp() < self._trigger_ns
            ):  # 0: nothing received, a failed frame
                break
            # begun before the trigger, or handed back unfilled (status cleared: the stream recycled
            # it, no packet of any frame in it, seen on a loaded machine): not this frame
            self._stream.push_buffer(buffer)
        try:
            return self._frame(buffer, step)
        finally:
            self._stream.push_buffer(buffer)
            if not self._can_trigger:
                with self._errors(step):
                    self._cam.stop_acquisition()
                self._started = False

    def _frame(self, buffer: Any, step: str) -> Frame:
        status = buffer.get_status()
        if status != self._Aravis.BufferStatus.SUCCESS:
            raise AcquisitionError(
                self.device, step, f"incomplete frame (buffer status {status.value_nick})"
            )
        if buffer.get_payload_type() not in (
            self._Aravis.BufferPayloadType.IMAGE,
            self._Aravis.BufferPayloadType.EXTENDED_CHUNK_DATA,
            self._Aravis.BufferPayloadType.CHUNK_DATA,
        ):
            raise AcquisitionError(
                self.device,
                step,
                f"not an image (payload type {buffer.get_payload_type().value_nick})",
            )
        width, height = buffer.get_image_width(), buffer.get_image_height()
        if [width, height] != self._region[2:]:
            raise AcquisitionError(
                self.device,
                step,
                f"a {width}x{height} px frame, expected {self._region[2]}x{self._region[3]}",
            )
        eight = PIXEL_FORMATS[self._format] == 8
        dtype = np.dtype(np.uint8 if eight else "<u2")  # GenICam pixels are little-endian
        data = buffer.get_image_data()
        if len(data) != width * height * dtype.itemsize:
            raise AcquisitionError(
                self.device,
                step,
                f"{len(data)} bytes of image data, expected {width}x{height} {self._format} pixels",
            )
        return Frame(
            image=np.frombuffer(data, dtype=dtype)
            .reshape(height, width)
            .astype(np.uint8 if eight else np.uint16, copy=False),
            device_timestamp_ns=int(buffer.get_timestamp()),
            frame_id=int(buffer.get_frame_id()),
        )

    def describe(self) -> dict[str, Any]:
        cam = self._cam
        with self._errors("reading the camera's description"):
            gain = float(cam.get_gain()) if cam.is_gain_available() else None
            return {
                "driver": "aravis",
                "device_id": self.config.device_id,
                "protocol": "GigE Vision"
                if cam.is_gv_device()
                else "USB3 Vision"
                if cam.is_uv_device()
                else "Aravis fake",
                "vendor": cam.get_vendor_name(),
                "model": cam.get_model_name(),
                "serial": cam.get_device_serial_number(),
                "pixel_format": self._format,
                "bit_depth": PIXEL_FORMATS.get(self._format),
                "region": self._region,
                "gain_db": gain,
                "trigger": "software" if self._can_trigger else "single frame",
            }

    def close(self) -> None:
        if self._started:
            with suppress(self._GLib.Error):  # a camera that is gone cannot be stopped
                self._cam.stop_acquisition()
        self._stream = None
        self._cam = None
