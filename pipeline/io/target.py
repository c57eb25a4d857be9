"""plate-target/1: parametric targets and mesh targets."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..formats import (
    TARGET_FORMAT,
    InputError,
    TargetFile,
)
from .bundle import _check_relative
from .jsonfile import read_json
from .validation import _validate

MESH_SUFFIXES = (".stl", ".ply", ".obj")


@dataclass(frozen=True)
class Target:
    """The CAD target of a plate (``plate-target/1``).

    Attributes
    ----------
    shape : {"plane", "cylinder", "sphere", "mesh"}
    radius_mm : float or None
        Cylinder or sphere radius; None for plane and mesh.
    size_mm : (float, float)
        Plate size; a cylinder's axis runs along the second size axis.
    tolerance_mm : float
        Allowed absolute deviation.
    mesh_vertices_mm : (V, 3) float64 or None
        For ``mesh``: vertices in the target's own frame, mm.
    mesh_faces : (F, 3) int64 or None
    source : Path or None
    """

    shape: str
    radius_mm: float | None
    size_mm: tuple[float, float]
    tolerance_mm: float
    mesh_vertices_mm: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None
    source: Path | None = None


def load_target(
    source: str | os.PathLike[str] | dict[str, Any],
    *,
    base_dir: str | os.PathLike[str] | None = None,
    file_label: str | None = None,
) -> Target:
    """Read a ``plate-target/1`` document.

    Parameters
    ----------
    source : str, Path or dict
        A path to target.json, or the parsed object.
    base_dir : str or Path, optional
        Folder that a ``mesh`` shape's ``file`` is relative to (default: the
        folder of ``source`` when it is a path; required for a mesh given as a dict).
    file_label : str, optional
        How error messages name the document (default: the path, or
        ``"target.json"`` for a dict).

    Returns
    -------
    Target
        For ``mesh``: vertices (V, 3) float64 in mm in the target's own frame
        and faces (F, 3) int64, read with trimesh (STL, PLY or OBJ; several
        bodies are concatenated).

    Raises
    ------
    InputError
        Unreadable file, unknown format or shape type, unknown or missing keys,
        non-finite or non-positive sizes; a mesh file that is missing, leaves
        ``base_dir``, has an unknown type, cannot be read, or holds no triangles.
    """
    if isinstance(source, dict):
        doc, label, src = source, file_label or "target.json", None
    elif isinstance(source, (str, os.PathLike)):
        src = Path(source)
        label = file_label or str(src)
        doc = read_json(src, label=label)
        if base_dir is None:
            base_dir = src.parent
    else:
        raise TypeError(f"source: expected a path or a dict, got {type(source).__name__}")
    tgt = _validate(TargetFile, doc, label=label, expected_format=TARGET_FORMAT)
    shape = tgt.shape
    vertices = faces = None
    if shape.type == "mesh":
        if base_dir is None:
            reason = f"{shape.file!r}: a target given as an object needs base_dir to find its mesh"
            raise InputError(label, "shape.file", reason)
        vertices, faces = _load_mesh(Path(base_dir), shape.file, label=label)
    return Target(
        shape=shape.type,
        radius_mm=float(shape.radius_mm) if shape.type in ("cylinder", "sphere") else None,
        size_mm=(float(tgt.size_mm[0]), float(tgt.size_mm[1])),
        tolerance_mm=float(tgt.tolerance_mm),
        mesh_vertices_mm=vertices,
        mesh_faces=faces,
        source=src,
    )


def _load_mesh(base_dir: Path, name: str, *, label: str) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    field = "shape.file"
    rel = _check_relative(name, label=label, field=field)
    suffix = Path(rel).suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(
            label,
            field,
            f"{name!r}: expected an STL, PLY or OBJ file, got {suffix or 'no extension'!r}",
        )
    path = base_dir / rel
    if not path.resolve().is_relative_to(base_dir.resolve()):
        raise InputError(label, field, f"{name!r} leaves the target's folder (through a symlink)")
    if not path.is_file():
        raise InputError(label, field, f"{name!r}: file not found in {base_dir}")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on bad files
        raise InputError(label, field, f"{name!r}: cannot read the mesh: {exc}") from None
    vertices = np.asarray(getattr(mesh, "vertices", np.empty((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.empty((0, 3))), dtype=np.int64)
    if faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        count = faces.shape[0] if faces.ndim == 2 else 0
        raise InputError(label, field, f"{name!r}: expected a triangle mesh, got {count} triangles")
    if not np.all(np.isfinite(vertices)):
        raise InputError(label, field, f"{name!r}: vertices hold non-finite coordinates")
    return vertices, faces
