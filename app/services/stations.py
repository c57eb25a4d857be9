"""A plate uploaded as its conveyor stations: several bundles for one inspection (docs/stations.md).

Two forms of upload carry them (docs/api.md): several multipart parts ``capture``, one bundle each,
or one ``capture`` zip holding a folder per station (``station_00/``, ``station_01/``, ...; at its
root or in its one top folder). Either way each station becomes a zip of its own under the upload's
``stations/`` folder, named by its index (``station_00.zip``, ...), after the set is checked as the
pipeline checks it (:func:`pipeline.stations.plan_stations`: a ``station`` in every bundle, one plate,
indices 0 .. n-1 without a duplicate, travels that overlap), each bundle within the request limits.
The job measures the bundles :func:`capture_bundles` lists as one plate; the pages and the report
read the stations of its result from details.json (:func:`read_stations`).

Errors name the station as the client sent it: a part by its file name (``s1.zip:capture.json``,
or ``capture[1]`` when parts share a name or have none), a folder of the zip by its path in the zip
(``plate.zip:station_01/capture.json``).
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from app.limits import Limits
from app.limits.physical import check_lights
from app.limits.work import read_capture_header
from app.schemas import StationOut
from pipeline.formats import InputError
from pipeline.io import CaptureHeader
from pipeline.io.bundle import MAX_ZIP_RATIO, MAX_ZIP_TOTAL_BYTES, check_zip_members
from pipeline.stations import plan_stations

log = logging.getLogger(__name__)

#: Folder (under an inspection's inputs) holding one bundle per station, ``station_00.zip`` on.
STATIONS_DIR = "stations"
#: Folder (under an upload's staging folder) the parts of a multipart upload are saved into as sent,
#: ``0.zip``, ``1.zip``, ... (the multipart parts' order).
PARTS_DIR = "parts"
#: The capture.json of a station folder in a zip: the folder (at the root or in one top folder).
_STATION_MEMBER = re.compile(r"^((?:[^/]+/)?[^/]+/)capture\.json$")


@dataclass(frozen=True)
class StagedStations:
    """The stations of an upload, checked and staged.

    Attributes
    ----------
    headers : list of pipeline.io.CaptureHeader
        Each station's header, in station order (index 0 first).
    labels : list of str
        Each station's capture.json named as sent (``s0.zip:capture.json``,
        ``plate.zip:station_00/capture.json``), in station order.
    folder : Path
        The staging folder's :data:`STATIONS_DIR`, holding ``station_<index:02d>.zip``.
    """

    headers: list[CaptureHeader]
    labels: list[str]
    folder: Path


def station_bundle_name(index: int) -> str:
    """The file name of station ``index``'s bundle in :data:`STATIONS_DIR`."""
    return f"station_{index:02d}.zip"


def capture_bundles(capture_path: Path) -> list[Path]:
    """The capture bundles an inspection's job measures, in station order: an upload's stations (a
    :data:`STATIONS_DIR` folder of ``station_NN.zip``), an acquisition's (a folder of ``station_NN/``
    bundles, written whole by :func:`pipeline.acquisition.acquire_stations`), else ``[capture_path]``
    (one bundle)."""
    capture_path = Path(capture_path)
    if not capture_path.is_dir() or (capture_path / "capture.json").is_file():
        return [capture_path]
    bundles = [p for p in capture_path.iterdir() if re.fullmatch(r"station_\d+(\.zip)?", p.name)]
    if not bundles:
        return [capture_path]
    return sorted(bundles, key=lambda p: int(p.name.split("_")[1].split(".")[0]))


def part_names(filenames: list[str | None]) -> list[str]:
    """How errors name each multipart part ``capture``: its file name as sent (folders cut), or
    ``capture[i]`` (0-based, in the order sent) when parts share a name or have none."""
    names = [PurePosixPath((f or "").replace("\\", "/")).name for f in filenames]
    if all(names) and len(set(names)) == len(names):
        return names
    return [f"capture[{i}]" for i in range(len(names))]


def station_folders(zip_path: Path) -> list[str] | None:
    """The station folders of a zip holding one bundle folder per station (``station_00/``, ...,
    at its root or in its one top folder), each as its member prefix (``station_00/``); None for a
    zip that is one bundle (``capture.json`` at its root or in its one top folder), that has fewer
    than two such folders, or that is not a readable zip (the bundle's checks then say why)."""
    try:
        with zipfile.ZipFile(zip_path) as zf:
            names = [n for n in zf.namelist() if not n.startswith("__MACOSX/")]
    except (zipfile.BadZipFile, OSError):
        return None
    tops = {n.split("/", 1)[0] for n in names}
    if "capture.json" in names or (len(tops) == 1 and f"{next(iter(tops))}/capture.json" in names):
        return None
    folders = sorted(m.group(1) for n in names if (m := _STATION_MEMBER.match(n)))
    return folders if len(folders) >= 2 else None  # one folder deeper is a misplaced bundle


