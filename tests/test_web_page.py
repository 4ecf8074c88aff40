"""The web page at ``/`` in a real browser: Debian's headless Chromium driven by Playwright,
against the embedded server (API + worker) on loopback with an API key and a toy scene.

One user's session, in order: the page asks for the key (the API's 401 shown as worded),
the key is typed once; a broken zip is refused with the API's own message; the toy zip is
uploaded; a 1-step fine-tune runs to the end with its step, loss curve and before/after
metrics; a test view is opened: the enhanced image's pixels are exactly the ones ``/enhance``
returned, the metrics and neighbours are the library's; the slider is dragged with the mouse
and moved with the keyboard, and what the screen shows left and right of it is the render's
and the enhanced image's pixels. Then: a cancelled and a failed job show their reason; no
layout overflows at 1280x800 and 390x844; every control has a label; and the page never
contacted any other origin.
"""

from __future__ import annotations

import io
import json

import httpx
import pytest

from tests.browser_helpers import browser, embedded_server, pixels_of_img, wait_for
from tests.service_helpers import make_checkpoint, make_scene, wait_until, zip_folder

KEY = "page-key-4c2e9a71d0"
AUTH = {"Authorization": f"Bearer {KEY}"}
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    root = tmp_path_factory.mktemp("toy")
    scene = make_scene(root / "scene", seed=2)
    (root / "scene.zip").write_bytes(zip_folder(root / "scene"))
    make_checkpoint(root / "micro.safetensors")
    (root / "broken.zip").write_bytes(b"this is not a zip archive")
    return {"root": root, "scene": scene, "zip": root / "scene.zip", "ckpt": root / "micro.safetensors",
            "broken": root / "broken.zip"}


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    with embedded_server(data, log_path=data.parent / f"{data.name}-server.log", api_key=KEY,
                         finetune_evaluate="true") as url:
        with httpx.Client(base_url=url, headers=AUTH, timeout=120) as api:
            yield {"url": url, "api": api, "data": data}


@pytest.fixture(scope="module")
def chromium():
    with browser() as b:
        yield b


@pytest.fixture(scope="module")
def session(chromium, site):
    """One browser tab for the ordered user session; records every URL it requested."""
    context = chromium.new_context(viewport={"width": 1280, "height": 800}, device_scale_factor=1)
    page = context.new_page()
    requested: list[str] = []
    page.on("request", lambda r: requested.append(r.url))
    enhance_answers: list = []

    def through(route):
        # The real request goes to the server; its answer is recorded and handed to the page
        # unchanged (Chromium does not keep the bodies of POST answers for later reading).
        answer = route.fetch()
        enhance_answers.append({"status": answer.status, "headers": answer.headers, "body": answer.body(),
                                "method": route.request.method})
        route.fulfill(response=answer)

    page.route("**/enhance", through)
    state = {"page": page, "requested": requested, "enhance": enhance_answers}
    yield state
    context.close()
    origin = site["url"] + "/"
    foreign = [u for u in requested if not (u.startswith(origin) or u.startswith("blob:" + site["url"]))]
    assert not foreign, f"the page contacted other origins: {foreign}"


def _text(page, selector: str) -> str:
    return page.locator(selector).inner_text().strip()


def test_1_key_then_upload_with_api_errors_as_worded(session, site, toy):
    page = session["page"]
    page.goto(site["url"] + "/")
    anon = httpx.get(site["url"] + "/scenes", timeout=30).json()["error"]["message"]
    page.locator("#scenes-error").wait_for(state="visible", timeout=30_000)
    assert _text(page, "#scenes-error .msg") == anon
    assert _text(page, "#scenes-error .code") == "unauthorized"

    page.get_by_label("API key").fill(KEY)
    page.get_by_label("API key").press("Enter")
    wait_for(page, "() => document.getElementById('scenes-error').hidden", timeout_s=30)
    assert page.evaluate("sessionStorage.getItem('roguenerf.apiKey')") == KEY
    assert page.get_by_label("API key").input_value() == ""   # not left in the form
    assert page.locator("#scenes-table tbody tr").count() == 0
    assert page.locator("#scenes-empty").is_visible()

    # A broken zip: the API's words, exactly.
    expected = site["api"].post("/scenes", files={"archive": ("broken.zip", toy["broken"].read_bytes(),
                                                              "application/zip")}).json()["error"]
    page.get_by_label("Scene zip").set_input_files(str(toy["broken"]))
    page.get_by_role("button", name="Upload", exact=True).click()
    page.locator("#scenes-error").wait_for(state="visible", timeout=30_000)
    assert _text(page, "#scenes-error .msg") == expected["message"]
    assert _text(page, "#scenes-error .code") == expected["code"] == "invalid_archive"

    page.get_by_label("Scene zip").set_input_files(str(toy["zip"]))
    page.get_by_label("Checkpoint (optional, .safetensors)").set_input_files(str(toy["ckpt"]))
    page.get_by_role("button", name="Upload", exact=True).click()
    page.locator("#scenes-table tbody tr").first.wait_for(timeout=60_000)
    listed = site["api"].get("/scenes").json()["items"]
    assert len(listed) == 1
    scene = listed[0]
    session["scene_id"] = scene["id"]
    assert page.locator("#upload-progress").evaluate("e => e.value") == 100
    assert _text(page, "#upload-status") == f"registered {scene['id']} (8 views)"
    assert page.locator("#scenes-error").is_hidden()
    cells = page.locator("#scenes-table tbody tr").first.locator("td").all_inner_texts()
    assert cells[:4] == [scene["id"], "8 (6 / 2)", "64×48", "v1"]


