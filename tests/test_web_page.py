"""The operator's page in a real browser: Debian's Chromium, headless, driven by Playwright for Python,
against a real ``cell serve`` (the sim Franka + RGB-D cell) reached through a TCP relay whose connections
the test can cut (``tests.tcp_proxy``).

One service and one browser serve the whole module. A wrong key is refused; a viewer's key is offered no
scan, nor the stop of a queued job; the packing line's PackML state shows when the status has one, and an
operator switches its unit mode (a cell of its own); an operator starts a raster scan from the form (a
pose off the table is refused next to the field first), watches progress arrive, sees it complete with
its coverage and dimensions, downloads a file and finds it in the jobs table; uploads a mesh; a vs-local
scan is watched live through a cut of every connection (the event stream resumes and no progress is
lost), then stopped with the STOP key and the queue resumed; the views fit 1024x768; an operator recovers
the arm after a protective stop (a cell of its own). The 3D view is checked to have drawn (its canvas
read back), and each main view is saved as a screenshot under
``tests/artifacts/web/``.
"""

from __future__ import annotations

import base64
import io
import itertools
import json
import os
import re
import shutil
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
import yaml
from PIL import Image

from drivers.sim.objects import DEFAULT_OBJECT
from tests.conftest import FRANKA
from tests.service_process import REPO, ServedCell
from tests.tcp_proxy import CuttableProxy

CHROMIUM = Path("/usr/bin/chromium")
pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed "
                                "(deploy/system-deps.sh installs it): no browser to run the page in")
sync_api = pytest.importorskip("playwright.sync_api")

ARTIFACTS = REPO / "tests" / "artifacts" / "web"
# as the machine's own probe starts it: no sandbox (root), no GPU, no calls home; WebGL on SwiftShader
LAUNCH_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
               "--disable-background-networking", "--disable-component-update", "--disable-sync",
               "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
WAIT_MS = 90_000  # a bound on waiting for a job, not a timed check
ENDED = ("completed", "no_object", "failed", "stopped", "cancelled", "interrupted")
SPIN_BUTTONS_PX = 20  # the room a number field's spin buttons take at its right in Chromium (about 15 px)
BACKGROUND = (0xF4, 0xF6, 0xF8)  # the 3D view's background (scene.js COLORS.background)

Page = Any  # playwright.sync_api.Page


# ---------------------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServedCell]:
    with ServedCell(FRANKA, tmp_path_factory.mktemp("web") / "data") as served:
        yield served


@pytest.fixture(scope="module")
def proxy(cell: ServedCell) -> Iterator[CuttableProxy]:
    relay = CuttableProxy((cell.host, cell.port))
    try:
        yield relay
    finally:
        relay.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    shutil.rmtree(ARTIFACTS, ignore_errors=True)
    ARTIFACTS.mkdir(parents=True)
    with sync_api.sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=LAUNCH_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


@pytest.fixture
def open_page(browser: Any, proxy: CuttableProxy, cell: ServedCell) -> Iterator[Callable[..., Page]]:
    """``open_page(role=None, width=1280, height=800, other=None)``: a fresh browser context on the page
    of the module's cell (or of ``other``), logged in with the role's key (typed, then Enter) unless
    ``role`` is None. Script errors fail the test."""
    contexts: list[Any] = []
    errors: list[str] = []

    def open_(role: str | None = None, width: int = 1280, height: int = 800,
              other: ServedCell | None = None) -> Page:
        context = browser.new_context(viewport={"width": width, "height": height}, accept_downloads=True)
        contexts.append(context)
        page = context.new_page()
        page.set_default_timeout(WAIT_MS)
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto((proxy.url if other is None else other.url) + "/")
        if role is not None:
            log_in(page, (other or cell).keys[role])
            page.wait_for_selector("#statusbar:not([hidden])")
        return page

    yield open_
    for context in contexts:
        context.close()
    assert errors == [], errors


def log_in(page: Page, key: str) -> None:
    """Type the key into the focused field and press Enter, as a keyboard user does."""
    assert page.evaluate("() => document.activeElement.id") == "login-key"
    page.keyboard.type(key)
    page.keyboard.press("Enter")


def wait_for(page: Page, expression: str) -> None:
    """Wait until the JavaScript ``expression`` holds (a function: the page's CSP forbids eval)."""
    page.wait_for_function(f"() => {expression}")


def progress_count(page: Page) -> int:
    return int(page.evaluate("() => Number(document.querySelector('.charts').dataset.count || 0)"))


def view_pixels(page: Page) -> np.ndarray:
    """The 3D view's canvas read back (its WebGL drawing buffer, kept for this), (H, W, 3) uint8."""
    url = page.evaluate("() => document.querySelector('#view3d canvas').toDataURL('image/png')")
    image = Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB")
    return np.asarray(image)


def cloud_pixels(page: Page) -> int:
    """Pixels of the 3D view that are the cloud's colours (blue to amber by height) rather than the
    background, the grey grid or the thin coloured lines."""
    rgb = view_pixels(page).astype(int)
    assert rgb.shape[0] > 100 and rgb.shape[1] > 100, rgb.shape
    drawn = np.abs(rgb - np.array(BACKGROUND)).max(axis=2) > 40
    grey = (rgb.max(axis=2) - rgb.min(axis=2)) < 30
    return int(np.count_nonzero(drawn & ~grey))


def text_js(element_id: str) -> str:
    """The JavaScript expression of an element's text, for :func:`wait_for`."""
    return f"document.getElementById('{element_id}').textContent"


def start_watching(served: ServedCell, open_page: Callable[..., Page]) -> tuple[str, Page]:
    """A vs-local scan queued on ``served`` and an operator's page on it, once it shows live progress."""
    with served.client("operator") as client:
        response = client.post("/api/v1/jobs", json={"object": "bunny", "planner": "vs-local",
                                                     "max_time_s": 120.0})
    assert response.status_code == 201, response.text
    job_id = response.json()["id"]
    page = open_page("operator", other=served)
    page.goto(f"{served.url}/#/jobs/{job_id}")
    wait_for(page, "Number(document.querySelector('.charts')?.dataset.count || 0) >= 1")
    wait_for(page, "document.getElementById('job-link').textContent === 'live'")
    return job_id, page


def shot(page: Page, name: str, full_page: bool = False) -> None:
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=full_page)


def read(cell: ServedCell, path: str) -> Any:
    """GET ``path`` of the API with a viewer's key (what the test checks the page against)."""
    with cell.client("viewer") as client:
        response = client.get(path)
    assert response.status_code == 200, response.text
    return response.json()


