"""Server-rendered pages (FastAPI TestClient, a real app on a migrated SQLite file)."""

from __future__ import annotations

import csv
import io
import json
import re

import pytest
from fastapi.testclient import TestClient

from app.models import Inspection
from tests.web.helpers import seed_done_inspection, seed_queued_inspection


def test_cell_page_has_form_queue_and_no_external_assets(demo_app):
    queued = seed_queued_inspection(demo_app)
    with TestClient(demo_app) as client:
        page = client.get("/cell")
        assert page.status_code == 200
        html = page.text
        assert 'id="start-form"' in html and 'id="queue"' in html
        assert f'data-id="{queued}"' in html and "queued" in html
        # No CDN: every script and stylesheet is served by the app.
        for url in re.findall(r'(?:src|href)="([^"]+)"', html):
            assert not url.startswith(("http:", "https:", "//")), url
        for asset in re.findall(r'(?:src|href)="(/static/[^"]+)"', html):
            assert client.get(asset).status_code == 200, asset
        # Demo mode hands out the write session to same-origin pages.
        assert "plate_inspect_session" in page.headers.get("set-cookie", "")
        partial = client.get("/cell/queue")
        assert (
            partial.status_code == 200
            and f'data-id="{queued}"' in partial.text
            and "<html" not in partial.text
        )


def test_result_page_shows_verdict_numbers_view_and_templates(demo_app):
    inspection_id = seed_done_inspection(demo_app)
    with TestClient(demo_app) as client:
        html = client.get(f"/inspections/{inspection_id}").text
        assert (
            'class="verdict-banner verdict-fail"' in html
        )  # 2.2 mm max deviation > 2 mm tolerance
        assert "5050.0 mm" in html and "5000.0 mm" in html and "+1.00 %" in html
        assert f'src="/viewer/{inspection_id}/?hideViserLogo"' in html
        # Frames every 700 mm over the 2000 mm axis: 3 templates (300, 1000, 1700 mm).
        assert html.count('<figure class="template"') == 3
        # no registration seeded: the frame is placed from the plate's first edge, and says so
        assert "Frame 1000 mm from the plate's first edge" in html
        # The largest true gap is at the edges: sagitta difference 2.2 mm, labelled in red.
        assert 'class="gap-label bad"' in html
        partial = client.get(f"/inspections/{inspection_id}/templates", params={"spacing_mm": 300})
        assert partial.text.count('<figure class="template"') == 7 and "<html" not in partial.text
        assert (
            client.get(
                f"/inspections/{inspection_id}/templates", params={"spacing_mm": 10}
            ).status_code
            == 422
        )
        assert client.get("/inspections/999").status_code == 404


def test_result_page_states_each_figure_with_its_uncertainty(demo_app):
    stated = seed_done_inspection(
        demo_app, uncertainty={"k": 2, "radius_mm": 3.1, "deviation_mm": 0.12}
    )
    older = seed_done_inspection(demo_app, plate_id="H1-P09")
    with TestClient(demo_app) as client:
        html = client.get(f"/inspections/{stated}").text
        assert "± 3.1 mm" in html and "± 0.12 mm" in html and "U95" in html
        assert client.get(f"/inspections/{older}").text.count("not stated") == 2


def test_running_result_page_watches_the_job(demo_app):
    inspection_id = seed_queued_inspection(demo_app)
    with TestClient(demo_app) as client:
        html = client.get(f"/inspections/{inspection_id}").text
        assert f'data-watch="/api/v1/inspections/{inspection_id}"' in html
        assert "<iframe" not in html


def test_plate_history_has_trend_and_links(demo_app):
    first = seed_done_inspection(demo_app, plate_id="H2-P03", measured_radius_mm=5100.0)
    second = seed_done_inspection(demo_app, plate_id="H2-P03", measured_radius_mm=5020.0)
    with TestClient(demo_app) as client:
        html = client.get("/plates/H2-P03").text
        assert f'href="/inspections/{first}"' in html and f'href="/inspections/{second}"' in html
        assert (
            html.count('<circle class="dot dot-1"') == 2
            and html.count('<circle class="dot dot-2"') == 2
        )
        assert 'class="limit"' in html  # the tolerance line
        assert client.get("/plates/NOPE").status_code == 404


def test_calibration_and_login_pages(demo_app):
    with TestClient(demo_app) as client:
        html = client.get("/calibration").text
        assert "No calibration uploaded yet." in html and 'id="calibration-form"' in html
        assert 'id="login-form"' in client.get("/login").text
        assert client.get("/", follow_redirects=False).headers["location"] == "/cell"