def test_2_one_step_finetune_runs_to_the_end(session, site):
    page, sid = session["page"], session["scene_id"]
    page.get_by_role("link", name="Fine-tuning").click()
    assert page.locator("#finetune").get_by_label("Scene", exact=True).input_value() == sid
    page.get_by_label("Budget").fill("1")
    page.get_by_label("Unit").select_option("steps")
    page.get_by_role("button", name="Start fine-tuning").click()
    wait_for(page, "() => ['succeeded', 'failed', 'cancelled'].includes(document.getElementById('job').dataset.state)",
             timeout_s=240)
    job_id = _text(page, "#job-id")
    job = site["api"].get(f"/jobs/{job_id}").json()
    assert job["scene_id"] == sid and job["request"] == {"steps": 1}
    assert job["state"] == "succeeded", job
    assert _text(page, "#job-state") == "succeeded"
    assert _text(page, "#job-step") == "1 of 1"
    assert _text(page, "#job-version") == "v2" and job["checkpoint_version"] == 2
    assert page.locator("#job-progress").evaluate("e => e.value") == 1
    assert _text(page, "#job-loss") == f"{job['loss']:.4g}" or float(_text(page, "#job-loss")) == pytest.approx(job["loss"], rel=1e-3)
    assert page.locator("#loss-curve").get_attribute("data-points") == "1"
    assert page.locator("#job-error").is_hidden()
    assert page.locator("#ft-cancel").is_disabled()
    rows = page.locator("#job-metrics tbody tr")
    assert rows.count() == 3
    shown = [rows.nth(i).locator("td").all_inner_texts() for i in range(3)]
    wanted = [job["before"]["render"], job["before"]["enhanced"], job["after"]["enhanced"]]
    assert shown == [[f"{m['psnr']:.2f}", f"{m['ssim']:.4f}"] for m in wanted]
    assert job["after"]["enhanced"] != job["before"]["enhanced"]