def events_of(cell: ServedCell, job_id: str) -> list[str]:
    with cell.client("viewer") as client, client.stream("GET", f"/api/v1/jobs/{job_id}/events") as response:
        return re.findall(r"^event: (\w+)$", response.read().decode(), flags=re.MULTILINE)


# ---------------------------------------------------------------------------------------------- docs


def test_the_api_docs_run_under_their_policy_and_list_the_operations(browser: Any, cell: ServedCell) -> None:
    """``/docs`` goes out with a policy that lets only the service's scripts and the page's own start of
    Swagger UI run: the page still draws every operation, and the browser refuses nothing it asks for."""
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    page = context.new_page()
    page.set_default_timeout(WAIT_MS)
    refused: list[str] = []
    page.on("console", lambda message: refused.append(message.text) if message.type == "error" else None)
    page.on("pageerror", lambda error: refused.append(str(error)))
    try:
        answer = page.goto(cell.url + "/docs")
        assert answer is not None and "frame-ancestors 'none'" in answer.headers["content-security-policy"]
        page.wait_for_selector(".opblock-summary-path")
        paths = page.eval_on_selector_all(".opblock-summary-path", "nodes => nodes.map(n => n.textContent)")
        assert "/api/v1/stop" in [p.replace("\u200b", "") for p in paths]
        shot(page, "docs")
    finally:
        context.close()
    assert refused == [], refused


# ---------------------------------------------------------------------------------------------- login


def test_a_wrong_key_is_refused_and_nothing_is_kept(open_page: Callable[..., Page]) -> None:
    page = open_page()
    # the command that makes a key, set as code (not in Markdown's backticks)
    assert page.text_content("#login-help code") == "cell keys create"
    assert "`" not in page.text_content("#login-help")
    shot(page, "login")
    log_in(page, "cell_" + "A" * 43)
    wait_for(page, "document.getElementById('login-error').textContent.length > 0")
    assert "not valid" in page.text_content("#login-error")
    assert page.is_hidden("#statusbar")
    assert page.evaluate("() => sessionStorage.length") == 0
    assert "cell_" not in page.url


def test_a_viewer_may_watch_and_stop_but_is_offered_no_scan(open_page: Callable[..., Page],
                                                            cell: ServedCell) -> None:
    page = open_page("viewer")
    page.wait_for_selector("#no-submit")
    assert page.locator("#f-planner").count() == 0 and page.locator("form.scan-form").count() == 0
    assert page.is_visible("#stop") and page.is_enabled("#stop")
    assert page.is_hidden("#recover") and page.is_hidden("#resume")
    wait_for(page, "document.getElementById('st-name').textContent === 'sim-franka-rgbd'")
    assert page.text_content("#st-mode") == "sim" and page.text_content("#whoami") == "test-viewer (viewer)"
    # the key is kept in this tab's session storage only, never in the address
    assert page.evaluate("() => sessionStorage.getItem('cell.key')") == cell.keys["viewer"]
    assert cell.keys["viewer"] not in page.url
    # this cell has no packing line: nothing shown for it
    assert page.is_hidden("#st-line-item")


def test_a_queued_job_offers_its_stop_only_to_a_key_that_may_cancel(open_page: Callable[..., Page],
                                                                     cell: ServedCell) -> None:
    """A queued job's stop cancels it: the page offered "Stop this job" on one to a viewer, whose key may
    not cancel (the API answers that stop 403), and to an operator as a stop, not as the cancel it is. A
    job waiting in a held queue says so and why (it showed "queued" alone, as if it hung)."""
    with cell.client("operator") as client:
        assert client.post("/api/v1/stop", json={"reason": "a queued job"}).status_code == 200
        job_id = client.post("/api/v1/jobs", json={"object": "bunny", "max_time_s": 1.0}).json()["id"]
    try:
        for role, offered in (("viewer", 0), ("operator", 1)):
            page = open_page(role)
            page.goto(f"{page.url.split('#')[0]}#/jobs/{job_id}")
            wait_for(page, "document.getElementById('job-status')?.textContent === 'queued'")
            assert page.locator("#job-stop").count() == offered, role
            wait_for(page, f"{text_js('job-waiting')}.startsWith('Waiting: the queue is held')")
            assert "a queued job" in page.text_content("#job-waiting"), role  # the hold's reason
        assert page.text_content("#job-stop") == "Cancel this job"
        shot(page, "job-queued-held")
        page.click("#job-stop")  # its reason says what was done: it was "stopped on the operator's page"
        wait_for(page, "document.getElementById('job-status').textContent === 'cancelled'")
        assert "cancelled on the operator's page" in page.text_content("#job-termination")
        # nothing was captured: no empty 3D view, but why there is none
        wait_for(page, "document.getElementById('view-nothing')?.textContent === "
                       "'Nothing to draw: the job was cancelled before it started.'")
        assert page.locator("#view3d").count() == 0
        shot(page, "job-cancelled")
    finally:
        with cell.client("operator") as client:
            if client.get(f"/api/v1/jobs/{job_id}").json()["status"] == "queued":  # the test failed before
                assert client.delete(f"/api/v1/jobs/{job_id}").status_code == 200
            assert client.post("/api/v1/queue/resume").status_code == 200


def test_the_status_bar_shows_the_lines_packml_state_when_there_is_one(
        open_page: Callable[..., Page], cell: ServedCell) -> None:
    """A cell with a packing line has ``line`` in GET /cell (``cell.line.controller.LineSnapshot``); here a
    route adds one, as such a cell reports it, to this line-less cell's answer."""
    page = open_page()

    def with_line(route: Any) -> None:
        status = route.fetch().json()
        status["line"] = {"state": 6, "state_name": "Execute", "mode": 1, "mode_name": "Production"}
        route.fulfill(json=status)

    page.route("**/api/v1/cell", with_line)
    log_in(page, cell.keys["viewer"])
    wait_for(page, "document.getElementById('st-line').textContent === 'Execute (6)'")
    assert page.is_visible("#st-line-item") and page.text_content("#st-line-mode") == "Production"


