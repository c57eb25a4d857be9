"""Helpers of the dashboard tests: inspections seeded in the database as a job would leave them;
the fixtures are in conftest.py.
"""

from __future__ import annotations

import json

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