def test_3_compare_shows_what_enhance_returned_and_the_slider_moves(session, site, toy):
    from PIL import Image

    from roguenerf import psnr, ssim
    from roguenerf.imageio import read_image

    page, sid, api = session["page"], session["scene_id"], site["api"]
    page.get_by_role("link", name="Compare").click()
    wait_for(page, "() => document.getElementById('compare').dataset.ready === 'true'", timeout_s=120)
    t0, t1 = toy["scene"].indices("test")
    assert page.get_by_label("Test view").input_value() == str(t0)
    assert len(session["enhance"]) == 1
    answer = session["enhance"][0]
    assert answer["status"] == 200 and answer["method"] == "POST"
    returned = answer["body"]

    # The displayed enhanced image is the /enhance answer, pixel for pixel (and the same
    # request made outside the browser gives the same pixels).
    decoded = Image.open(io.BytesIO(returned)).convert("RGB")
    for selector in ("#img-enhanced", "#cmp-after"):
        w, h, rgb = pixels_of_img(page, selector)
        assert (w, h) == (64, 48) and rgb == decoded.tobytes(), selector
    view = api.get(f"/scenes/{sid}/views", params={"split": "test"}).json()["items"][0]
    again = api.post("/enhance", data={"scene_id": sid, "camera": json.dumps(view["camera"])},
                     files={"render": ("r.png", api.get(f"/scenes/{sid}/views/{t0}/render").content, "image/png"),
                            "depth": ("d.npy", api.get(f"/scenes/{sid}/views/{t0}/depth").content, "x/y")})
    assert Image.open(io.BytesIO(again.content)).convert("RGB").tobytes() == decoded.tobytes()
    render_img = Image.open(io.BytesIO(api.get(f"/scenes/{sid}/views/{t0}/render").content)).convert("RGB")
    assert pixels_of_img(page, "#cmp-before")[2] == render_img.tobytes()
    assert pixels_of_img(page, "#img-photo")[2] == Image.open(
        io.BytesIO(api.get(f"/scenes/{sid}/views/{t0}/photo").content)).convert("RGB").tobytes()
    assert render_img.tobytes() != decoded.tobytes()

    # Metrics: the library's psnr/ssim of the displayed images against the photo.
    scene = toy["scene"]
    photo = scene.photo(t0)[None]
    enh = read_image(returned)[None]
    assert _text(page, "#m-enhanced-psnr") == f"{float(psnr(enh, photo)[0]):.2f}"
    assert _text(page, "#m-enhanced-ssim") == f"{float(ssim(enh, photo)[0]):.4f}"
    assert _text(page, "#m-render-psnr") == f"{float(psnr(scene.render(t0)[None], photo)[0]):.2f}"
    assert _text(page, "#m-render-ssim") == f"{float(ssim(scene.render(t0)[None], photo)[0]):.4f}"
    assert _text(page, "#cmp-neighbours") == answer["headers"]["x-neighbours"].replace(",", ", ")
    assert len(answer["headers"]["x-neighbours"].split(",")) == 2
    assert _text(page, "#cmp-version") == "v2" == "v" + answer["headers"]["x-checkpoint-version"]

    # Zoom 4x with pixelated scaling, then drag the divider to a quarter of the width.
    page.get_by_label("Zoom").select_option("4")
    stage = page.locator("#stage")
    box = stage.bounding_box()
    assert (round(box["width"]), round(box["height"])) == (256, 192)
    assert page.locator("#cmp-after").evaluate("e => getComputedStyle(e).imageRendering") == "pixelated"
    handle = page.locator("#cmp-handle").bounding_box()
    y = box["y"] + box["height"] / 2
    page.mouse.move(handle["x"] + handle["width"] / 2, y)
    page.mouse.down()
    for i in range(1, 11):
        page.mouse.move(box["x"] + 128 - i * 6.4, y)
    page.mouse.up()
    assert page.locator("#cmp-handle").get_attribute("aria-valuenow") == "25"
    _assert_split(stage, render_img, decoded, divider_px=64)

    # The keyboard moves it too: End = all left image (render), Home = all right (enhanced).
    page.locator("#cmp-handle").focus()
    page.keyboard.press("End")
    assert page.locator("#cmp-handle").get_attribute("aria-valuenow") == "100"
    _assert_split(stage, render_img, decoded, divider_px=256)
    page.keyboard.press("Home")
    page.keyboard.press("ArrowRight")
    page.keyboard.press("Shift+ArrowRight")
    assert page.locator("#cmp-handle").get_attribute("aria-valuenow") == "11"

    # A second look at the same view uses the cached /enhance result, not a new request.
    page.get_by_label("Test view").select_option(str(t1))
    name7 = api.get(f"/scenes/{sid}/views", params={"split": "test"}).json()["items"][1]["name"]
    wait_for(page, "(name) => document.getElementById('compare').dataset.ready === 'true' && "
                   "document.getElementById('cmp-status').textContent.startsWith(name + ':')", arg=name7,
             timeout_s=120)
    page.get_by_label("Test view").select_option(str(t0))
    wait_for(page, "() => document.getElementById('cmp-seconds').textContent.includes('cached')", timeout_s=60)
    assert len(session["enhance"]) == 2
    assert pixels_of_img(page, "#img-enhanced")[2] == decoded.tobytes()