def test_an_operator_switches_the_line_to_manual_mode_from_the_status_bar(open_page: Callable[..., Page],
                                                                          tmp_path: Path) -> None:
    """In Production the line owns the cell and an operator's scan is refused until Manual: the switch
    is on the page for keys that may change the unit mode (an operator's, not a viewer's)."""
    data = yaml.safe_load(FRANKA.read_text())
    data["line"] = {"initial_mode": "production"}
    config = tmp_path / "line.yaml"
    config.write_text(yaml.safe_dump(data))
    with ServedCell(config, tmp_path / "data", key_prefix="line") as lined:
        viewer = open_page("viewer", other=lined)
        wait_for(viewer, "document.getElementById('st-line-mode').textContent === 'Production'")
        assert viewer.is_hidden("#line-mode")
        page = open_page("operator", other=lined)
        page.wait_for_selector("#line-mode:not([hidden])")
        assert page.text_content("#line-mode") == "Switch to Manual"
        shot(page, "line-production")
        page.click("#line-mode")
        wait_for(page, "document.getElementById('stop-outcome').textContent.startsWith('Line:')")
        assert page.text_content("#stop-outcome") == "Line: Manual mode"
        wait_for(page, "document.getElementById('st-line-mode').textContent === 'Manual'")
        assert page.text_content("#line-mode") == "Switch to Production"
        assert read(lined, "/api/v1/line")["mode_name"] == "Manual"


# ---------------------------------------------------------------------------------------------- scans


def test_the_form_preselects_the_object_cell_scan_takes_by_default(open_page: Callable[..., Page],
                                                                   cell: ServedCell) -> None:
    """The form preselected the first object by name (banana) where ``cell scan`` takes the bunny: it
    takes the one the API marks ``default``, which is the command line's (after a deletion too)."""
    assert [o["name"] for o in read(cell, "/api/v1/objects") if o["default"]] == [DEFAULT_OBJECT]
    page = open_page("operator")
    page.wait_for_selector("#f-object")
    assert page.evaluate("() => document.getElementById('f-object').value") == DEFAULT_OBJECT
    # an empty time budget is the cell's, whose figure the field shows (it said only "cell default")
    budget = read(cell, "/api/v1/cell")["max_time_s"]
    assert budget == yaml.safe_load(FRANKA.read_text())["scan"]["max_time_s"]
    assert page.get_attribute("#f-max_time_s", "placeholder") == f"{budget:g} (the cell's)"
    # shown whole: the field was as narrow as the seed's, and the words were cut at "(the cell's" (9 px
    # were left beside them, under the room Chromium keeps for a number field's spin buttons)
    room = page.eval_on_selector("#f-max_time_s", """e => {
        const style = getComputedStyle(e), text = document.createElement("canvas").getContext("2d");
        text.font = style.font;
        return e.clientWidth - parseFloat(style.paddingLeft) - parseFloat(style.paddingRight)
            - text.measureText(e.placeholder).width; }""")
    assert room >= SPIN_BUTTONS_PX, room


def test_the_form_says_it_is_loading_until_the_api_answers(open_page: Callable[..., Page],
                                                          cell: ServedCell) -> None:
    """The form needs the planners, the cell and the objects: while an answer is held back, its place says
    that it is loading (not a blank panel), and the form replaces that once the answer arrives."""
    page = open_page()
    held: list[Any] = []

    def hold(route: Any) -> None:
        held.append(route)

    page.route("**/api/v1/planners", hold)
    log_in(page, cell.keys["operator"])
    page.wait_for_selector("#form-loading")
    wait_for(page, "document.querySelector('#form-loading h2').textContent === 'New scan'")
    assert "Loading the form" in page.text_content("#form-loading")
    assert page.locator("form.scan-form").count() == 0 and len(held) == 1
    shot(page, "new-scan-loading")
    held[0].continue_()
    page.wait_for_selector("form.scan-form")
    assert page.locator("#form-loading").count() == 0


def test_a_form_that_could_not_load_says_which_call_failed_and_loads_when_tried_again(
        open_page: Callable[..., Page], cell: ServedCell) -> None:
    """The objects' list refused once (as a service just restarted may): the form's place says which
    call failed and how, and offers to try again, which loads it (it had said "The form could not load"
    with no way but reloading the page)."""
    page = open_page()
    refused: list[str] = []

    def once(route: Any) -> None:
        if refused:
            route.continue_()
        else:
            refused.append(route.request.url)
            route.fulfill(status=503, json={"detail": "the cell is starting"})

    page.route("**/api/v1/objects", once)
    log_in(page, cell.keys["operator"])
    page.wait_for_selector("#form-failed")
    text = page.text_content("#form-failed .error")
    assert "the objects (GET /api/v1/objects): the cell is starting (HTTP 503)" in text, text
    shot(page, "new-scan-failed")
    page.click("#form-retry")
    page.wait_for_selector("form.scan-form")
    assert page.locator("#form-failed").count() == 0 and len(refused) == 1


