"""The "Next pass" panel (issue 14) on the plate and inspection pages, and the passes in the plate's history."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.api.helpers import MACHINE, MATERIAL, process, target_json


def _seed(
    app, *, plate_id: str, passes: list[tuple[float, float, str]], material=MATERIAL
) -> int | None:
    """A machine, the plate's cylinder target and its done passes ``(setting, measured radius, verdict)``."""
    from app.schemas import SimulatedInspectionIn
    from app.services import forming as forming_svc
    from app.services import inspections as svc
    from app.services import leases
    from app.services.targets import TARGET_FILE, create_target

    storage = app.state.storage
    last = None
    with app.state.session_factory() as session:
        forming_svc.put_machine(
            session=session,
            machine_id="R3-01",
            spec={k: float(v) if k != "kind" else v for k, v in MACHINE.items()},
        )
        staging = storage.new_staging_dir()
        (staging / TARGET_FILE).write_bytes(target_json(material=material))
        create_target(session=session, storage=storage, plate_id=plate_id, staging_dir=staging)
        session.commit()
        for setting, radius, verdict in passes:
            simulation = SimulatedInspectionIn(process=process(setting)).model_dump(mode="json")
            row = svc.create_simulated_inspection(
                session=session, storage=storage, plate_id=plate_id, simulation=simulation
            )
            session.commit()
            assert leases.claim(session=session, inspection_id=row.id)
            document = {
                "format": "plate-result/1",
                "plate_id": plate_id,
                "radius_mm": radius,
                "target_radius_mm": 5000.0,
                "verdict": verdict,
            }
            assert leases.mark_done(session=session, inspection_id=row.id, document=document)
            session.commit()
            last = row.id
    return last


def test_plate_page_advises_the_next_pass_and_lists_settings(demo_app):
    last = _seed(demo_app, plate_id="P-W1", passes=[(97.0, 6200.0, "fail")])
    with TestClient(demo_app) as client:
        html = client.get("/plates/P-W1").text
        assert 'id="next-pass"' in html and 'data-action="bend"' in html
        assert "this plate&#39;s passes" in html or "this plate's passes" in html
        assert "1 inspected pass of this plate" in html
        assert "97.0 mm" in html and "6200.0 mm" in html  # the setting beside the radius after it
        assert 'data-action="bend"' in client.get(f"/inspections/{last}").text


def test_panel_says_why_there_is_no_advice(demo_app):
    _seed(demo_app, plate_id="P-W2", passes=[], material=None)
    _seed(demo_app, plate_id="P-W3", passes=[(101.0, 5004.0, "pass")])
    with TestClient(demo_app) as client:
        html = client.get("/plates/P-W2").text
        assert 'id="next-pass"' in html and "has no material" in html
        assert 'data-action="done"' in client.get("/plates/P-W3").text


def test_first_pass_without_history_says_the_data_is_nominal(demo_app):
    _seed(demo_app, plate_id="P-W4", passes=[])
    with TestClient(demo_app) as client:
        html = client.get("/plates/P-W4").text
        assert 'data-action="bend"' in html and "nominal only: no history" in html
        assert "no inspected pass of this plate or of this machine" in html


def test_plate_page_draws_radius_against_setting_with_the_next_pass(demo_app):
    _seed(
        demo_app,
        plate_id="P-W5",
        # two passes the model can follow (a 6 mm step that took 9 m to 6.2 m left it no safe setting)
        passes=[(80.0, 12000.0, "fail"), (85.0, 9000.0, "fail")],
    )
    with TestClient(demo_app) as client:
        html = client.get("/plates/P-W5").text
    assert 'id="forming-passes"' in html and 'class="forming"' in html
    # both passes drawn in order, with their setting and radius, and the advised next one
    assert 'data-pass="1"' in html and 'data-pass="2"' in html
    assert "pass 1" in html and "80.0 mm → 12000 mm" in html and "85.0 mm → 9000 mm" in html
    assert 'class="next"' in html and 'class="band"' in html and ">target<" in html


def test_forming_chart_places_passes_band_and_next_pass():
    from web.charts import forming_chart

    chart = forming_chart(
        [(1, 90.0, 9000.0, "fail"), (2, 95.0, None, None), (3, 96.0, 5200.0, "fail")],
        target_radius_mm=5000.0,
        band_mm=(4900.0, 5100.0),
        next_pass=(97.0, 5010.0, (4950.0, None)),
    )
    assert [p.number for p in chart.points] == [1, 3] and chart.flat_passes == 1
    a, b = chart.points
    assert a.x < b.x and a.y < b.y  # deeper setting to the right, smaller radius lower
    assert chart.top <= a.y <= chart.bottom and chart.top <= b.y <= chart.bottom
    tight, open_ = chart.band_y
    assert open_ < chart.target_y < tight  # the band straddles the target line
    n = chart.next_pass
    assert n.x > b.x and n.y_hi == chart.top  # a range open to flat reaches the top
    assert chart.x_ticks[0][0] == chart.left and chart.x_ticks[-1][0] == chart.right


