"""The inputs of the forming model: machine, material, target, passes and a plate's record.

All are small frozen dataclasses that check themselves when built: a bad value raises
:class:`~pipeline.formats.InputError` naming the record and the field (``"machine: bottom_roll_spacing_mm:
expected a positive finite number of mm, got -1"``), which the service answers with 422. ``from_dict``
reads the JSON shapes of issue 14::

    machine   {"kind": "three-roll-pyramid", "bottom_roll_spacing_mm": 1400, "bottom_roll_diameter_mm": 420,
               "top_roll_diameter_mm": 500}
    material  {"grade": "AH36", "thickness_mm": 20, "yield_mpa": 355, "youngs_mpa": 206000, "poisson": 0.3}
    pass      {"method": "roll-bending", "machine_id": "R3-01", "top_roll_displacement_mm": 97.0}

Units: mm, MPa (N/mm^2). Radii are unsigned (the plate is bent one way only).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from ..formats import InputError

if TYPE_CHECKING:
    from ..io import Target

MACHINE_KIND = "three-roll-pyramid"
PASS_METHOD = "roll-bending"
#: Which surface of the plate the target's and the inspection's radii describe (see FormingTarget).
SURFACES = ("convex", "concave", "mid")
VERDICTS = ("pass", "fail")


def _number(record: str, name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(record, name, f"expected a number, got {value!r}")
    return float(value)


def _positive(record: str, name: str, value: Any, unit: str) -> float:
    v = _number(record, name, value)
    if not (math.isfinite(v) and v > 0):
        raise InputError(
            record, name, f"expected a positive finite number of {unit}, got {value!r}"
        )
    return v


def _text(record: str, name: str, value: Any) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(record, name, f"expected a non-empty string, got {value!r}")
    return value


def _mapping(record: str, data: Any) -> Mapping[str, Any]:
    if not isinstance(data, Mapping):
        raise InputError(record, "", f"expected an object, got {type(data).__name__}")
    return data


def _known_keys(record: str, data: Mapping[str, Any], allowed: tuple[str, ...]) -> None:
    for key in data:
        if key not in allowed:
            raise InputError(
                record, str(key), f"unknown field (expected one of {', '.join(allowed)})"
            )


def _required(record: str, data: Mapping[str, Any], key: str) -> Any:
    if key not in data:
        raise InputError(record, key, "missing")
    return data[key]


@dataclass(frozen=True)
class Machine:
    """A three-roll pyramid bender.

    Attributes
    ----------
    machine_id : str
    bottom_roll_spacing_mm : float
        Distance between the two bottom rolls' axes, mm; more than a bottom roll's diameter.
    bottom_roll_diameter_mm : float
    top_roll_diameter_mm : float
    kind : str
        Only ``"three-roll-pyramid"``.
    """

    machine_id: str
    bottom_roll_spacing_mm: float
    bottom_roll_diameter_mm: float
    top_roll_diameter_mm: float
    kind: str = MACHINE_KIND

    def __post_init__(self) -> None:
        rec = "machine"
        _text(rec, "machine_id", self.machine_id)
        if self.kind != MACHINE_KIND:
            raise InputError(rec, "kind", f"expected {MACHINE_KIND!r}, got {self.kind!r}")
        for name in ("bottom_roll_spacing_mm", "bottom_roll_diameter_mm", "top_roll_diameter_mm"):
            object.__setattr__(self, name, _positive(rec, name, getattr(self, name), "mm"))
        if self.bottom_roll_spacing_mm <= self.bottom_roll_diameter_mm:
            raise InputError(
                rec,
                "bottom_roll_spacing_mm",
                f"expected more than the bottom rolls' diameter "
                f"({self.bottom_roll_diameter_mm:g} mm), got {self.bottom_roll_spacing_mm:g}",
            )

    @property
    def half_span_mm(self) -> float:
        """Half the bottom rolls' spacing, mm."""
        return 0.5 * self.bottom_roll_spacing_mm

    @property
    def bottom_roll_radius_mm(self) -> float:
        return 0.5 * self.bottom_roll_diameter_mm

    @property
    def top_roll_radius_mm(self) -> float:
        return 0.5 * self.top_roll_diameter_mm

    @classmethod
    def from_dict(cls, machine_id: str, data: Mapping[str, Any]) -> Machine:
        """Read a machine from its JSON object (issue 14's shape; ``kind`` required)."""
        data = _mapping("machine", data)
        keys = ("kind", "bottom_roll_spacing_mm", "bottom_roll_diameter_mm", "top_roll_diameter_mm")
        _known_keys("machine", data, keys)
        spacing, bottom, top = (_required("machine", data, k) for k in keys[1:])
        return cls(machine_id, spacing, bottom, top, kind=_required("machine", data, "kind"))