def test_an_operator_runs_a_raster_scan_from_the_form_and_sees_it_complete(
        open_page: Callable[..., Page], cell: ServedCell) -> None:
    page = open_page("operator")
    page.wait_for_selector("#f-planner")
    page.select_option("#f-planner", "raster")
    assert "rings of views" in page.text_content("#hint-planner")
    page.select_option("#f-object", "bunny")
    page.fill("#f-max_time_s", "30")
    page.fill("#f-part_id", "crate-17")
    shot(page, "new-scan")
    # a pose off the table: the API's 422 is shown next to the pose, and nothing is queued
    page.fill("input[aria-label='x [m]']", "2")
    page.click("button[type=submit]")
    wait_for(page, "document.getElementById('err-object_pose').textContent.length > 0")
    assert "table" in page.text_content("#err-object_pose")
    shot(page, "new-scan-refused")
    assert page.url.endswith("/")
    page.fill("input[aria-label='x [m]']", "0")
    page.click("button[type=submit]")

    page.wait_for_url(re.compile(r"#/jobs/[0-9a-f]{16}$"))
    job_id = page.url.rsplit("/", 1)[1]
    page.wait_for_selector("#job-status")
    wait_for(page, "Number(document.querySelector('.charts')?.dataset.count || 0) >= 1")  # progress arrives
    page.wait_for_selector("#result")
    assert page.text_content("#job-status") == "completed"
    job = read(cell, f"/api/v1/jobs/{job_id}")
    result = job["result"]
    assert job["status"] == "completed" and result["planner"] == "raster"
    assert progress_count(page) == events_of(cell, job_id).count("progress") >= 2
    # coverage and the packing dimensions, as the result holds them
    assert page.text_content("#fig-coverage") == f"{result['metrics']['coverage_pct']:.2f} %"
    # H_ROI named with its form (result.json's and progress's h_roi_entropy), in the figures and the curve
    assert result["perception"]["h_roi_entropy"] == "observation_aware"
    h_roi_row = "() => document.getElementById('fig-h_roi').previousElementSibling.textContent"
    assert page.evaluate(h_roi_row) == "H_ROI (observation-aware) at the end"
    assert page.get_attribute("#plot-h_roi", "aria-label").startswith("H_ROI (observation-aware) [nats]: ")
    dims = " × ".join(f"{v:.3f}" for v in result["packing"]["dims_m"])
    assert page.text_content("#fig-dims") == f"{dims} m"
    upper = " × ".join("unbounded" if v is None else f"{v:.3f}" for v in result["packing"]["dims_upper_m"])
    assert page.text_content("#fig-upper") == f"{upper} m"  # the container is chosen on it
    assert page.text_content("#fig-container").startswith(result["packing"]["container"]["name"])
    assert dims in page.text_content("#packing-note")
    wait_for(page, "document.getElementById('job-log').textContent.includes('raster complete')")
    page.wait_for_selector("#img-path-png")  # the sensor's path, a raster scan's too
    assert cloud_pixels(page) > 500, "the 3D view shows no cloud"
    shot(page, "job-completed", full_page=True)

    # a file downloads through a blob URL (the key goes in a header, never in a link)
    with page.expect_download() as download:
        page.click("button[aria-label='Download result.json']")
    saved = json.loads(Path(download.value.path()).read_text())
    assert saved["status"] == "completed" and saved["n_captures"] == result["n_captures"]

    # the jobs table, filtered, opens the job's detail page
    page.click("nav a[href='#/jobs']")
    page.select_option("#filter-planner", "raster")
    page.fill("#filter-part", "crate-17")
    page.click("form.filters button[type=submit]")
    page.wait_for_url(re.compile(r"#/jobs\?planner=raster&part_id=crate-17$"))
    page.wait_for_selector(f"table.jobs a[href='#/jobs/{job_id}']")
    assert page.locator("table.jobs tbody tr").count() == 1 and page.text_content(".pager span") == "1–1 of 1"
    # the part id on one line of text, as it is written: an identifier is not broken at its hyphen
    lines = page.evaluate("() => { const r = document.createRange(); "
                          "r.selectNodeContents(document.querySelector('table.jobs tbody td.part')); "
                          "return r.getClientRects().length; }")
    assert lines == 1 and page.get_attribute("table.jobs tbody td.part", "title") == "crate-17"
    shot(page, "jobs")
    page.click(f"table.jobs a[href='#/jobs/{job_id}']")
    page.wait_for_selector("#result")
    assert page.text_content("#fig-dims") == f"{dims} m"


def upload(page: Page, mesh: Path) -> str:
    """Upload ``mesh`` from the form (the button is disabled until the upload and the object list
    that follows it are done); returns the upload's error, "" when there is none."""
    page.set_input_files("#f-file", str(mesh))
    page.click("#upload")
    wait_for(page, "!document.getElementById('upload').disabled")
    return page.text_content("#err-file")


def chosen_object(page: Page) -> str:
    return str(page.evaluate("() => document.getElementById('f-object').selectedOptions[0].textContent"))


def test_an_operator_uploads_a_mesh_from_the_form(open_page: Callable[..., Page], tmp_path: Path) -> None:
    notes = tmp_path / "notes.txt"
    notes.write_text("not a mesh")
    crate = tmp_path / "crate.ply"
    trimesh.creation.box(extents=(0.06, 0.05, 0.04)).export(crate)
    page = open_page("operator")
    page.wait_for_selector("#f-file")
    assert "not a mesh file" in upload(page, notes)
    assert upload(page, crate) == ""
    assert chosen_object(page) == "crate (0.060 × 0.050 × 0.040 m, uploaded)"


def test_a_mesh_in_millimetres_uploads_with_its_units_and_a_second_one_is_refused_beside_the_upload(
        open_page: Callable[..., Page], tmp_path: Path) -> None:
    """A mesh in millimetres read as metres is refused, the refusal naming millimetres; with the form's
    units set to millimetres it uploads at its size in metres. Uploading it again is refused (409) next
    to the upload, not under Start scan."""
    block = tmp_path / "block_mm.ply"
    trimesh.creation.box(extents=(60.0, 50.0, 40.0)).export(block)
    page = open_page("operator")
    page.wait_for_selector("#f-scale")
    assert "millimetres" in upload(page, block)
    page.select_option("#f-scale", label="millimetres")
    assert upload(page, block) == ""
    assert chosen_object(page) == "block_mm (0.060 × 0.050 × 0.040 m, uploaded)"
    assert "exists already" in upload(page, block)
    assert page.text_content("form.scan-form > p.error") == ""
    shot(page, "upload-refused")


def test_an_operator_deletes_an_uploaded_object_from_the_form(open_page: Callable[..., Page],
                                                              cell: ServedCell, tmp_path: Path) -> None:
    """The form offers to delete the chosen object when it is an upload (not a shipped one); once the
    operator confirms, it is gone from the list and from the cell."""
    tray = tmp_path / "tray.ply"
    trimesh.creation.box(extents=(0.08, 0.06, 0.02)).export(tray)
    page = open_page("operator")
    page.wait_for_selector("#f-file")
    page.select_option("#f-object", "bunny")
    assert page.is_hidden("#delete-object")
    assert upload(page, tray) == ""
    assert page.is_visible("#delete-object")
    shot(page, "new-scan-uploaded")
    asked: list[str] = []
    page.once("dialog", lambda dialog: (asked.append(dialog.message), dialog.accept()))
    page.click("#delete-object")
    wait_for(page, "![...document.getElementById('f-object').options].some((o) => o.value === 'tray')")
    assert asked == ["Delete the uploaded object tray? The jobs that scanned it keep their results."]
    assert page.is_hidden("#delete-object") and page.text_content("#err-object") == ""
    assert page.evaluate("() => document.getElementById('f-object').value") == DEFAULT_OBJECT  # as at first
    assert "tray" not in {o["name"] for o in read(cell, "/api/v1/objects")}


def test_a_number_field_that_holds_no_number_is_refused_beside_it(open_page: Callable[..., Page]) -> None:
    """Text typed into the time budget, the pose or the seed is said to be no number, next to the field,
    and nothing is submitted (it had been dropped: the job started with the default)."""
    page = open_page("operator")
    page.wait_for_selector("#f-max_time_s")
    posted: list[str] = []
    page.on("request", lambda r: posted.append(r.url) if r.method == "POST" else None)
    for selector, typed in (("#f-max_time_s", "ten"), ("input[aria-label='yaw [deg]']", "3e"),
                            ("#f-seed", "-")):
        page.click(selector)
        page.keyboard.press("Control+A")
        page.keyboard.type(typed)
    page.click("button[type=submit]")
    wait_for(page, f"{text_js('err-max_time_s')}.length > 0")
    assert "Not a number" in page.text_content("#err-max_time_s")
    assert "x, y and yaw are numbers" in page.text_content("#err-object_pose")
    assert "Not a number" in page.text_content("#err-seed")
    assert page.get_attribute("#f-max_time_s", "aria-invalid") == "true"
    shot(page, "new-scan-not-a-number")
    assert posted == [] and page.url.endswith("/")