def stage_stations(
    staging_dir: Path, capture_file: str, *, limits: Limits, sent_names: list[str]
) -> StagedStations | None:
    """Check and stage the stations of an upload in ``staging_dir``; None for an upload of one bundle.

    The upload holds the multipart parts in :data:`PARTS_DIR` (``0.zip``, ... as sent; named
    ``sent_names`` in errors) or one zip ``capture_file`` (sent as ``sent_names[0]``) of station folders
    (:func:`station_folders`; split into a zip per station, the zip then removed). Each bundle is
    checked without decoding an image and within ``limits`` (:func:`app.limits.work.read_capture_header`,
    its lights), then the set as the pipeline checks it (:func:`pipeline.stations.plan_stations`).

    Raises
    ------
    pipeline.formats.InputError
        Naming the part (or the zip's folder) as sent and the field: a bad bundle, one over
        ``limits``, a bundle without ``station``, another ``plate_id``, a duplicate or missing index,
        travels that do not overlap.
    """
    parts = staging_dir / PARTS_DIR
    if parts.is_dir():
        labels = {parts / f"{i}.zip": name for i, name in enumerate(sent_names)}
    else:
        folders = station_folders(staging_dir / capture_file)
        if folders is None:
            return None
        sent = sent_names[0] if sent_names and sent_names[0] != "capture[0]" else capture_file
        labels = _split(staging_dir / capture_file, folders, parts, sent)
    try:
        headers = {path: _checked_header(path, limits) for path in labels}
        ordered = plan_stations(list(labels), headers=headers)
    except InputError as err:
        raise _as_sent(err, labels) from None
    folder = staging_dir / STATIONS_DIR
    folder.mkdir()
    sources = [Path(str(ref.source)) for ref in ordered]  # planned from paths: each its path
    for ref, source in zip(ordered, sources, strict=True):
        source.rename(folder / station_bundle_name(ref.station.index))
    shutil.rmtree(parts)
    return StagedStations(
        headers=[headers[source] for source in sources],
        labels=[_as_sent(InputError(r.label, "", ""), labels).file for r in ordered],
        folder=folder,
    )


def _checked_header(path: Path, limits: Limits) -> CaptureHeader:
    """A station's bundle checked as an uploaded bundle is (its header, within ``limits``)."""
    header = read_capture_header(path, limits)
    check_lights(header.lights, label=header.label, field="photometric.lights")
    return header


def _split(zip_path: Path, folders: list[str], parts: Path, sent: str) -> dict[Path, str]:
    """Write each station folder of ``zip_path`` as a zip of its own into ``parts`` (``0.zip``, ...,
    stored: the images are compressed already), then remove ``zip_path``; each new zip's label
    (``sent:station_00/``). Every member is checked first as the pipeline checks a bundle's (no
    link, no encrypted member, the sizes and compression ratios within its zip limits).

    Raises
    ------
    pipeline.formats.InputError
        A member refused (named by its path in the zip).
    """
    parts.mkdir()
    labels: dict[Path, str] = {}
    with zipfile.ZipFile(zip_path) as zf:
        members = check_zip_members(
            zf, sent, max_total_bytes=MAX_ZIP_TOTAL_BYTES, max_ratio=MAX_ZIP_RATIO
        ).values()
        for i, prefix in enumerate(folders):
            path = parts / f"{i}.zip"
            with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as out:
                for info in members:
                    if info.filename.startswith(prefix) and not info.is_dir():
                        with (
                            zf.open(info) as src,
                            out.open(info.filename[len(prefix) :], "w") as dst,
                        ):
                            shutil.copyfileobj(src, dst, 1 << 20)
            labels[path] = f"{sent}:{prefix}"
    zip_path.unlink()
    return labels


def _as_sent(err: InputError, labels: dict[Path, str]) -> InputError:
    """The error with each staged bundle named as sent (``s1.zip:capture.json``, ``plate.zip:station_01/capture.json``)."""
    file, reason = err.file, err.reason
    for path, label in labels.items():
        joined = label if label.endswith("/") else label + ":"
        file = file.replace(f"{path}:", joined).replace(str(path), label)
        reason = reason.replace(f"{path}:", joined).replace(str(path), label)
    return InputError(file, err.field, reason)


def station_rows(details: dict[str, Any] | None) -> list[StationOut]:
    """The stations of a result's details.json (its ``stations``), each with its overlap with the
    station before; empty for a plate measured in one view (or details without them)."""
    stitched = (details or {}).get("stations")
    if not isinstance(stitched, dict):
        return []
    seams = {
        tuple(o["stations"]): o
        for o in stitched.get("overlaps") or []
        if isinstance(o, dict) and len(o.get("stations") or []) == 2
    }
    rows = []
    for s in stitched.get("stations") or []:
        seam = seams.get((s["index"] - 1, s["index"])) or {}
        rows.append(
            StationOut(
                index=s["index"],
                travel_mm=s["travel_mm"],
                travel_encoder_mm=s["travel_encoder_mm"],
                outline_mm=s.get("footprint_mm"),
                overlap_matches=seam.get("matches"),
                overlap_rms_mm=seam.get("rms_mm"),
                overlap_max_mm=seam.get("max_mm"),
            )
        )
    return sorted(rows, key=lambda r: r.index)


def read_stations(artifacts_dir: Path, details: dict[str, Any] | None = None) -> list[StationOut]:
    """:func:`station_rows` of an artifact folder's details.json (``details`` when the caller has read
    it already); empty when it is missing or unreadable (the pages then show the plate without its
    stations)."""
    try:
        if details is None:
            doc = json.loads((Path(artifacts_dir) / "details.json").read_text(encoding="utf-8"))
            details = doc if isinstance(doc, dict) else None
        return station_rows(details)
    except (OSError, ValueError, KeyError, TypeError) as err:
        log.warning("%s: no stations read from details.json: %s", artifacts_dir, err)
        return []
