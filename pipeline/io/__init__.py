"""Reading and writing the project's files: calibrations, capture bundles, targets, results.

Modules: ``jsonfile`` (JSON limits), ``validation`` (pydantic errors named by file and field),
``bundle`` (folders and zips), ``images`` (decoding), ``calibration``, ``capture``, ``headers``
(a bundle checked without decoding), ``lights_file``, ``target``.

Every failure on bad input is an :class:`~pipeline.formats.InputError` naming the
file and the field (``"capture.json: photometric.lights[3].direction: ..."``); the
field is a dotted path into the JSON document, list indices in brackets.

Capture bundles (``plate-capture/1``) are a folder holding ``capture.json`` and
the images it names, or a ``.zip`` of such a folder. A zip is read in memory,
never extracted to disk: every member name, type and size is checked first
(no absolute paths, no ``..``, no symlinks, no encrypted members, no duplicate
names, a total uncompressed size limit and a per-member compression-ratio
limit); only then are the members the capture names read and decoded with
``cv2.imdecode`` from bytes. Images must be PNG or TIFF; their size is read
from the file header and checked against the calibration before decoding, so a
small file claiming a huge image is refused without allocating it.
:func:`read_capture_header` checks a bundle as far as that goes without decoding
any image (capture.json, the calibration, each image's format and size from its
header), for a process that must not hold the images (the web service).
"""

from ..formats import InputError
from .bundle import MAX_ZIP_RATIO, MAX_ZIP_TOTAL_BYTES, ZIP_RATIO_EXEMPT_BYTES
from .calibration import calibration_document, load_calibration
from .capture import Capture, load_capture
from .headers import CaptureHeader, ImageHeader, InputLimitError, read_capture_header
from .jsonfile import MAX_JSON_DEPTH, read_json
from .lights_file import light_calibration_document, load_light_calibration
from .target import MESH_SUFFIXES, Target, load_target

__all__ = [
    "MAX_JSON_DEPTH",
    "MAX_ZIP_RATIO",
    "MAX_ZIP_TOTAL_BYTES",
    "MESH_SUFFIXES",
    "ZIP_RATIO_EXEMPT_BYTES",
    "Capture",
    "CaptureHeader",
    "ImageHeader",
    "InputError",
    "InputLimitError",
    "Target",
    "calibration_document",
    "light_calibration_document",
    "load_calibration",
    "load_capture",
    "load_light_calibration",
    "load_target",
    "read_capture_header",
    "read_json",
]