def test_a_live_vs_local_scan_survives_a_cut_and_the_stop_key_stops_it(
        open_page: Callable[..., Page], cell: ServedCell, proxy: CuttableProxy) -> None:
    with cell.client("operator") as client:
        response = client.post("/api/v1/jobs", json={"object": "bunny", "planner": "vs-local",
                                                     "max_time_s": 120.0})
    assert response.status_code == 201, response.text
    job_id = response.json()["id"]
    page = open_page("operator")
    page.click("#running-now a")  # the job running now, from the first view
    page.wait_for_url(re.compile(f"#/jobs/{job_id}$"))
    wait_for(page, "Number(document.querySelector('.charts')?.dataset.count || 0) >= 2")
    wait_for(page, "document.getElementById('job-link').textContent === 'live'")

    # every connection cut: the page says so, reconnects by itself and resumes after the last event
    assert proxy.cut() > 0
    wait_for(page, "document.getElementById('job-link').textContent.includes('reconnecting')")
    wait_for(page, "document.getElementById('job-link').textContent === 'live'")
    before = progress_count(page)
    wait_for(page, f"Number(document.querySelector('.charts').dataset.count) > {before}")
    assert cloud_pixels(page) > 500, "the 3D view shows no live cloud"
    shot(page, "job-live")

    page.keyboard.press("Escape")  # STOP
    wait_for(page, "document.getElementById('stop-outcome').textContent.startsWith('STOP:')")
    assert "the arm was commanded to stop" in page.text_content("#stop-outcome")
    wait_for(page, "document.getElementById('job-status').textContent === 'stopped'")
    page.wait_for_selector("#result")
    assert progress_count(page) == events_of(cell, job_id).count("progress"), "progress was lost"
    assert page.text_content("#result-termination").startswith("operator stop: ")
    assert "operator stop at " in page.text_content("#safety")  # not "motion stopped by the guard"
    page.wait_for_selector("#img-servo-png")
    assert page.evaluate("() => document.getElementById('img-servo-png').naturalWidth") > 100

    # STOP held the queue: an operator resumes it from the status bar
    page.wait_for_selector("#resume:not([hidden])")
    page.click("#resume")
    page.wait_for_selector("#resume", state="hidden")
    assert read(cell, "/api/v1/cell")["queue"]["held"] is None


def test_the_safety_section_counts_the_limits_applied_in_times_not_as_factors(
        open_page: Callable[..., Page], cell: ServedCell) -> None:
    """result.json's ``safety.clamps`` count how often a limit was applied: the page wrote them
    "tcp acceleration ×787", which reads as a limit exceeded 787-fold."""
    with cell.client("operator") as client:
        job = client.post("/api/v1/jobs", json={"object": "bunny", "max_time_s": 5.0}).json()
    clamps = cell.wait_job(job["id"], ENDED)["result"]["safety"]["clamps"]
    assert clamps, "a vs-local scan whose limits were never applied: nothing to show"
    page = open_page("operator")
    page.goto(f"{page.url.split('#')[0]}#/jobs/{job['id']}")
    page.wait_for_selector("#safety")
    counts = ", ".join(f"{kind.replace('_', ' ')} {n} {'time' if n == 1 else 'times'}"
                       for kind, n in clamps.items())
    assert page.text_content("#safety p") == f"Limits applied: {counts}."  # its first paragraph


def test_the_pages_fit_a_1024x768_tablet(open_page: Callable[..., Page], cell: ServedCell) -> None:
    ended = read(cell, "/api/v1/jobs?status=stopped&status=completed&limit=1")["items"]
    if not ended:  # this test alone: a job of its own
        with cell.client("operator") as client:
            job = client.post("/api/v1/jobs", json={"object": "bunny", "max_time_s": 5.0}).json()
        ended = [cell.wait_job(job["id"], ("completed",))]
    page = open_page("operator", width=1024, height=768)
    shot(page, "new-scan-1024")
    page.goto(f"{page.url.split('#')[0]}#/jobs/{ended[0]['id']}")
    page.wait_for_selector("#result")
    wait_for(page, "document.querySelector('#view3d canvas') !== null")
    assert page.evaluate("() => document.documentElement.scrollWidth") <= 1024
    assert cloud_pixels(page) > 500
    shot(page, "job-stopped-1024")
    page.goto(f"{page.url.split('#')[0]}#/jobs")
    page.wait_for_selector("table.jobs tbody a")
    assert page.evaluate("() => document.documentElement.scrollWidth") <= 1024
    shot(page, "jobs-1024")


def test_the_jobs_table_follows_its_jobs_while_it_is_shown(open_page: Callable[..., Page],
                                                            cell: ServedCell) -> None:
    """A job queued while the table is shown appears in it and its row follows it to its end, without
    the operator reloading; once the view is left the table is no longer read."""
    page = open_page("operator")
    page.goto(f"{page.url.split('#')[0]}#/jobs")
    page.wait_for_selector("table.jobs tbody tr")
    with cell.client("operator") as client:
        response = client.post("/api/v1/jobs", json={"object": "bunny", "planner": "raster",
                                                     "max_time_s": 5.0})
    assert response.status_code == 201, response.text
    link = f"table.jobs a[href='#/jobs/{response.json()['id']}']"
    page.wait_for_selector(link)
    status = cell.wait_job(response.json()["id"], ENDED)["status"]
    wait_for(page, f"document.querySelector(\"{link}\").closest('tr').querySelector('.status').textContent"
                   f" === '{status}'")
    read_again: list[str] = []
    page.on("request", lambda r: read_again.append(r.url) if "/api/v1/jobs?" in r.url else None)
    page.click("nav a[href='#/']")
    page.wait_for_selector("form.scan-form")
    page.wait_for_timeout(6000)  # beyond the table's period (5 s)
    assert read_again == []