@dataclass(frozen=True)
class Material:
    """Nominal material of a plate (from its CAD/ERP record).

    Attributes
    ----------
    grade : str
        E.g. ``"AH36"``.
    thickness_mm : float
    yield_mpa : float
        Nominal (minimum) yield stress, uniaxial, MPa.
    youngs_mpa : float
        Young's modulus, MPa.
    poisson : float
        Poisson's ratio, in [0, 0.5).
    """

    grade: str
    thickness_mm: float
    yield_mpa: float
    youngs_mpa: float = 206000.0
    poisson: float = 0.3

    def __post_init__(self) -> None:
        rec = "material"
        _text(rec, "grade", self.grade)
        object.__setattr__(
            self, "thickness_mm", _positive(rec, "thickness_mm", self.thickness_mm, "mm")
        )
        object.__setattr__(self, "yield_mpa", _positive(rec, "yield_mpa", self.yield_mpa, "MPa"))
        object.__setattr__(self, "youngs_mpa", _positive(rec, "youngs_mpa", self.youngs_mpa, "MPa"))
        nu = _number(rec, "poisson", self.poisson)
        if not (0.0 <= nu < 0.5):
            raise InputError(rec, "poisson", f"expected a number in [0, 0.5), got {self.poisson!r}")
        object.__setattr__(self, "poisson", nu)
        if self.yield_mpa >= self.youngs_mpa:
            raise InputError(
                rec,
                "yield_mpa",
                f"expected less than youngs_mpa ({self.youngs_mpa:g}), got {self.yield_mpa:g}",
            )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Material:
        """Read a material from its JSON object (``youngs_mpa`` and ``poisson`` optional)."""
        data = _mapping("material", data)
        _known_keys(
            "material", data, ("grade", "thickness_mm", "yield_mpa", "youngs_mpa", "poisson")
        )
        optional = {k: data[k] for k in ("youngs_mpa", "poisson") if k in data}
        return cls(
            *(_required("material", data, k) for k in ("grade", "thickness_mm", "yield_mpa")),
            **optional,
        )


@dataclass(frozen=True)
class FormingTarget:
    """What a single-curvature plate is rolled to.

    Attributes
    ----------
    radius_mm : float
        Target radius of ``surface``.
    tolerance_mm : float
        The inspection's allowed absolute deviation (``Target.tolerance_mm``).
    width_mm : float
        Extent across the bend (the chord the inspection measures; ``Target.size_mm[0]``).
    length_mm : float
        Extent along the rolls (the cylinder's axis; ``Target.size_mm[1]``); the rolls' force scales with it.
    material : Material
    surface : {"convex", "concave", "mid"}
        The surface whose radius the target and the inspections give: ``"convex"`` (the cameras look at
        the convex side, the demo cell's default), ``"concave"``, or the mid-surface. The model bends
        the mid-surface; radii are converted with half the thickness.
    """

    radius_mm: float
    tolerance_mm: float
    width_mm: float
    length_mm: float
    material: Material
    surface: Literal["convex", "concave", "mid"] = "convex"

    def __post_init__(self) -> None:
        rec = "target"
        for name in ("radius_mm", "tolerance_mm", "width_mm", "length_mm"):
            object.__setattr__(self, name, _positive(rec, name, getattr(self, name), "mm"))
        if not isinstance(self.material, Material):
            raise InputError(
                rec, "material", f"expected a Material, got {type(self.material).__name__}"
            )
        if self.surface not in SURFACES:
            raise InputError(
                rec, "surface", f"expected one of {', '.join(SURFACES)}, got {self.surface!r}"
            )
        if self.mid_radius_mm(self.radius_mm) <= 0.5 * self.material.thickness_mm:
            raise InputError(
                rec,
                "radius_mm",
                f"expected a radius whose inner surface is more than 0 "
                f"(thickness {self.material.thickness_mm:g} mm), got {self.radius_mm:g}",
            )

    def mid_radius_mm(self, surface_radius_mm: float) -> float:
        """The mid-surface radius of a plate whose ``surface`` has this radius (``inf`` stays ``inf``)."""
        half = 0.5 * self.material.thickness_mm
        return (
            surface_radius_mm - half
            if self.surface == "convex"
            else (surface_radius_mm + half if self.surface == "concave" else surface_radius_mm)
        )

    def surface_radius_mm(self, mid_radius_mm: float) -> float:
        """The radius of ``surface`` on a plate whose mid-surface has this radius."""
        half = 0.5 * self.material.thickness_mm
        return (
            mid_radius_mm + half
            if self.surface == "convex"
            else (mid_radius_mm - half if self.surface == "concave" else mid_radius_mm)
        )

    @classmethod
    def from_target(
        cls,
        target: Target,
        material: Material | Mapping[str, Any] | None,
        surface: Literal["convex", "concave", "mid"] = "convex",
    ) -> FormingTarget:
        """From an inspection target (:class:`pipeline.io.Target`, a cylinder) and its material.

        Raises
        ------
        InputError
            Not a cylinder, or no material (field ``material``: the model needs thickness and yield).
        """
        if getattr(target, "shape", None) != "cylinder" or target.radius_mm is None:
            raise InputError(
                "target",
                "shape",
                f"roll bending makes cylinders, got {getattr(target, 'shape', None)!r}",
            )
        if material is None:
            raise InputError(
                "target",
                "material",
                "missing: roll-bending advice needs the plate's grade, thickness and yield",
            )
        if not isinstance(material, Material):
            material = Material.from_dict(material)
        width, length = target.size_mm
        return cls(target.radius_mm, target.tolerance_mm, width, length, material, surface)


