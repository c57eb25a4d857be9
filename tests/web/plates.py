"""Synthetic inspection artifacts for the dashboard tests (analytic cylinders, no pipeline run)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh


def cylinder_grid(
    *,
    radius_mm: float,
    size_mm: tuple[float, float],
    n: tuple[int, int],
    depth_mm: float = 3000.0,
    convex: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A cylinder patch seen by the left camera: axis along camera y, apex at (0, 0, depth).

    Returns vertices (V, 3) mm in the camera frame, faces (F, 3), and the plate
    coordinates (V, 2) mm (u across the curvature, v along the axis).
    """
    u = np.linspace(-size_mm[0] / 2, size_mm[0] / 2, n[0])
    v = np.linspace(-size_mm[1] / 2, size_mm[1] / 2, n[1])
    uu, vv = np.meshgrid(u, v)  # (n1, n0)
    sag = radius_mm - np.sqrt(radius_mm**2 - uu**2)
    # Convex: the middle bulges towards the cameras (smaller z).
    z = depth_mm + (sag if convex else -sag)
    vertices = np.stack([uu, vv, z], axis=-1).reshape(-1, 3)
    rows, cols = uu.shape
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate(
        [np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)]
    )
    return vertices, faces, np.stack([uu, vv], -1).reshape(-1, 2)


def write_artifacts(
    out_dir: Path,
    *,
    plate_id: str = "H1-P01",
    radius_mm: float = 5000.0,
    measured_radius_mm: float = 5050.0,
    size_mm: tuple[float, float] = (3000.0, 2000.0),
    n: tuple[int, int] = (61, 41),
    tolerance_mm: float = 2.0,
    uncertainty: dict[str, float] | None = None,
) -> Path:
    """Write result.json, surface.ply (with ``deviation_mm``) and target.ply for a cylinder plate.

    The measured surface is a cylinder of ``measured_radius_mm`` touching the target at
    its apex; its deviation is exact (measured minus target along -z, the cameras' side
    positive), so sections and colours can be checked against it.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tv, tf, _ = cylinder_grid(radius_mm=radius_mm, size_mm=size_mm, n=n)
    mv, mf, _ = cylinder_grid(radius_mm=measured_radius_mm, size_mm=size_mm, n=n)
    deviation = (
        tv[:, 2] - mv[:, 2]
    )  # same (x, y) grid: positive where the measured lies nearer the cameras
    surface = trimesh.Trimesh(mv, mf, process=False)
    surface.vertex_attributes["deviation_mm"] = deviation.astype(np.float32)
    (out_dir / "surface.ply").write_bytes(
        trimesh.exchange.ply.export_ply(surface, include_attributes=True)
    )
    (out_dir / "target.ply").write_bytes(
        trimesh.exchange.ply.export_ply(trimesh.Trimesh(tv, tf, process=False))
    )
    max_abs = float(np.abs(deviation).max())
    document = {
        "format": "plate-result/1",
        "plate_id": plate_id,
        "radius_mm": measured_radius_mm,
        "principal_radii_mm": [measured_radius_mm, None],
        "target_radius_mm": radius_mm,
        "radius_error_pct": 100.0 * (measured_radius_mm - radius_mm) / radius_mm,
        "deviation_mm": {
            "rms": float(np.sqrt(np.mean(deviation**2))),
            "max_abs": max_abs,
            "p95": max_abs,
        },
        "tolerance_mm": tolerance_mm,
        "within_tolerance_pct": float(100.0 * np.mean(np.abs(deviation) <= tolerance_mm)),
        "verdict": "pass" if max_abs <= tolerance_mm else "fail",
        "timings_s": {"total": 1.0},
        "artifacts": {"surface": "surface.ply", "target_surface": "target.ply"},
    }
    if uncertainty is not None:
        document["uncertainty"] = uncertainty
    (out_dir / "result.json").write_text(json.dumps(document, indent=2))
    return out_dir