def test_a_part_id_filter_that_matches_nothing_says_a_part_id_is_matched_whole(
        open_page: Callable[..., Page]) -> None:
    """The API matches ``part_id`` whole: an operator who typed the start of an id ("crate" for
    "crate-17") was told only "No job matches.", as if the part had never been scanned."""
    page = open_page("operator")
    page.click("nav a[href='#/jobs']")
    page.fill("#filter-part", "crat")
    page.click("form.filters button[type=submit]")
    page.wait_for_url(re.compile(r"#/jobs\?part_id=crat$"))
    wait_for(page, "document.querySelector('.pager span')?.textContent === '0 jobs'")  # the page is in
    assert page.text_content("table.jobs tbody td") == ('No job matches. A part id is matched whole, not in '
                                                        'part: "crat" finds the jobs of exactly that id.')
    assert page.get_attribute("#filter-part", "placeholder") == "the whole id"  # said before asking, too


def test_a_cell_busy_with_large_answers_is_waited_for_and_said_busy_not_failed(
        open_page: Callable[..., Page]) -> None:
    """A list refused 503 with a Retry-After (the cell's queue of large answers is full, cell/api/bulk.py:
    here a route answers the first two so, as the cell does) was an error in the table. The page waits
    the Retry-After, says on the status bar that the cell is busy, and asks again."""
    page = open_page("viewer")
    asked: list[float] = []

    def busy_twice(route: Any) -> None:
        asked.append(time.monotonic())
        if len(asked) > 2:
            route.continue_()
        else:
            route.fulfill(status=503, headers={"Retry-After": "1"}, json={
                "detail": "32 requests for large answers (job lists, file lists, the line's history, clouds, "
                          "retention) are waiting already: ask again later"})

    page.route(re.compile(r"/api/v1/jobs\?"), busy_twice)
    page.goto(f"{page.url.split('#')[0]}#/jobs")
    page.wait_for_function("() => !document.getElementById('st-busy').hidden", timeout=10_000)
    assert page.text_content("#st-busy") == "cell busy with large answers: asking again in 1 s"
    shot(page, "jobs-busy")
    page.wait_for_selector(".pager span")  # the page of jobs is shown
    wait_for(page, "document.getElementById('st-busy').hidden")
    assert page.locator("table.jobs td.error").count() == 0 and page.text_content("#jobs-note") == ""
    assert len(asked) >= 3 and all(b - a >= 0.9 for a, b in itertools.pairwise(asked[:3])), asked
    shot(page, "jobs-after-busy")


def test_a_cell_busy_beyond_every_try_says_so(open_page: Callable[..., Page]) -> None:
    """Still busy after BUSY_TRIES calls (api.js), the table says the cell is busy, and reads again later."""
    page = open_page("viewer")
    asked: list[str] = []

    def busy(route: Any) -> None:
        asked.append(route.request.url)
        route.fulfill(status=503, headers={"Retry-After": "0"}, json={"detail": "ask again later"})

    page.route(re.compile(r"/api/v1/jobs\?"), busy)
    page.goto(f"{page.url.split('#')[0]}#/jobs")
    page.wait_for_selector("table.jobs td.error")
    assert page.text_content("table.jobs td.error") == "the cell is busy, asked 5 times: ask again later"
    assert len(asked) == 5


def test_a_page_past_the_last_job_says_so_and_leads_back(open_page: Callable[..., Page],
                                                         cell: ServedCell) -> None:
    if read(cell, "/api/v1/jobs?limit=1")["total"] == 0:  # this test alone: a job of its own
        with cell.client("operator") as client:
            client.post("/api/v1/jobs", json={"object": "bunny", "planner": "raster", "max_time_s": 5.0})
    total = read(cell, "/api/v1/jobs?limit=1")["total"]
    assert 0 < total <= 20
    page = open_page("operator")
    page.goto(f"{page.url.split('#')[0]}#/jobs?offset=200")
    wait_for(page, "document.querySelector('.pager span') !== null")
    assert page.text_content(".pager span") == f"no job from 201 on ({total} in all)"
    assert page.is_disabled(".pager button:has-text('Older')")
    page.click(".pager button:has-text('Newer')")  # to the last page that has jobs: here the first
    page.wait_for_url(re.compile(r"#/jobs$"))
    wait_for(page, f"document.querySelector('.pager span')?.textContent === '1–{total} of {total}'")


def test_an_operator_recovers_the_arm_after_a_protective_stop(open_page: Callable[..., Page],
                                                              tmp_path: Path) -> None:
    data = yaml.safe_load(FRANKA.read_text())
    data["sim"]["faults"] = [{"at_s": 3.5, "kind": "protective stop"}]
    config = tmp_path / "faulty.yaml"
    config.write_text(yaml.safe_dump(data))
    with ServedCell(config, tmp_path / "data", key_prefix="faulty") as faulty:
        with faulty.client("operator") as client:
            job = client.post("/api/v1/jobs", json={"object": "bunny", "max_time_s": 8.0}).json()
        faulty.wait_job(job["id"], ("stopped",))
        viewer = open_page("viewer", other=faulty)
        wait_for(viewer, "document.getElementById('st-arm').textContent.startsWith('protective stop')")
        assert viewer.is_hidden("#recover")  # a viewer may not recover
        page = open_page("operator", other=faulty)
        page.wait_for_selector("#recover:not([hidden])")
        assert "recover the arm first" in page.text_content("#st-held")
        page.wait_for_selector("form.scan-form")
        shot(page, "protective-stop")
        page.click("#recover")
        wait_for(page, "document.getElementById('stop-outcome').textContent.startsWith('Recover:')")
        assert "recovered" in page.text_content("#stop-outcome")
        assert outcome_background(page) == OUTCOME_GREEN  # a recovery that went through is no alarm
        shot(page, "recovered")
        wait_for(page, "document.getElementById('st-arm').textContent === 'idle'")
        page.wait_for_selector("#recover", state="hidden")


def test_a_stop_for_the_services_shutdown_is_said_as_such_not_as_the_guards(
        open_page: Callable[..., Page], cell: ServedCell) -> None:
    """A job that the service's shutdown stopped (SIGTERM of ``cell serve``) records ``shutdown stop:``;
    its safety section said "motion stopped by the guard" for it. The job's answer is given that stop by a
    route, as such a job's result.json has it."""
    with cell.client("operator") as client:
        job_id = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 1.0}).json()["id"]
    cell.wait_job(job_id, ENDED)
    page = open_page("viewer")

    def shut_down(route: Any) -> None:
        answer = route.fetch().json()
        shutdown = {"t": 0.5, "reason": "shutdown stop: the service is shutting down"}
        answer["result"]["safety"]["stops"] = [shutdown]
        route.fulfill(json=answer)

    page.route(f"**/api/v1/jobs/{job_id}", shut_down)
    page.goto(f"{page.url.split('#')[0]}#/jobs/{job_id}")
    page.wait_for_selector("#safety")
    said = page.text_content("#safety")
    assert "stop for the service's shutdown at 0.50 s: the service is shutting down" in said, said
    assert "by the guard" not in said