@dataclass(frozen=True)
class RollPass:
    """One pass through the bender and, optionally, the inspection after it.

    Attributes
    ----------
    machine_id : str
    top_roll_displacement_mm : float
        How far the top roll moved down from touching the flat plate on the bottom rolls, mm.
    measured_radius_mm : float or None
        The inspected radius after the pass (of the target's ``surface``); ``inf`` for a flat plate;
        None when the plate was not inspected after this pass.
    verdict : {"pass", "fail"} or None
        The inspection's verdict, when known.
    radius_uncertainty_mm : float or None
        The inspection's *standard* uncertainty of ``measured_radius_mm`` (its expanded uncertainty
        ``uncertainty.radius_mm`` of result.json divided by the coverage factor ``k``), mm; None when the
        inspection did not report one (the model then takes its constant, ``Priors.radius_noise``).
    capable : bool
        False when the inspection said it is not capable for the plate's tolerance (a warning of
        result.json with the words "not capable"); the fit then weighs it by at least the uncertainty
        of a measurement at the capability limit (:func:`.learning.inspection_variance`).
    flipped : bool
        A reverse pass: the plate was turned over and rolled to open it. Its displacement is measured
        as for a bending pass (down from touching a flat plate) and may be negative: the top roll stops
        above that point, pressing the flipped plate's arch flatter (:mod:`.reverse`).
    """

    machine_id: str
    top_roll_displacement_mm: float
    measured_radius_mm: float | None = None
    verdict: Literal["pass", "fail"] | None = None
    radius_uncertainty_mm: float | None = None
    capable: bool = True
    flipped: bool = False

    def __post_init__(self) -> None:
        rec = "pass"
        _text(rec, "machine_id", self.machine_id)
        if not isinstance(self.flipped, bool):
            raise InputError(rec, "flipped", f"expected true or false, got {self.flipped!r}")
        d = _number(rec, "top_roll_displacement_mm", self.top_roll_displacement_mm)
        if not self.flipped:
            d = _positive(rec, "top_roll_displacement_mm", d, "mm")
        elif not math.isfinite(d):
            raise InputError(
                rec, "top_roll_displacement_mm", f"expected a finite number of mm, got {d!r}"
            )
        object.__setattr__(self, "top_roll_displacement_mm", d)
        if self.radius_uncertainty_mm is not None:
            object.__setattr__(
                self,
                "radius_uncertainty_mm",
                _positive(rec, "radius_uncertainty_mm", self.radius_uncertainty_mm, "mm"),
            )
        if not isinstance(self.capable, bool):
            raise InputError(rec, "capable", f"expected true or false, got {self.capable!r}")
        if self.measured_radius_mm is not None:
            r = _number(rec, "measured_radius_mm", self.measured_radius_mm)
            if not r > 0 or math.isnan(r):
                raise InputError(
                    rec,
                    "measured_radius_mm",
                    f"expected a positive number of mm (inf for flat), got {self.measured_radius_mm!r}",
                )
            object.__setattr__(self, "measured_radius_mm", r)
        if self.verdict is not None and self.verdict not in VERDICTS:
            raise InputError(
                rec,
                "verdict",
                f"expected one of {', '.join(VERDICTS)} or null, got {self.verdict!r}",
            )
        if self.verdict is not None and self.measured_radius_mm is None:
            raise InputError(
                rec, "measured_radius_mm", "missing: a verdict needs the inspected radius"
            )

    @property
    def inspected(self) -> bool:
        return self.measured_radius_mm is not None

    @classmethod
    def from_dict(
        cls,
        data: Mapping[str, Any],
        *,
        measured_radius_mm: float | None = None,
        verdict: Literal["pass", "fail"] | None = None,
        result: Mapping[str, Any] | None = None,
    ) -> RollPass:
        """Read a pass from its JSON object (issue 14's shape, optional ``"flipped": true``) plus the
        inspection after it: its radius, verdict, and the uncertainty and capability its result
        document (``plate-result/1``) reports (:func:`inspection_quality`)."""
        data = _mapping("pass", data)
        _known_keys("pass", data, ("method", "machine_id", "top_roll_displacement_mm", "flipped"))
        if _required("pass", data, "method") != PASS_METHOD:
            raise InputError("pass", "method", f"expected {PASS_METHOD!r}, got {data['method']!r}")
        u, capable = inspection_quality(result or {})
        return cls(
            _required("pass", data, "machine_id"),
            _required("pass", data, "top_roll_displacement_mm"),
            measured_radius_mm,
            verdict,
            radius_uncertainty_mm=u,
            capable=capable,
            flipped=data.get("flipped", False),
        )