def test_advice_is_said_in_an_operators_words():
    """Issue 26: "under-bent: radius +5.0 %", the next pass with its setting and outcome, one more
    pass announced when the expected radius stays outside the band; plural and singular right."""
    from types import SimpleNamespace

    from web.forming_words import count, mm, next_pass_words, radius_band_mm, radius_state

    row = SimpleNamespace(radius_mm=5250.6, target_radius_mm=5000.0, verdict="fail")
    band = (4950.0, 5050.0)
    assert radius_state(row, band) == "under-bent: radius +5.0 % (5\u202f251 mm, 5.0 % open)"
    tight = SimpleNamespace(radius_mm=4850.0, target_radius_mm=5000.0, verdict="fail")
    assert radius_state(tight, band).startswith("over-bent: radius \u22123.0 %")
    on = SimpleNamespace(radius_mm=5010.0, target_radius_mm=5000.0, verdict="pass")
    assert radius_state(on, band) == "radius on target: 5\u202f010 mm (+0.2 %)"
    advice = {
        "action": "bend",
        "machine_id": "R3-07",
        "top_roll_displacement_mm": 111.26,
        "expected_radius_mm": 5106.0,
        "basis": {"tolerance_band_radius_mm": list(band)},
    }
    assert next_pass_words(advice) == (
        "next pass on R3-07: top roll 111.3 mm, expected 5\u202f106 mm, then one more pass"
    )
    assert next_pass_words({**advice, "expected_radius_mm": 5020.0}).endswith("within tolerance")
    assert count(1, "plate", "plates") == "1 plate" and count(3, "pass", "passes") == "3 passes"
    assert mm(-1234.0) == "\u22121\u202f234 mm"
    # the band from a cylinder target: 8 tol R / w^2 = 0.889 % at R 5000, 3000 mm wide, 2 mm
    target = {"shape": {"type": "cylinder", "radius_mm": 5000.0}, "size_mm": [3000.0, 3000.0]}
    lo, hi = radius_band_mm({**target, "tolerance_mm": 2.0})
    assert (round(lo, 1), round(hi, 1)) == (4955.6, 5044.4)
    almost = SimpleNamespace(radius_mm=4998.5, target_radius_mm=5000.0, verdict="fail")
    assert radius_state(almost, (lo, hi)) == "radius on target: 4\u202f998 mm (0.0 %)"


def test_no_advice_links_the_page_that_supplies_what_is_missing(demo_app):
    """No target: a link to the plate's target form; no machine: to the machines page; never an
    API path."""
    from app.services.targets import TARGET_FILE, create_target
    from tests.web.helpers import seed_done_inspection

    inspection_id = seed_done_inspection(demo_app, plate_id="P-W6")
    storage = demo_app.state.storage
    with demo_app.state.session_factory() as session:
        staging = storage.new_staging_dir()
        (staging / TARGET_FILE).write_bytes(target_json(material=MATERIAL))
        create_target(session=session, storage=storage, plate_id="P-W8", staging_dir=staging)
        session.commit()
    with TestClient(demo_app) as client:
        html = client.get(f"/inspections/{inspection_id}").text
        panel = html.split('id="next-pass"')[1].split("</section>")[0]
        assert "/api/v1" not in panel
        assert 'href="/plates/P-W6#target"' in panel and "has no target" in panel
        # no target document to judge the radius by (a seeded row): the radius, not judged
        assert "radius 5\u202f050 mm against 5\u202f000 mm (+1.0 %)" in panel
        panel = client.get("/plates/P-W8").text.split('id="next-pass"')[1].split("</section>")[0]
        assert "no roll bender is known" in panel and 'href="/machines"' in panel
        assert "/api/v1" not in panel


def test_service_messages_lose_their_api_paths_on_the_page():
    """A service's message names an API path for API clients; the page says the reason without it."""
    from web.forming_words import _API_PATH

    message = "no machine 'R3': add it first with PUT /api/v1/machines/R3"
    assert _API_PATH.sub("", message).rstrip(" :;,") == "no machine 'R3'"
    message = "plate 'P' has no target: set one with its material (PUT /api/v1/plates/P/target)"
    assert "/api/" not in _API_PATH.sub("", message)