def test_a_job_whose_cloud_and_path_do_not_load_keeps_its_view_and_is_not_said_to_have_captured_nothing(
        open_page: Callable[..., Page], cell: ServedCell) -> None:
    """A job that captured, whose cloud and path the page could not load (the network, a busy cell): the
    page had decided from what loaded that the job captured nothing, and removed its 3D view."""
    with cell.client("operator") as client:
        job_id = client.post("/api/v1/jobs", json={"object": "cube", "max_time_s": 3.0}).json()["id"]
    job = cell.wait_job(job_id, ENDED)
    assert job["result"]["n_captures"] > 0, job
    page = open_page("viewer")

    def without_packing(route: Any) -> None:  # no packing box to draw either: only the cloud and the path
        answer = route.fetch().json()
        answer["result"].pop("packing", None)
        route.fulfill(json=answer)

    page.route(f"**/api/v1/jobs/{job_id}", without_packing)
    # its events too, whose progress draws the path: the page then asks the job's record whether it ended
    page.route(re.compile(rf"/api/v1/jobs/{job_id}/(cloud|files/trajectory\.csv|events)"),
               lambda route: route.abort())
    page.goto(f"{page.url.split('#')[0]}#/jobs/{job_id}")
    page.wait_for_selector(".live[data-ended='true']", state="attached")
    assert page.locator("#view-nothing").count() == 0
    assert page.locator("#view3d").count() == 1


def test_a_job_id_in_the_address_is_only_ever_a_job_id(open_page: Callable[..., Page]) -> None:
    """Whatever follows #/jobs/ is asked for as a job, never as another path of the API (``..%2Fcell``
    had shown the cell's status as a job) nor a resource a URL's dot segments lead to."""
    page = open_page("operator")
    for fragment in ("..%2Fcell", "..", "%3Cb%3Ex"):
        page.goto(f"{page.url.split('#')[0]}#/jobs/{fragment}")
        page.wait_for_selector("#main p.error")
        assert "HTTP 404" in page.text_content("#main p.error"), fragment
        assert page.locator("#job-status").count() == 0
        page.goto(f"{page.url.split('#')[0]}#/")
        page.wait_for_selector("form.scan-form")


# ---------------------------------------------------------------------------------------------- a cell away


def test_a_job_the_restarted_service_ended_is_shown_ended_and_nothing_is_polled_any_more(
        open_page: Callable[..., Page], tmp_path: Path) -> None:
    """The service dies under a watched job and comes back: the job is ``interrupted`` (or finished by
    its worker), and the restarted service's event ids begin at 1 again, so the stream resumed with
    Last-Event-ID brings nothing. The page reads the job's status from the REST API, shows it with its
    result and stops polling; a STOP that failed while the service was away stays said (the arm may
    still move), now with when the cell answered again."""
    with ServedCell(FRANKA, tmp_path / "data", key_prefix="restart") as served:
        job_id, page = start_watching(served, open_page)
        served.kill()
        wait_for(page, "document.getElementById('job-link').textContent.includes('reconnecting')")
        wait_for(page, "document.getElementById('st-link').textContent.startsWith('status not updated for')")
        page.keyboard.press("Escape")
        wait_for(page, f"{text_js('stop-failed-text')}.includes('failed')")
        served.start()
        job = served.wait_job(job_id, ENDED)
        page.wait_for_selector("#result")
        assert page.text_content("#job-status") == job["status"]
        assert page.text_content("#job-link") == "" and page.locator("#job-stop").count() == 0
        wait_for(page, f"{text_js('stop-failed-text')}.includes('answers again since')")
        assert "failed: the cell did not answer" in page.text_content("#stop-failed-text")
        shot(page, "job-after-restart")
        polled: list[str] = []
        page.on("request", lambda r: polled.append(r.url) if re.search(r"/(events|cloud)\b", r.url) else None)
        page.wait_for_timeout(5000)  # the old page asked for /events every 0.5 s and the cloud every 1.5 s
        assert polled == []


STOP_RED, OUTCOME_GREEN = "rgb(92, 43, 43)", "rgb(43, 92, 58)"  # the bar's outcome line (app.css)


def outcome_background(page: Page) -> str:
    """The background colour of the status bar's outcome line, as the browser draws it."""
    return page.eval_on_selector("#stop-outcome", "e => getComputedStyle(e).backgroundColor")


def test_a_stops_word_that_the_queue_is_held_gives_way_once_it_is_resumed_elsewhere(
        open_page: Callable[..., Page], cell: ServedCell) -> None:
    """The STOP's outcome says the queue is held; resumed from elsewhere (``cell jobs resume``, another
    page), the bar went on saying so for the rest of the shift, beside a queue shown running."""
    page = open_page("operator")
    page.click("#stop")
    wait_for(page, f"{text_js('stop-outcome')}.startsWith('STOP:')")
    assert "the queue is held" in page.text_content("#stop-outcome")
    assert outcome_background(page) == STOP_RED
    with cell.client("operator") as client:
        assert client.post("/api/v1/queue/resume").status_code == 200
    # the bar's queue and the outcome come from the same poll of the status
    wait_for(page, f"!{text_js('st-queue')}.includes('held')")
    assert page.text_content("#stop-outcome") == "The queue runs again."
    assert outcome_background(page) == OUTCOME_GREEN  # no alarm: the STOP's red is for stops
    # an outcome said after the STOP's is not the STOP's to replace: here a line's mode switch that failed
    # (a route gives this line-less cell a line in Production, and refuses the switch)

    def with_line(route: Any) -> None:
        status = route.fetch().json()
        status["line"] = {"state": 2, "state_name": "Stopped", "mode": 1, "mode_name": "Production"}
        route.fulfill(json=status)

    page.route("**/api/v1/cell", with_line)
    page.route("**/api/v1/line/mode", lambda route: route.fulfill(status=500, json={"detail": "refused"}))
    page.click("#stop")
    wait_for(page, f"{text_js('stop-outcome')}.startsWith('STOP:')")
    page.wait_for_selector("#line-mode:not([hidden])")
    page.click("#line-mode")
    wait_for(page, f"{text_js('stop-outcome')}.startsWith('Line mode switch failed')")
    with cell.client("operator") as client:
        assert client.post("/api/v1/queue/resume").status_code == 200
    wait_for(page, f"!{text_js('st-queue')}.includes('held')")
    assert page.text_content("#stop-outcome").startswith("Line mode switch failed"), "replaced"