#: The words of a result's warning that says the measurement is not capable for the tolerance.
NOT_CAPABLE = "not capable"


def inspection_quality(result: Mapping[str, Any]) -> tuple[float | None, bool]:
    """The standard uncertainty of an inspection's radius and whether it is capable, from its result.

    Parameters
    ----------
    result : mapping
        A ``plate-result/1`` document (or the part of it kept): optional ``"uncertainty": {"k": 2,
        "radius_mm": U, ...}`` (expanded uncertainty, coverage factor ``k``) and ``"warnings"``.

    Returns
    -------
    radius_uncertainty_mm : float or None
        ``U / k``, mm; None when the result has no radius uncertainty (older results).
    capable : bool
        False when a warning says "not capable" (case-insensitive).

    Raises
    ------
    InputError
        An uncertainty that is not an object with a positive ``k`` and a positive (or null) radius.
    """
    result = _mapping("result", result)
    warnings = result.get("warnings") or []
    capable = not any(isinstance(w, str) and NOT_CAPABLE in w.lower() for w in warnings)
    block = result.get("uncertainty")
    if block is None:
        return None, capable
    block = _mapping("result.uncertainty", block)
    radius = block.get("radius_mm")
    if radius is None:
        return None, capable
    k = _positive("result.uncertainty", "k", block.get("k", 2), "(coverage factor)")
    return _positive("result.uncertainty", "radius_mm", radius, "mm") / k, capable


@dataclass(frozen=True)
class PlateRecord:
    """A plate: its target and its passes so far, oldest first (the plate starts flat).

    Attributes
    ----------
    plate_id : str
    target : FormingTarget
    passes : tuple of RollPass
    """

    plate_id: str
    target: FormingTarget
    passes: tuple[RollPass, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        _text("plate", "plate_id", self.plate_id)
        if not isinstance(self.target, FormingTarget):
            raise InputError(
                "plate", "target", f"expected a FormingTarget, got {type(self.target).__name__}"
            )
        passes = tuple(self.passes)
        for i, p in enumerate(passes):
            if not isinstance(p, RollPass):
                raise InputError(
                    "plate", f"passes[{i}]", f"expected a RollPass, got {type(p).__name__}"
                )
        object.__setattr__(self, "passes", passes)

    @property
    def group(self) -> tuple[str, float]:
        """(grade, thickness rounded to 0.1 mm): plates whose yield is pooled."""
        return (
            self.target.material.grade.strip().upper(),
            round(self.target.material.thickness_mm, 1),
        )

    def with_pass(self, roll_pass: RollPass) -> PlateRecord:
        """The same plate with one more pass."""
        return PlateRecord(self.plate_id, self.target, (*self.passes, roll_pass))

    @property
    def forward(self) -> PlateRecord:
        """The same plate with its passes before its first reverse (flipped) pass: what the bending
        model (:mod:`.rolling`, :mod:`.learning`) describes."""
        flipped = [i for i, q in enumerate(self.passes) if q.flipped]
        if not flipped:
            return self
        return PlateRecord(self.plate_id, self.target, self.passes[: flipped[0]])
