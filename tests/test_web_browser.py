"""The web page in a real browser (Debian's chromium driven by Playwright) against the served
app on localhost: the orthophoto shows, start and target are set by clicking the map, a
mission flies with both tracks drawn live and its fixes' matches shown, a past run opens
again, a mission is cancelled from the page, runs are compared with their tracks on the map,
a GeoTIFF uploaded from the page becomes a map, and bad input and a failed mission are
explained on the page. A screenshot is kept in test-artifacts/."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

pytest.importorskip("fastapi", reason="the web extra is not installed: pip install 'orthonav[web]'")
pytest.importorskip("rio_tiler", reason="the web extra is not installed: pip install 'orthonav[web]'")

from conftest import write_naip_crop
from helpers_web import MAP_NAME, map_fraction, mission_request, served, web_data_dir

from orthonav.errors import OrthonavError
from orthonav.mapdb import MapPackage
from orthonav.web import WebSettings

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts"
MISSION_TIMEOUT_MS = 60_000
# Every text the upload panel's message takes, kept in window.uploadMessages.
RECORD_UPLOAD_MESSAGES = """() => {
  const box = document.getElementById("upload-message");
  window.uploadMessages = [];
  new MutationObserver(() => window.uploadMessages.push(box.textContent))
    .observe(box, {childList: true, characterData: true, subtree: true});
}"""


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """``orthonav serve`` in a thread, on a free loopback port, over a data folder with one map."""
    data = web_data_dir(tmp_path_factory.mktemp("web_browser"))
    with served(WebSettings(data)) as (url, _, _):
        yield SimpleNamespace(url=url, package=MapPackage(data / "maps" / MAP_NAME))


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.is_file():
        pytest.skip(f"{CHROMIUM} is missing: apt-get install chromium (the browser tests use Debian's)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (test extra)")
    with sync_api.sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


@pytest.fixture
def page(browser, server):
    """A fresh page on the app; fails the test on any uncaught script error."""
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.goto(server.url)
    page.locator(".leaflet-tile-loaded").first.wait_for()
    yield page
    context.close()
    assert not errors, errors


def _expect():
    from playwright.sync_api import expect

    return expect


def _click_on_map(page, point: dict[str, float]) -> None:
    """A real mouse click at the screen position of a WGS84 point."""
    to_screen = "([lat, lon]) => window.orthonav.map.latLngToContainerPoint([lat, lon])"
    xy = page.evaluate(to_screen, [point["lat"], point["lon"]])
    box = page.locator("#map").bounding_box()
    page.mouse.click(box["x"] + xy["x"], box["y"] + xy["y"])


def _set_start_and_target(page, server) -> tuple[dict, dict]:
    start, target = map_fraction(server.package, 0.3, 0.65), map_fraction(server.package, 0.7, 0.35)
    page.click("#pick-start")
    _click_on_map(page, start)  # a click sets the start, and the next one the target
    _click_on_map(page, target)
    for which, point in (("start", start), ("target", target)):
        assert float(page.input_value(f"#{which}-lat")) == pytest.approx(point["lat"], abs=3e-4)
        assert float(page.input_value(f"#{which}-lon")) == pytest.approx(point["lon"], abs=3e-4)
    return start, target


def test_plan_a_mission_on_the_map_watch_it_fly_and_open_it_again(page, server) -> None:
    expect = _expect()
    expect(page.locator("#map-select")).to_have_value(MAP_NAME)
    _set_start_and_target(page, server)
    page.fill("#altitude", "1000")
    page.fill("#speed", "30")
    page.fill("#seed", "1")
    page.click("#start-mission")
    expect(page.locator("#run-status")).to_contain_text("done", timeout=MISSION_TIMEOUT_MS)

    counts = page.evaluate("window.orthonav.trackCounts()")
    print(f"\ntracks drawn: {counts}")
    assert counts["true"] > 1 and counts["estimatedDrawn"] > 1, "both tracks are on the map"
    assert counts["steps"] >= 3 and counts["fixes"] == counts["steps"]
    expect(page.locator("#step-log tbody tr")).to_have_count(counts["steps"])
    expect(page.locator("#run-files a", has_text="trajectory.png")).to_have_count(1)
    # The last fix's matches: the 640 px frame beside the 480 px square of the map's orthophoto.
    last = page.evaluate("window.orthonav.state.steps.at(-1)")
    assert last["matches_url"] and page.get_attribute("#frame", "src") == last["matches_url"]
    page.wait_for_function("() => document.getElementById('frame').naturalWidth > 0")
    assert page.evaluate("document.getElementById('frame').naturalWidth") == 640 + 480
    drawn = page.evaluate(
        "(() => { const c = document.getElementById('error-plot');"
        " const pixels = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
        " return pixels.filter((v, i) => i % 4 == 3 && v).length; })()"
    )
    assert drawn > 200, "the error plot is drawn"
    ARTIFACTS.mkdir(exist_ok=True)
    shot = ARTIFACTS / "web_mission.png"
    page.screenshot(path=str(shot))
    assert shot.stat().st_size > 10_000

    run_id = page.locator("#run-title").inner_text().removeprefix("Run ")
    page.reload()
    page.locator(f'#runs-table tr[data-run="{run_id}"]').click()
    expect(page.locator("#run-status")).to_contain_text("done")
    expect(page.locator("#step-log tbody tr")).to_have_count(counts["steps"])
    reopened = page.evaluate("window.orthonav.trackCounts()")
    assert reopened["true"] == counts["true"] and reopened["steps"] == counts["steps"]
    expect(page.locator("#run-summary")).to_contain_text("nav_error_median_m")


def test_bad_input_and_a_failed_mission_are_explained_on_the_page(page, server, monkeypatch) -> None:
    expect = _expect()
    _set_start_and_target(page, server)
    page.fill("#start-lat", "95")
    page.click("#start-mission")
    expect(page.locator("#mission-message")).to_contain_text(
        "start.lat: Input should be less than or equal to 90"
    )

    def unreadable(*args, **kwargs):
        raise OrthonavError("frames.tif: not a readable GeoTIFF (truncated)")

    monkeypatch.setattr("orthonav.web.jobs.run_mission", unreadable)
    _set_start_and_target(page, server)
    page.click("#start-mission")
    expect(page.locator("#run-status")).to_contain_text(
        "failed: frames.tif: not a readable GeoTIFF (truncated)"
    )
    expect(page.locator("#runs-table tbody tr", has_text="failed").first).to_be_visible()


def _post_json(page, server, path: str, body: dict) -> dict:
    response = page.request.post(server.url + path, data=body)
    assert response.ok, response.text()
    return response.json()


def test_cancel_a_mission_then_compare_runs_with_both_tracks_on_the_map(page, server) -> None:
    expect = _expect()
    ins_only = _post_json(
        page, server, "/api/runs", mission_request(server.package, fix_source="ins", max_time_s=30)
    )
    slow = _post_json(page, server, "/api/runs", mission_request(server.package, speed_mps=5.0))
    page.click("#refresh-runs")
    page.locator(f'#runs-table tr[data-run="{slow["id"]}"]').click()
    expect(page.locator("#cancel-run")).to_be_visible()
    page.wait_for_function("() => window.orthonav.state.steps.length >= 1", timeout=MISSION_TIMEOUT_MS)
    page.click("#cancel-run")
    expect(page.locator("#run-status")).to_contain_text("cancelled", timeout=MISSION_TIMEOUT_MS)
    expect(page.locator("#cancel-run")).to_be_hidden()
    expect(page.locator("#run-summary")).to_contain_text("end_reason")
    expect(page.locator("#runs-table tbody tr", has_text="cancelled").first).to_be_visible()

    for run in (ins_only, slow):
        page.locator(f'#runs-table tr[data-run="{run["id"]}"] input').check()
    page.click("#compare-runs")
    expect(page.locator("#compare table th[title]")).to_have_count(2)
    page.wait_for_function("() => window.orthonav.overlays.compare.getLayers().length === 2")
    drawn = page.evaluate("window.orthonav.overlays.compare.getLayers().map((l) => l.getLatLngs().length)")
    print(f"\ncompared tracks: {drawn} points")
    assert len(drawn) == 2 and min(drawn) > 3, "both runs' estimated tracks are on the map"
    expect(page.locator("#compare")).to_contain_text("ins")


def test_upload_a_geotiff_from_the_page_and_build_a_map_from_it(page, server, tmp_path: Path) -> None:
    expect = _expect()
    crop = write_naip_crop("20200831", (300, 200, 400, 360), tmp_path / "crop.tif")  # 2 x 1.8 km
    page.evaluate(RECORD_UPLOAD_MESSAGES)
    page.set_input_files("#upload-file", str(crop))
    page.fill("#upload-name", "crop2020")
    page.fill("#build-altitude", "1000")
    page.click("#upload-start")
    expect(page.locator("#upload-message")).to_have_text("map crop2020 built", timeout=MISSION_TIMEOUT_MS)

    messages = page.evaluate("window.uploadMessages")
    print(f"\nupload and build: {messages}")
    assert any("map crop2020: running" in m for m in messages), "the build's progress was shown"
    assert page.evaluate("document.getElementById('upload-progress').value") == 1
    assert page.evaluate("document.getElementById('build-progress').value") == 1
    expect(page.locator("#map-select")).to_have_value("crop2020")
    expect(page.locator("#map-select option[value=crop2020]")).to_have_count(1)
    expect(page.locator("#frames-from option[value=crop2020]")).to_have_count(1)
    expect(page.locator("#map-info")).to_contain_text("orb, nominal 1000")
    expect(page.locator(".leaflet-tile-loaded[src*='/maps/crop2020/tiles/']").first).to_be_visible()