def test_a_refused_stop_stays_said_with_the_cells_answer_until_dismissed_or_a_stop_succeeds(
        open_page: Callable[..., Page], cell: ServedCell) -> None:
    """STOP answered 503 while the status polls failed too: the failure says the cell answered, with
    what, and stays once the status answers again (it had become "STOP ... got no answer; the cell
    answers again now" after one poll); Dismiss clears it, and so does a STOP that succeeds."""
    page = open_page("operator")
    page.wait_for_selector("#f-planner")

    def unavailable(route: Any) -> None:
        route.fulfill(status=503, json={"detail": "Service Unavailable"})

    stops: list[str] = []

    def stop_unavailable(route: Any) -> None:  # a Retry-After, as a proxy may send: a STOP is not asked again
        stops.append(route.request.method)
        route.fulfill(status=503, headers={"Retry-After": "1"}, json={"detail": "Service Unavailable"})

    page.route("**/api/v1/cell", unavailable)
    page.route("**/api/v1/stop", stop_unavailable)
    wait_for(page, f"{text_js('st-link')}.startsWith('status not updated for')")
    page.click("#stop")
    wait_for(page, f"{text_js('stop-failed-text')}.includes('failed')")
    assert stops == ["POST"]
    refused = page.text_content("#stop-failed-text")
    assert "failed: the cell answered with an error: Service Unavailable (HTTP 503)" in refused, refused
    assert "emergency stop" in refused and page.text_content("#stop-outcome") == ""
    page.unroute("**/api/v1/cell")
    wait_for(page, f"{text_js('st-link')} === ''")
    wait_for(page, f"{text_js('stop-failed-text')}.includes('answers again since')")
    page.wait_for_timeout(3000)  # polls that get through do not end the warning
    text = page.text_content("#stop-failed-text")
    assert text.startswith(refused) and "no answer" not in text, text
    assert page.is_visible("#stop-failed")
    shot(page, "stop-refused")
    page.click("#stop-dismiss")
    assert page.is_hidden("#stop-failed")

    page.keyboard.press("Escape")
    wait_for(page, f"{text_js('stop-failed-text')}.includes('HTTP 503')")
    page.unroute("**/api/v1/stop")
    try:
        page.click("#stop")
        wait_for(page, "document.getElementById('stop-outcome').textContent.startsWith('STOP: ')")
        assert page.is_hidden("#stop-failed")
    finally:
        with cell.client("operator") as client:
            assert client.post("/api/v1/queue/resume").status_code == 200


def test_a_hung_service_shows_its_age_and_stop_says_it_got_no_answer_and_stays_pressable(
        open_page: Callable[..., Page], tmp_path: Path) -> None:
    """The service stopped (SIGSTOP) while a job runs: connections are accepted and never answered. The
    status bar says how old its status is, the job is no longer called live, and STOP says it waits,
    then that it got no answer, and can be pressed again; once the service runs again STOP works."""
    with ServedCell(FRANKA, tmp_path / "data", key_prefix="hung") as served:
        job_id, page = start_watching(served, open_page)
        assert served.proc is not None
        os.kill(served.proc.pid, signal.SIGSTOP)
        try:
            wait_for(page, f"{text_js('st-link')}.startsWith('status not updated for')")
            assert page.evaluate("() => document.getElementById('statusbar').classList.contains('stale')")
            wait_for(page, f"{text_js('job-link')}.startsWith('no news from the cell')")
            page.click("#stop")
            wait_for(page, f"{text_js('stop-outcome')}.includes('waiting for the cell')")
            assert page.is_enabled("#stop") and page.get_attribute("#stop", "aria-busy") == "true"
            wait_for(page, f"{text_js('stop-failed-text')}.includes('failed')")
            assert "did not answer within 10 s" in page.text_content("#stop-failed-text")
            assert "press STOP again" in page.text_content("#stop-failed-text")
            assert "Esc" not in page.text_content("#stop-failed-text")  # had been "STOP Esc failed"
            assert page.is_enabled("#stop") and page.get_attribute("#stop", "aria-busy") is None
            shot(page, "service-hung")
        finally:
            os.kill(served.proc.pid, signal.SIGCONT)
        wait_for(page, "document.getElementById('st-link').textContent === ''")
        assert not page.evaluate("() => document.getElementById('statusbar').classList.contains('stale')")
        page.click("#stop")
        wait_for(page, "document.getElementById('stop-outcome').textContent.startsWith('STOP: ')")
        assert page.is_hidden("#stop-failed")  # a STOP that succeeded ends the failure's warning
        assert served.wait_job(job_id, ENDED)["status"] == "stopped"


# ---------------------------------------------------------------------------------------------- phones


@pytest.mark.parametrize(("width", "height"), [(320, 640), (390, 844)])
def test_stop_stays_in_view_on_a_phone_with_the_queue_held(open_page: Callable[..., Page], cell: ServedCell,
                                                           width: int, height: int) -> None:
    """The held queue adds Resume to the bar: STOP stays wholly on the screen and reachable, nothing
    scrolls sideways, and the bar leaves most of the screen to the views."""
    with cell.client("operator") as client:
        assert client.post("/api/v1/stop", json={"reason": "phone test"}).status_code == 200
        try:
            page = open_page("operator", width=width, height=height)
            page.wait_for_selector("#resume:not([hidden])")
            page.wait_for_selector("form.scan-form")
            held = page.text_content("#st-held") or ""
            assert "phone test" in held and "(since " in held, held  # the hold outlives a restart: since when
            box = page.locator("#stop").bounding_box()
            assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= width, box
            assert page.evaluate("() => document.documentElement.scrollWidth") <= width
            hit = page.evaluate(f"() => document.elementFromPoint({box['x'] + box['width'] / 2}, "
                                f"{box['y'] + box['height'] / 2})?.closest('#stop') !== null")
            assert hit, "STOP is covered"
            bar = page.locator("#statusbar").bounding_box()
            assert bar is not None and bar["height"] <= 0.3 * height, bar
            shot(page, f"phone-{width}-held")
            page.click("#stop")
            wait_for(page, "document.getElementById('stop-outcome').textContent.startsWith('STOP: ')")
            assert page.text_content("#stop-outcome").count("queue is held") == 1  # had been said twice
        finally:
            client.post("/api/v1/queue/resume")