def test_no_outside_url_in_pages_static_files_or_the_viewer_client():
    """Shop-floor networks are closed: nothing the dashboard or the 3D view serves points outside."""
    from pathlib import Path

    import viser

    web = Path(__file__).resolve().parents[2] / "web"
    files = [p for p in web.rglob("*") if p.is_file() and p.suffix in (".html", ".js", ".css")]
    assert len(files) >= 10
    for path in files:
        assert not re.search(r"https?://|//cdn", path.read_text(encoding="utf-8")), path
    client_page = (Path(viser.__file__).parent / "client" / "build" / "index.html").read_text(
        encoding="utf-8"
    )
    # The only URL in viser's bundled client is the SVG namespace (an identifier, never fetched).
    assert set(re.findall(r"https?://[A-Za-z0-9.-]+", client_page)) <= {"http://www.w3.org"}


def test_result_page_says_why_and_where_a_plate_failed(demo_app):
    """The reasons and the defect table come from the inspection's details.json."""
    inspection_id = seed_done_inspection(demo_app)
    details = {
        "reasons": ["1 region(s) out of the 2 mm tolerance over 100 mm^2 (largest 13786 mm^2)"],
        "defects": [
            {
                "centroid_px": [352.0, 224.5],
                "centroid_mm": [-596.2, 301.4],
                "area_mm2": 13785.7,
                "peak_deviation_mm": 5.93,
                "mean_deviation_mm": 3.74,
            }
        ],
    }
    folder = demo_app.state.storage.artifacts_dir(inspection_id)
    (folder / "details.json").write_text(json.dumps(details))
    with TestClient(demo_app) as client:
        html = client.get(f"/inspections/{inspection_id}").text
        api = client.get(f"/api/v1/inspections/{inspection_id}").json()
    # areas in cm² throughout (issue 26), older results' "mm^2" reasons too, singular right
    assert 'id="defects"' in html and "1 region out of the 2 mm tolerance over 1 cm²" in html
    assert "largest 137.9 cm²" in html and "mm^2" not in html
    row = html.split('class="defect-table"')[1].split("</tbody>")[0]
    for cell in ("<td>1</td>", "<td>-596</td>", "<td>301</td>", "<td>137.9</td>", "+5.9", "+3.7"):
        assert cell in row, (cell, row)
    assert api["defects"] == [
        {
            "id": 1,
            "centroid_mm": [-596.2, 301.4],
            "centroid_px": [352.0, 224.5],
            "area_mm2": 13785.7,
            "peak_mm": 5.93,
            "mean_mm": 3.74,
        }
    ]
    assert api["reasons"] == ["1 region out of the 2 mm tolerance over 1 cm² (largest 137.9 cm²)"]


def test_a_plates_inspections_as_csv(demo_app):
    first = seed_done_inspection(demo_app, plate_id="CSV-1", measured_radius_mm=5050.0)
    second = seed_done_inspection(demo_app, plate_id="CSV-1", measured_radius_mm=5010.0)
    with demo_app.state.session_factory() as session:
        session.get(Inspection, second).operator = "=Kim Ji-woo"  # a spreadsheet formula: quoted
        session.commit()
    with TestClient(demo_app) as client:
        r = client.get("/api/v1/plates/CSV-1/inspections.csv")
        missing = client.get("/api/v1/plates/NO-SUCH/inspections.csv")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/csv")
    assert 'filename="CSV-1-inspections.csv"' in r.headers["content-disposition"]
    rows = list(csv.DictReader(io.StringIO(r.text)))
    assert [int(row["inspection_id"]) for row in rows] == [first, second]  # oldest first
    assert [float(row["radius_mm"]) for row in rows] == pytest.approx([5050.0, 5010.0], abs=1.0)
    assert all(row["status"] == "done" and row["verdict"] in ("pass", "fail") for row in rows)
    assert rows[0]["created_at"].endswith("+00:00")  # the time zone is said
    assert rows[0]["target_radius_mm"] == "5000.0"
    assert [row["operator"] for row in rows] == ["", "'=Kim Ji-woo"]
    assert missing.status_code == 404 and missing.json()["field"] == "plate_id"


def test_pages_say_which_calibration_applies(demo_app):
    inspection_id = seed_done_inspection(demo_app, plate_id="H1-CAL")
    with TestClient(demo_app) as client:
        calibration = client.get("/calibration").text
        result = client.get(f"/inspections/{inspection_id}").text
    assert 'id="calibration-use"' in calibration and "<b>not</b> applied" in calibration
    assert (
        "stereo calibration: the bundle&#39;s own" in result
        or "stereo calibration: the bundle's own" in result
    )
    assert (
        "no light calibration (the bundle&#39;s lights)" in result
        or "no light calibration (the bundle's lights)" in result
    )


