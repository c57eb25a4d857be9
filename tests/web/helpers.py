"""Helpers of the dashboard tests: inspections seeded in the database as a job would leave them;
the fixtures are in conftest.py.
"""

from __future__ import annotations

import json

import numpy as np

from tests.web.plates import write_artifacts


def seed_done_inspection(
    app,
    *,
    plate_id: str = "H1-P01",
    measured_radius_mm: float = 5050.0,
    uncertainty: dict[str, float] | None = None,
) -> int:
    """A done inspection of ``plate_id`` whose artifacts are an analytic cylinder pair."""
    from app.services import inspections as svc
    from app.services import leases

    with app.state.session_factory() as session:
        row = svc.create_simulated_inspection(
            session=session,
            storage=app.state.storage,
            plate_id=plate_id,
            simulation=_simulation(),
        )
        inspection_id = row.id
        session.commit()
        assert leases.claim(session=session, inspection_id=inspection_id)
        folder = write_artifacts(
            app.state.storage.artifacts_dir(inspection_id),
            plate_id=plate_id,
            measured_radius_mm=measured_radius_mm,
            uncertainty=uncertainty,
        )
        leases.mark_done(
            session=session,
            inspection_id=inspection_id,
            document=json.loads((folder / "result.json").read_text()),
        )
        session.commit()
    return inspection_id


def seed_queued_inspection(app, *, plate_id: str = "H1-P02") -> int:
    from app.services import inspections as svc

    with app.state.session_factory() as session:
        row = svc.create_simulated_inspection(
            session=session,
            storage=app.state.storage,
            plate_id=plate_id,
            simulation=_simulation(),
        )
        session.commit()
        return row.id


def _simulation() -> dict:
    from app.schemas import SimulatedInspectionIn

    return SimulatedInspectionIn(shape="cylinder", radius_mm=5000.0, tolerance_mm=2.0).model_dump(
        mode="json"
    )


def ring_of_lights(n: int = 8, *, radius_mm: float = 1616.58, height_mm: float = 200.0) -> dict:
    """A light-calibration/1 document: ``n`` LEDs on a ring around the cameras, aimed at a plate 2.8 m away."""
    from pipeline.io import light_calibration_document
    from pipeline.lights.model import Lights

    angles = np.arange(n) * 2 * np.pi / n
    positions = np.stack(
        [radius_mm * np.cos(angles), radius_mm * np.sin(angles), np.full(n, height_mm)], axis=1
    )
    axes = np.array([0.0, 0.0, 2800.0]) - positions
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    lights = Lights.points(positions, np.linspace(9.5, 10.5, n), axes=axes, mu=np.full(n, 1.5))
    return light_calibration_document(lights, 0.0042)
