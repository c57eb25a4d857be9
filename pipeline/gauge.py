"""A type-1 gauge study (VDA 5 / AIAG MSA): the inspection repeated on one plate, its capability.

The same plate is measured ``n`` times (n >= 25 for a study that counts): on the simulated cell each
repeat renders it afresh (new sensor noise, paint and light intensities, the same geometry), or
``n`` capture bundles of one real plate are given. For each characteristic -- the radius, and the
deviation at fixed points of the plate (a small patch around each, in the target's frame) -- the
study prints the mean, the standard deviation ``s``, the bias against the reference (the true
radius and zero deviation for a simulated plate formed exactly; for bundles the target's own radius
and zero, which is only right for a plate known to be formed to its target), and

    Cg  = 0.2 T / (6 s)                      (the gauge's spread within 20 % of the tolerance)
    Cgk = (0.1 T - |mean - reference|) / (3 s)

with ``T`` the characteristic's tolerance: ``2 tol`` for a deviation (``+/- tol``), and for the
radius the change of radius that moves the plate's edges by ``tol`` (``T = 2 * 8 R^2 tol / w^2``
over the plate's curved width ``w``). A capable gauge has Cg and Cgk >= 1.33. Beside them: the
mean expanded uncertainty the inspections reported (k = 2) against twice the observed ``s``, and
how often the reported ``U`` covered the error.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .artifacts import ARTIFACT_FILES
from .artifacts.ply import read_surface_ply
from .io import load_target

#: Capability indices at or above this make a capable gauge (VDA 5, AIAG MSA).
CAPABLE_INDEX = 1.33
#: Radius (mm) of the patch around a fixed point whose mean deviation is the point's reading.
PATCH_MM = 40.0
#: Fixed points, as fractions of the target's half sizes (a 3 x 3 grid inside the plate).
POINTS = tuple((fx, fy) for fy in (-0.6, 0.0, 0.6) for fx in (-0.6, 0.0, 0.6))


@dataclass(frozen=True)
class Characteristic:
    """One characteristic of the study: readings, their reported expanded uncertainties, its figures."""

    name: str
    reference: float
    tolerance: float
    values: np.ndarray
    reported_u: np.ndarray

    @property
    def mean(self) -> float:
        return float(np.mean(self.values))

    @property
    def sd(self) -> float:
        return float(np.std(self.values, ddof=1)) if len(self.values) > 1 else float("nan")

    @property
    def cg(self) -> float:
        return 0.2 * self.tolerance / (6.0 * self.sd) if self.sd > 0 else float("inf")

    @property
    def cgk(self) -> float:
        bias = abs(self.mean - self.reference)
        return (0.1 * self.tolerance - bias) / (3.0 * self.sd) if self.sd > 0 else float("inf")

    @property
    def covered(self) -> int:
        """Readings whose error against the reference lies within their reported U."""
        return int(np.sum(np.abs(self.values - self.reference) <= self.reported_u))


@dataclass(frozen=True)
class GaugeStudy:
    """The study's characteristics (the radius first, when the target has one), and its repeats."""

    characteristics: list[Characteristic]
    n: int
    label: str

    def table(self) -> str:
        """The study as a Markdown table."""
        lines = [
            f"Type-1 gauge study: {self.label}, n = {self.n}",
            "",
            "| characteristic | reference | T | mean | s | Cg | Cgk | mean U (k=2) | 2 s | U covered |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for c in self.characteristics:
            lines.append(
                f"| {c.name} | {c.reference:.3f} | {c.tolerance:.3f} | {c.mean:.3f} | {c.sd:.4f} | "
                f"{c.cg:.2f} | {c.cgk:.2f} | {float(np.mean(c.reported_u)):.3f} | {2 * c.sd:.3f} | "
                f"{c.covered}/{len(c.values)} |"
            )
        worst = min(min(c.cg, c.cgk) for c in self.characteristics)
        verdict = "capable" if worst >= CAPABLE_INDEX else "NOT capable"
        lines += ["", f"lowest index {worst:.2f}: {verdict} (Cg, Cgk >= {CAPABLE_INDEX})"]
        return "\n".join(lines)


def bundles_study(
    bundles: Sequence[str | Path],
    target: str | Path,
    *,
    workdir: str | Path,
    inspect: Callable[..., Any] | None = None,
) -> GaugeStudy:
    """The study of ``n`` capture bundles of one real plate (measured here into ``workdir``).

    The reference is the target: right only for a plate known to be formed to it (a master plate).
    """
    from .io import load_capture
    from .run import inspect as run_inspect

    measure = inspect or run_inspect
    outs = []
    K = None
    for i, bundle in enumerate(bundles):
        cap = load_capture(bundle)
        K = cap.rig.left.K if K is None else K
        out = Path(workdir) / f"result-{i:03d}"
        measure(cap, target, out_dir=out)
        outs.append(out)
    if K is None:
        raise ValueError("bundles: expected at least 2 capture bundles, got none")
    return study(outs, target, K, label=f"{len(outs)} capture bundles of one plate")


def study(
    results: Sequence[Path],
    target: dict[str, Any] | str | Path,
    K: np.ndarray,
    *,
    reference_radius_mm: float | None = None,
    label: str = "",
) -> GaugeStudy:
    """The study of inspections already made of one plate (their output folders).

    Parameters
    ----------
    results : sequence of Path
        Output folders of :func:`pipeline.run.inspect` (``result.json``, ``details.json`` and
        ``surface.ply`` in each), all of one plate.
    target : dict or path
        The plate's ``plate-target/1``.
    K : (3, 3) float
        Intrinsics of the undistorted left camera that took them, px.
    reference_radius_mm : float, optional
        The radius's reference value (default: the target's radius).
    label : str

    Returns
    -------
    GaugeStudy

    Raises
    ------
    ValueError
        Fewer than 2 results, or a result that is not a measured plate.
    """
    import json

    if len(results) < 2:
        raise ValueError(f"results: expected at least 2 inspections, got {len(results)}")
    tgt = load_target(target)
    docs = [json.loads((Path(r) / "result.json").read_text()) for r in results]
    for r, doc in zip(results, docs, strict=True):
        if doc.get("verdict") == "error" or doc.get("uncertainty") is None:
            raise ValueError(
                f"{Path(r) / 'result.json'}: verdict, uncertainty: expected a measured plate with its uncertainty"
            )
    characteristics = []
    if docs[0]["radius_mm"] is not None:
        radius_ref = reference_radius_mm or float(docs[0]["target_radius_mm"])
        width = float(min(tgt.size_mm))
        t_radius = 2.0 * 8.0 * radius_ref**2 * tgt.tolerance_mm / width**2
        characteristics.append(
            Characteristic(
                name="radius mm",
                reference=radius_ref,
                tolerance=t_radius,
                values=np.array([d["radius_mm"] for d in docs], dtype=np.float64),
                reported_u=np.array([d["uncertainty"]["radius_mm"] for d in docs], np.float64),
            )
        )
    readings = np.array([_point_readings(Path(r), tgt.size_mm, K) for r in results])  # (n, P, 2)
    for j, (fx, fy) in enumerate(POINTS):
        x, y = fx * tgt.size_mm[0] / 2.0, fy * tgt.size_mm[1] / 2.0
        characteristics.append(
            Characteristic(
                name=f"deviation at ({x:+.0f}, {y:+.0f}) mm",
                reference=0.0,
                tolerance=2.0 * tgt.tolerance_mm,
                values=readings[:, j, 0],
                reported_u=readings[:, j, 1],
            )
        )
    return GaugeStudy(characteristics=characteristics, n=len(results), label=label)


def _point_readings(out: Path, size_mm: tuple[float, float], K: np.ndarray) -> np.ndarray:
    """(P, 2): mean deviation and mean expanded uncertainty (mm) in a patch around each fixed point.

    The surface's vertices (surface.ply, with their deviation) are taken to the target's frame with
    details.json's registration; each vertex's uncertainty is the per-point map's (uncertainty.npy)
    at its pixel (``K``: the undistorted left camera's intrinsics).
    """
    import json

    details = json.loads((out / ARTIFACT_FILES["details"]).read_text())
    T = np.asarray(details["T_cam_target"], dtype=np.float64)
    verts, _, dev = read_surface_ply(out / ARTIFACT_FILES["surface"])
    local = (verts - T[:3, 3]) @ T[:3, :3]  # camera -> target frame
    u_at = _uncertainty_at(verts, np.load(out / ARTIFACT_FILES["uncertainty"]), K)
    rows = []
    for fx, fy in POINTS:
        x, y = fx * size_mm[0] / 2.0, fy * size_mm[1] / 2.0
        near = (np.hypot(local[:, 0] - x, local[:, 1] - y) <= PATCH_MM) & np.isfinite(dev)
        if not near.any():
            rows.append((math.nan, math.nan))
            continue
        rows.append((float(np.mean(dev[near])), float(np.nanmean(u_at[near]))))
    return np.array(rows)


def _uncertainty_at(verts: np.ndarray, u_map: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The per-point uncertainty map's value at each vertex's pixel (the vertex projected with ``K``)."""
    h, w = u_map.shape
    z = np.where(verts[:, 2] > 0, verts[:, 2], np.nan)
    u = np.rint(K[0, 0] * verts[:, 0] / z + K[0, 2])
    v = np.rint(K[1, 1] * verts[:, 1] / z + K[1, 2])
    ok = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    out = np.full(len(verts), np.nan)
    out[ok] = u_map[v[ok].astype(np.int64), u[ok].astype(np.int64)]
    return out


def simulated_study(
    *,
    n: int = 25,
    width: int = 1224,
    height: int = 1024,
    n_lights: int = 12,
    near_field_mm: float | None = None,
    specular: float = 0.0,
    seed: int = 0,
    workdir: str | Path | None = None,
    inspect: Callable[..., Any] | None = None,
) -> GaugeStudy:
    """The study on the simulated cell: one plate formed exactly (the simulator's default cylinder),
    rendered ``n`` times with fresh noise, paint and light intensities, each measured by ``inspect``.

    Parameters
    ----------
    n : int
        Repeats (>= 2; a study that counts has >= 25).
    width, height : int
        Image size, px.
    n_lights : int
    near_field_mm : float or None
        LEDs this high above the plate with their positions in the capture (the real cell's lights);
        None: distant lights.
    specular : float
        A glossy coating: the specular lobe's strength against the diffuse light (0: matte; see
        :class:`pipeline.simulate.CaptureSpec`).
    seed : int
        First seed of the repeats.
    workdir : path, optional
        Where the bundles and results go (default: a temporary folder, removed afterwards).
    inspect : callable, optional
        :func:`pipeline.run.inspect` (a parameter so that tests may pass a stand-in).

    Returns
    -------
    GaugeStudy
    """
    from .run import inspect as run_inspect
    from .simulate import CaptureSpec, PlateSpec, default_rig, simulate_capture

    if n < 2:
        raise ValueError(f"n: expected at least 2 repeats, got {n}")
    measure = inspect or run_inspect
    plate = PlateSpec()
    spec = CaptureSpec(
        width=width,
        height=height,
        n_lights=n_lights,
        near_field_mm=near_field_mm,
        led_mu=1.0 if near_field_mm else 0.0,
        specular=specular,
    )
    cell = "near-field LEDs (positions given)" if near_field_mm else "distant lights"
    gloss = f", glossy (specular {specular:g})" if specular else ""
    label = f"simulated cell, {width}x{height}, {n_lights} lights, {cell}{gloss}, cylinder R {plate.radius_mm:g} mm"
    with tempfile.TemporaryDirectory(prefix="plate-inspect-gauge-") as tmp:
        root = Path(workdir) if workdir is not None else Path(tmp)
        outs, K = [], default_rig(width=width, height=height).left.K
        for i in range(n):
            bundle = simulate_capture(
                root / f"capture-{i:03d}", plate=plate, capture=spec, seed=seed + i
            )
            out = root / f"result-{i:03d}"
            measure(bundle, bundle / "target.json", out_dir=out)
            outs.append(out)
        return study(
            outs,
            root / "capture-000" / "target.json",
            K,
            reference_radius_mm=plate.radius_mm,
            label=label,
        )