def test_dashboard_errors_are_pages_in_the_layout_and_the_api_keeps_json(demo_app):
    html = {"Accept": "text/html,application/xhtml+xml"}
    with TestClient(demo_app) as client:
        page = client.get("/plates/NO-SUCH-PLATE", headers=html)
        assert page.status_code == 404 and page.headers["content-type"].startswith("text/html")
        assert 'id="error-page"' in page.text and "Not found" in page.text
        assert "plate &#39;NO-SUCH-PLATE&#39; not found" in page.text
        assert 'id="side"' in page.text  # the layout, with its side lists
        missing = client.get("/inspections/999999", headers=html)
        assert missing.status_code == 404 and 'id="error-page"' in missing.text
        # the API, a script asking for JSON, and the static files answer as before
        api = client.get("/api/v1/plates/NO-SUCH-PLATE", headers=html)
        assert api.status_code == 404 and api.json()["detail"]
        assert client.get("/plates/NO-SUCH-PLATE").json()["detail"]
        assert client.get("/static/nope.css", headers=html).status_code == 404


def test_side_lists_partial_and_time_zone(demo_app):
    inspection_id = seed_done_inspection(demo_app, plate_id="H1-SIDE")
    queued = seed_queued_inspection(demo_app, plate_id="H1-SIDE")
    with TestClient(demo_app) as client:
        side = client.get("/side", params={"current": "H1-SIDE"}).text
        assert "(1 active)" in side and f"#{queued} H1-SIDE" in side
        assert 'class="current"' in side
        page = client.get("/plates/H1-SIDE").text
        assert 'data-src="/side?current=H1-SIDE"' in page and "/static/js/layout.js" in page
        assert " UTC</td>" in page  # times say their zone
        assert client.get(f"/inspections/{inspection_id}").status_code == 200


def test_side_list_pages_through_the_plates(demo_app):
    """42 plates: the side list shows the 40 most recent, and a page of the older ones on request."""
    for k in range(42):
        seed_queued_inspection(demo_app, plate_id=f"PG-{k:02d}")
    with TestClient(demo_app) as client:
        first = client.get("/side").text.split("<h2>Plates")[1]
        older = client.get("/side", params={"page": 1}).text.split("<h2>Plates")[1]
        bad = client.get("/side", params={"page": -1})
    assert "PG-41" in first and "PG-02" in first and "PG-01" not in first
    assert "1–40 of 42" in first and 'data-side-page="1"' in first and "newer" not in first
    assert "PG-01" in older and "PG-00" in older and "PG-02" not in older
    assert "41–42 of 42" in older and 'data-side-page="0"' in older and "older ›" not in older
    assert bad.status_code == 422


def test_side_list_searches_plates(demo_app):
    for plate in ("HULL-A1", "HULL-B2", "DECK-C3"):
        seed_queued_inspection(demo_app, plate_id=plate)
    with TestClient(demo_app) as client:
        side = client.get("/side", params={"q": "hull"}).text.split("<h2>Plates")[1]
        assert "HULL-A1" in side and "HULL-B2" in side and "DECK-C3" not in side
        assert "(2 matching)" in side
        none = client.get("/side", params={"q": "50%_"}).text  # taken literally, not as a pattern
        assert "No plate id contains" in none
        page = client.get("/cell").text
    assert 'id="plate-search"' in page and 'id="side-body"' in page


def test_compare_two_inspections_of_a_plate(demo_app):
    """The plate page offers to compare its done inspections; the compare page puts two side by side
    with the change of each number, and refuses what cannot be compared in plain words."""
    first = seed_done_inspection(demo_app, plate_id="H13-CMP", measured_radius_mm=5300.0)
    second = seed_done_inspection(demo_app, plate_id="H13-CMP", measured_radius_mm=5050.0)
    other = seed_done_inspection(demo_app, plate_id="H13-OTHER")
    queued = seed_queued_inspection(demo_app, plate_id="H13-CMP")
    with TestClient(demo_app) as client:
        history = client.get("/plates/H13-CMP").text
        assert 'id="compare-form"' in history and 'action="/plates/H13-CMP/compare"' in history
        page = client.get("/plates/H13-CMP/compare")  # the last two by default
        assert page.status_code == 200
        html = page.text
        assert f'href="/inspections/{first}">#{first}</a>' in html
        assert f'href="/inspections/{second}">#{second}</a>' in html
        assert 'id="plate-map-a"' in html and 'id="plate-map-b"' in html
        assert f'data-src="/api/v1/inspections/{second}/plate-map"' in html
        radius = re.search(r'data-quantity="Radius error">(.*?)</tr>', html, re.S).group(1)
        cells = re.findall(r'<td class="num[^"]*">([^<]*)</td>', radius)
        a, b, change = (float(c.replace("%", "").replace("+", "").strip()) for c in cells)
        assert b < a and change == pytest.approx(b - a, abs=0.011)
        assert 'class="num better"' in radius  # the radius error shrank

        same = client.get(
            f"/plates/H13-CMP/compare?a={first}&b={first}", headers={"Accept": "text/html"}
        )
        assert same.status_code == 422 and "two different inspections" in same.text
        foreign = client.get(f"/plates/H13-CMP/compare?a={first}&b={other}")
        assert foreign.status_code == 404 and f"has no inspection {other}" in foreign.text
        pending = client.get(f"/plates/H13-CMP/compare?a={first}&b={queued}")
        assert pending.status_code == 422 and "only done ones have results" in pending.text
        alone = client.get("/plates/H13-OTHER/compare")
        assert alone.status_code == 422 and "comparing needs two" in alone.text