def _assert_split(stage, left, right, *, divider_px: int, zoom: int = 4) -> None:
    """The stage's screenshot: every zoomed pixel block left of the divider is the left image's
    pixel, every block right of it the right image's (blocks next to the divider line skipped).
    The stage may sit at a fractional position (its box is then one pixel taller): the blocks
    are looked for at offsets 0 and 1, and one offset must match everywhere."""
    from PIL import Image

    shot = Image.open(io.BytesIO(stage.screenshot(animations="disabled"))).convert("RGB")
    assert shot.size[0] == 64 * zoom and shot.size[1] in (48 * zoom, 48 * zoom + 1), shot.size
    results = []
    for dy in (0, 1):
        checked = {"left": 0, "right": 0}
        wrong = []
        for y in range(1, 48, 3):
            for x in range(64):
                cx = x * zoom + zoom // 2
                if abs(cx - divider_px) < 3 * zoom or (abs(cx - divider_px) < 6 * zoom and abs(y - 24) < 4):
                    continue  # the divider line and its round grip
                side, image = ("left", left) if cx < divider_px else ("right", right)
                if shot.getpixel((cx, y * zoom + zoom // 2 - 1 + dy)) != image.getpixel((x, y)):
                    wrong.append((side, x, y))
                checked[side] += 1
        results.append((len(wrong), wrong[:5], checked))
    best = min(results, key=lambda r: r[0])
    assert best[0] == 0, results
    checked = best[2]
    assert checked["left"] + checked["right"] > 600
    if 0 < divider_px < 64 * zoom:
        assert checked["left"] > 100 and checked["right"] > 100


def test_4_cancelled_and_failed_jobs_show_their_reason(session, site):
    page, sid, api = session["page"], session["scene_id"], site["api"]
    page.get_by_role("link", name="Fine-tuning").click()
    page.get_by_label("Budget").fill("10000")
    page.get_by_label("Unit").select_option("steps")
    page.get_by_role("button", name="Start fine-tuning").click()
    wait_for(page, "() => document.getElementById('job').dataset.state === 'running' && "
                   "document.getElementById('job-step').textContent !== '–'", timeout_s=120)
    assert _text(page, "#job-eta") not in ("", "–")
    assert page.locator("#job-progress").evaluate("e => e.value") > 0
    page.get_by_role("button", name="Cancel job").click()
    wait_for(page, "() => document.getElementById('job').dataset.state === 'cancelled'", timeout_s=60)
    job = api.get(f"/jobs/{_text(page, '#job-id')}").json()
    assert job["state"] == "cancelled" and job["request"] == {"steps": 10000}
    assert _text(page, "#job-error") == f"cancelled: {job['error']['message']} (cancelled)"

    # A job that fails: the scene's renders vanished from the server's disk behind its back.
    renders = site["data"] / "scenes" / sid / "scene" / "renders"
    assert renders.is_dir()
    hidden = renders.with_name("renders-away")
    renders.rename(hidden)
    page.get_by_label("Budget").fill("1")
    page.get_by_role("button", name="Start fine-tuning").click()
    wait_for(page, "() => ['failed', 'succeeded'].includes(document.getElementById('job').dataset.state)",
             timeout_s=120)
    job = api.get(f"/jobs/{_text(page, '#job-id')}").json()
    assert job["state"] == "failed" and job["error"]["message"]
    assert _text(page, "#job-error") == f"failed: {job['error']['message']} ({job['error']['code']})"
    assert page.locator("#job-error").get_attribute("role") == "alert"
    hidden.rename(renders)


@pytest.mark.parametrize("size", [(1280, 800), (390, 844)])
def test_5_no_layout_break_and_every_control_labelled(chromium, site, session, size):
    width, height = size
    context = chromium.new_context(viewport={"width": width, "height": height})
    page = context.new_page()
    requested: list[str] = []
    page.on("request", lambda r: requested.append(r.url))
    try:
        page.goto(site["url"] + "/")
        page.evaluate(f"sessionStorage.setItem('roguenerf.apiKey', {json.dumps(KEY)})")
        page.reload()
        page.locator("#scenes-table tbody tr").first.wait_for(timeout=30_000)
        for screen in ("scenes", "finetune", "compare"):
            page.get_by_role("link", name={"scenes": "Scenes", "finetune": "Fine-tuning",
                                           "compare": "Compare"}[screen]).click()
            if screen == "compare":
                wait_for(page, "() => document.getElementById('compare').dataset.ready === 'true'"
                               " || !document.getElementById('cmp-error').hidden", timeout_s=120)
            page.get_by_label("Zoom").select_option("16") if screen == "compare" else None
            overflow = page.evaluate("document.documentElement.scrollWidth - window.innerWidth")
            assert overflow <= 0, (screen, size, overflow)
            # Every visible control lies inside the viewport horizontally.
            outside = page.evaluate("""() => [...document.querySelectorAll('input, select, button, a, progress')]
                .filter(e => e.offsetParent !== null)
                .filter(e => { const r = e.getBoundingClientRect(); return r.left < -1 || r.right > innerWidth + 1; })
                .map(e => e.id || e.textContent)""")
            assert outside == [], (screen, size, outside)
        unlabelled = page.evaluate("""() => [...document.querySelectorAll('input, select, progress')]
            .filter(e => !e.labels || e.labels.length === 0).map(e => e.id)
            .concat([...document.querySelectorAll('button')].filter(b => !b.textContent.trim()).map(b => b.id))""")
        assert unlabelled == []
        # Keyboard: the screens are reachable with Tab + Enter.
        page.goto(site["url"] + "/#scenes")
        for _ in range(10):
            page.keyboard.press("Tab")
            if page.evaluate("document.activeElement.id") == "nav-compare":
                break
        assert page.evaluate("document.activeElement.id") == "nav-compare"
        page.keyboard.press("Enter")
        wait_until(lambda: page.locator("#compare").is_visible(), timeout=10, what="compare screen")
        assert page.locator("#scenes").is_hidden()
        assert requested and all(u.startswith(site["url"] + "/") or u.startswith("blob:") for u in requested)
    finally:
        context.close()
