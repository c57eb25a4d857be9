"""The Calibration page's light calibration and the result page's warnings (HTML of a real app)."""

from __future__ import annotations

import json
import re

from fastapi.testclient import TestClient

from tests.web.helpers import ring_of_lights, seed_done_inspection

APPLIED = "a light calibration was applied to the capture's nominal light directions"


def seed_light_calibration(
    app, document: dict, *, file_name: str | None = "cell-lights.json"
) -> int:
    from app.services import light_calibrations as svc

    storage = app.state.storage
    staging = storage.new_staging_dir()
    (staging / svc.LIGHT_CALIBRATION_FILE).write_text(json.dumps(document), encoding="utf-8")
    with app.state.session_factory() as session:
        row = svc.create_light_calibration(
            session=session, storage=storage, staging_dir=staging, file_name=file_name
        )
        session.commit()
        return row.id


def test_calibration_page_shows_the_current_light_calibration(demo_app):
    with TestClient(demo_app) as client:
        html = client.get("/calibration").text
        assert "No light calibration uploaded yet" in html and 'id="light-calibration-form"' in html
        assert 'id="light-table"' not in html

        seed_light_calibration(demo_app, ring_of_lights(6))
        newest = seed_light_calibration(demo_app, ring_of_lights(8))
        html = client.get("/calibration").text
        table = html[
            html.index('id="light-table"') : html.index("</table>", html.index('id="light-table"'))
        ]
        rows = re.findall(r"<tr>\s*<td>(\d+)</td>(.*?)</tr>", table, re.S)
        assert [int(k) for k, _ in rows] == list(
            range(8)
        )  # the current (newest) one, in image order
        first = re.findall(r'<td class="num">([^<]*)</td>', rows[0][1])
        # position in mm with one decimal, axis, mu, intensity
        assert first == ["1616.6", "0.0", "200.0", "-0.53, 0.00, 0.85", "1.50", "9.500"], first
        assert "-0.0<" not in table and "-0.00," not in table  # no negative zeros
        assert f"(#{newest})" in html and "cell-lights.json" in html and "0.0042" in html
        # the plan view: one marker per light, drawn on the server
        assert html.count('<circle class="light"') == 8
        # both calibrations in the history
        assert html.count("<td>cell-lights.json</td>") == 2


def test_result_page_shows_the_warnings_and_the_light_calibration(demo_app):
    plain = seed_done_inspection(demo_app, plate_id="H3-P01")
    warned = seed_done_inspection(demo_app, plate_id="H3-P02")
    calibration_id = seed_light_calibration(demo_app, ring_of_lights(8))
    from app.models import Inspection

    with demo_app.state.session_factory() as session:
        row = session.get(Inspection, warned)
        row.result = {**row.result, "warnings": [APPLIED, "measured area <far> below the target's"]}
        row.light_calibration_id = calibration_id
        session.commit()
    with TestClient(demo_app) as client:
        html = client.get(f"/inspections/{warned}").text
        section = html[
            html.index('id="warnings"') : html.index("</section>", html.index('id="warnings"'))
        ]
        assert f"<li>{APPLIED}</li>".replace("'", "&#39;") in section
        assert "&lt;far&gt;" in section  # escaped by the template
        assert f'href="/api/v1/light-calibrations/{calibration_id}"' in html
        html = client.get(f"/inspections/{plain}").text
        assert 'id="warnings"' not in html and "light calibration #" not in html
