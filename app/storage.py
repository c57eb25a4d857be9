"""Layout of the data directory: uploads and artifacts on disk, one folder per record.

::

    <data_dir>/
      plate_inspect.db                 the database (default SQLite URL)
      huey.db                          the job queue
      staging/<random>/                an upload being validated (removed after)
      plates/<plate_id>/targets/<target_id>/target.json (+ mesh file)
      calibrations/<calibration_id>/calibration.json
      light-calibrations/<light_calibration_id>/lights.json
      inspections/<inspection_id>/inputs/     capture.zip (or bundle/ for a simulated one),
                                              target.json (+ mesh), simulation.json
      inspections/<inspection_id>/artifacts/  result.json and the pipeline's artifacts

Paths stored in the database are relative to the data dir (the dir can move).
"""

from __future__ import annotations

import re
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

#: A plate id as a regular expression: letters, digits, '.', '_', '-', starting with a letter or
#: digit, never '..' (plate ids become folder names). Written without look-ahead so that OpenAPI
#: clients (and the Rust regex engine of pydantic) read it; the length apart (``PLATE_ID_MAX_LENGTH``).
PLATE_ID_REGEX = r"^[A-Za-z0-9](?:\.?[A-Za-z0-9_-])*\.?$"
#: Longest plate id.
PLATE_ID_MAX_LENGTH = 64
_PLATE_ID = re.compile(PLATE_ID_REGEX)
#: Artifact names served over HTTP: one plain file name, no folders.
ARTIFACT_NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def check_plate_id(plate_id: str) -> str:
    """``plate_id`` if it is a valid plate id, else ValueError naming what is allowed."""
    if (
        not isinstance(plate_id, str)
        or len(plate_id) > PLATE_ID_MAX_LENGTH
        or not _PLATE_ID.match(plate_id)
    ):
        raise ValueError(
            f"plate_id: expected 1-{PLATE_ID_MAX_LENGTH} letters, digits, '.', '_' or '-' (starting with a letter or "
            f"digit, no '..'), got {plate_id!r}"
        )
    return plate_id


@dataclass(frozen=True)
class Storage:
    """The data directory of one service (see the module docstring for the layout)."""

    data_dir: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "data_dir", Path(self.data_dir).resolve())

    def ensure(self) -> None:
        """Create the top-level folders."""
        for sub in ("staging", "plates", "calibrations", "light-calibrations", "inspections"):
            (self.data_dir / sub).mkdir(parents=True, exist_ok=True)

    # ---------------------------------------------------------------- paths

    def relative(self, path: Path) -> str:
        """``path`` relative to the data dir, as stored in the database."""
        return Path(path).resolve().relative_to(self.data_dir).as_posix()

    def absolute(self, stored: str) -> Path:
        """The absolute path of a path stored in the database."""
        return self.data_dir / stored

    def new_staging_dir(self) -> Path:
        path = self.data_dir / "staging" / uuid.uuid4().hex
        path.mkdir(parents=True)
        return path

    @contextmanager
    def staging(self, *, folder: bool = True) -> Iterator[Staged]:
        """The files of one write before its rows are committed (see :class:`Staged`).

        ``folder``: make a staging folder for the upload (``Staged.dir``; None without). The
        folder is removed on leaving, whatever the service did not move into place.
        """
        staged = Staged(self, self.new_staging_dir() if folder else None)
        try:
            yield staged
        finally:
            self.remove(staged.dir)

    def target_dir(self, plate_id: str, target_id: int) -> Path:
        return self.data_dir / "plates" / check_plate_id(plate_id) / "targets" / str(int(target_id))

    def calibration_dir(self, calibration_id: int) -> Path:
        return self.data_dir / "calibrations" / str(int(calibration_id))

    def light_calibration_dir(self, light_calibration_id: int) -> Path:
        return self.data_dir / "light-calibrations" / str(int(light_calibration_id))

    def inspection_dir(self, inspection_id: int) -> Path:
        return self.data_dir / "inspections" / str(int(inspection_id))

    def inputs_dir(self, inspection_id: int) -> Path:
        return self.inspection_dir(inspection_id) / "inputs"

    def artifacts_dir(self, inspection_id: int) -> Path:
        return self.inspection_dir(inspection_id) / "artifacts"

    def artifact_path(self, inspection_id: int, name: str) -> Path | None:
        """The file of artifact ``name`` of an inspection, or None if there is no such file.

        Raises
        ------
        ValueError
            ``name`` is not a plain file name (folders and ``..`` are refused).
        """
        if not ARTIFACT_NAME_PATTERN.match(name) or ".." in name:
            raise ValueError(
                f"name: expected a plain file name (letters, digits, '.', '_', '-'), got {name!r}"
            )
        path = self.artifacts_dir(inspection_id) / name
        return path if path.is_file() else None

    # ---------------------------------------------------------------- moves

    def staging_copy(self, source: Path) -> Path:
        """A copy of folder ``source`` in a new staging folder."""
        path = self.data_dir / "staging" / uuid.uuid4().hex
        shutil.copytree(source, path)
        return path

    def adopt(self, staging: Path, destination: Path) -> Path:
        """Move a staging folder to its final place (which must not exist yet)."""
        if destination.exists():
            raise FileExistsError(f"storage: {destination} exists already")
        destination.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(staging), str(destination))
        return destination

    @staticmethod
    def remove(path: Path | None) -> None:
        """Remove a folder or file if it exists (used to undo a refused upload)."""
        if path is None:
            return
        path = Path(path)
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists():
            path.unlink()

    def clear_artifacts(self, inspection_id: int) -> Path:
        """An empty artifacts folder for a (re)run of an inspection."""
        out = self.artifacts_dir(inspection_id)
        self.remove(out)
        out.mkdir(parents=True)
        return out


@dataclass
class Staged:
    """A write's files: its upload's staging folder and the folders of the rows it created.

    :meth:`track` each row folder the write makes; :meth:`undo` (the write's cleanup when its rows
    are not committed) removes them with the staging folder, so a refused write leaves nothing.
    """

    storage: Storage
    dir: Path | None
    created: list[Path] = field(default_factory=list)

    @property
    def folder(self) -> Path:
        """The staging folder of a write staged with one (``Storage.staging(folder=True)``).

        Raises
        ------
        RuntimeError
            The write was staged without a folder.
        """
        if self.dir is None:
            raise RuntimeError("storage: this write was staged without a folder")
        return self.dir

    def track(self, folder: Path) -> None:
        self.created.append(folder)

    def undo(self) -> None:
        self.storage.remove(self.dir)
        for folder in self.created:
            self.storage.remove(folder)