def test_map_legend_colours_are_the_maps():
    """The page's legend (app.css) shows the very colours the map and the 3D view are drawn with."""
    from pathlib import Path

    from app.report.figures import UNMEASURED_RGB
    from pipeline.artifacts.colours import ABOVE_RGB, BELOW_RGB, IN_TOLERANCE_RGB

    css = (Path(__file__).resolve().parents[2] / "web" / "static" / "css" / "app.css").read_text()
    bands = {
        name: tuple(int(v) for v in rgb.split(","))
        for name, rgb in re.findall(
            r"\.map-legend \.band-([a-z-]+) \{ background: rgb\(([^)]+)\)", css
        )
    }
    assert bands == {
        "in": IN_TOLERANCE_RGB,
        "above": ABOVE_RGB[0],
        "above-far": ABOVE_RGB[1],
        "below": BELOW_RGB[0],
        "below-far": BELOW_RGB[1],
        "none": UNMEASURED_RGB,  # unmeasured cells: the page's map and the PDF's alike
    }
    assert f".map-unmeasured {{ fill: rgb{UNMEASURED_RGB}; }}" in css


def test_the_machines_page_lists_adds_and_edits_roll_benders(demo_app):
    geometry = {
        "kind": "three-roll-pyramid",
        "bottom_roll_spacing_mm": 1400.0,
        "bottom_roll_diameter_mm": 420.0,
        "top_roll_diameter_mm": 500.0,
    }
    with TestClient(demo_app) as client:
        empty = client.get("/machines")
        client.get("/cell")  # the demo's session cookie
        assert client.put("/api/v1/machines/R3-01", json=geometry).status_code == 201
        listed = client.get("/machines").text
        editing = client.get("/machines", params={"edit": "R3-01"}).text
        unknown = client.get("/machines", params={"edit": "NOPE"}, headers={"Accept": "text/html"})
    assert empty.status_code == 200 and "No machine yet" in empty.text
    assert '<a href="/machines" aria-current="page">Machines</a>' in empty.text
    assert 'data-machine="R3-01"' in listed and "1400 mm" in listed and "420 mm" in listed
    assert 'href="/machines?edit=R3-01"' in listed and "Add a machine" in listed
    assert "Edit machine R3-01" in editing and 'value="R3-01" readonly' in editing
    assert 'value="1400.0"' in editing and 'data-editing="true"' in editing
    assert unknown.status_code == 404


def test_result_page_shows_traceability_and_not_capable_warnings_first(demo_app):
    """Issue 26: the target's drawing, revision, hull and block in the page's head; the result's
    warnings (a "not capable" measurement) right under the verdict, before the advice."""
    from app.models import Inspection
    from app.services.targets import TARGET_FILE, create_target
    from tests.api.helpers import target_json

    storage = demo_app.state.storage
    trace = {
        "drawing": {"number": "DWG-H77-B21-0042", "revision": "C"},
        "hull": "H77",
        "block": "B21",
    }
    with demo_app.state.session_factory() as session:
        staging = storage.new_staging_dir()
        (staging / TARGET_FILE).write_bytes(target_json(**trace))
        create_target(session=session, storage=storage, plate_id="H77-P3", staging_dir=staging)
        session.commit()
    inspection_id = seed_done_inspection(demo_app, plate_id="H77-P3")
    warning = "not capable: the test uncertainty ratio is 2.1 (below 4)"
    with demo_app.state.session_factory() as session:
        row = session.get(Inspection, inspection_id)
        row.result = {**row.result, "warnings": [warning]}
        session.commit()
    with TestClient(demo_app) as client:
        html = client.get(f"/inspections/{inspection_id}").text
    head = html.split('id="traceability">')[1].split("</span>")[0]
    assert head == "drawing DWG-H77-B21-0042 rev. C · hull H77 · block B21"
    assert warning in html
    assert html.index('id="verdict"') < html.index('id="warnings"') < html.index('id="next-pass"')


def test_numbers_on_the_pages_never_read_minus_zero():
    from web.routes import _fmt

    assert _fmt(-0.001, 2, "%", signed=True) == "+0.00 %"
    assert _fmt(-0.004, 2, "mm") == "0.00 mm"
    assert _fmt(-0.006, 2, "mm") == "-0.01 mm"
