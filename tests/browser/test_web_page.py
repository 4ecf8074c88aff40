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

from tests.browser_helpers import browser, pixels_of_img, wait_for
from tests.service_helpers import (
    EmbeddedServer,
    make_checkpoint,
    make_scene,
    path_zip,
    splat_dataset,
    wait_until,
    zip_folder,
)

KEY = "page-key-4c2e9a71d0"
AUTH = {"Authorization": f"Bearer {KEY}"}
pytestmark = pytest.mark.slow
TOY_SCENE = {"seed": 2}  # the shared toy fixture's scene (tests/conftest.py)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    with EmbeddedServer(data, log_path=data.parent / f"{data.name}-server.log", api_key=KEY,
                        finetune_evaluate="true") as server:
        with httpx.Client(base_url=server.url, headers=AUTH, timeout=120) as api:
            yield {"url": server.url, "api": api, "data": data}


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


def test_1_key_then_upload_with_api_errors_as_worded(session, site, toy, tmp_path):
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
    broken = tmp_path / "broken.zip"
    broken.write_bytes(b"this is not a zip archive")
    expected = site["api"].post("/scenes", files={"archive": ("broken.zip", broken.read_bytes(),
                                                              "application/zip")}).json()["error"]
    page.get_by_label("Scene zip").set_input_files(str(broken))
    page.get_by_role("button", name="Upload", exact=True).click()
    page.locator("#scenes-error").wait_for(state="visible", timeout=30_000)
    assert _text(page, "#scenes-error .msg") == expected["message"]
    assert _text(page, "#scenes-error .code") == expected["code"] == "invalid_archive"

    page.get_by_label("Scene zip").set_input_files(str(toy["zip_file"]))
    page.get_by_label("Name (optional)").fill("  Toy  garden ")
    page.get_by_label("Checkpoint (optional, .safetensors)").set_input_files(str(toy["ckpt"]))
    page.get_by_role("button", name="Upload", exact=True).click()
    page.locator("#scenes-table tbody tr").first.wait_for(timeout=60_000)
    listed = site["api"].get("/scenes").json()["items"]
    assert len(listed) == 1
    scene = listed[0]
    session["scene_id"] = scene["id"]
    assert page.locator("#upload-progress").evaluate("e => e.value") == 100
    assert scene["name"] == "Toy garden"
    assert _text(page, "#upload-status") == 'registered "Toy garden" (8 views)'
    assert page.locator("#scenes-error").is_hidden()
    cells = page.locator("#scenes-table tbody tr").first.locator("td").all_inner_texts()
    assert cells[:4] == [f"Toy garden\n{scene['id']}", "8 (6 / 2)", "64×48", "v1"]
    # The name is what the scene pickers show too (the id's start beside it).
    assert page.locator("#ft-scene option").first.inner_text().startswith(f"Toy garden · {scene['id'][:8]} · ")
    assert page.locator("#cmp-scene option").first.inner_text().startswith("Toy garden · ")


def test_2_one_step_finetune_runs_to_the_end(session, site):
    page, sid = session["page"], session["scene_id"]
    page.get_by_role("link", name="Fine-tuning").click()
    assert page.locator("#finetune").get_by_label("Scene", exact=True).input_value() == sid
    page.get_by_label("Budget").fill("1")
    page.get_by_label("Unit").select_option("steps")
    # Every phase the page shows, in order (a 1-step job may pass some between two polls).
    page.evaluate("""() => { window.phasesSeen = [];
        new MutationObserver(() => { const t = document.getElementById('job-phase').textContent;
            if (window.phasesSeen[window.phasesSeen.length - 1] !== t) window.phasesSeen.push(t); })
          .observe(document.getElementById('job-phase'), {childList: true, characterData: true, subtree: true}); }""")
    page.get_by_role("button", name="Start fine-tuning").click()
    wait_for(page, "() => ['succeeded', 'failed', 'cancelled'].includes(document.getElementById('job').dataset.state)",
             timeout_s=240)
    seen = page.evaluate("window.phasesSeen")
    order = ["waiting for a worker", "loading the scene", "measuring before", "training", "measuring after", "–"]
    positions = [order.index(p) for p in seen]
    assert len(seen) >= 2 and seen[-1] == "–" and positions == sorted(positions), seen
    job_id = _text(page, "#job-id")
    job = site["api"].get(f"/jobs/{job_id}").json()
    assert job["scene_id"] == sid and job["request"] == {"steps": 1}
    assert job["state"] == "succeeded", job
    assert _text(page, "#job-state") == "succeeded"
    assert _text(page, "#job-step") == "1 of 1"
    assert _text(page, "#job-version") == "v2" and job["checkpoint_version"] == 2
    assert page.locator("#job-progress").evaluate("e => e.value") == 1
    shown = _text(page, "#job-loss")
    assert shown == f"{job['loss']:.4g}" or float(shown) == pytest.approx(job["loss"], rel=1e-3)
    assert page.locator("#loss-curve").get_attribute("data-points") == "1"
    assert page.locator("#job-error").is_hidden()
    assert page.locator("#ft-cancel").is_disabled()
    rows = page.locator("#job-metrics tbody tr")
    assert rows.count() == 3
    shown = [rows.nth(i).locator("td").all_inner_texts() for i in range(3)]
    wanted = [job["before"]["render"], job["before"]["enhanced"], job["after"]["enhanced"]]
    assert shown == [[f"{m['psnr']:.2f}", f"{m['ssim']:.4f}"] for m in wanted]
    assert job["after"]["enhanced"] != job["before"]["enhanced"]

    # The fine-tuned checkpoint downloads as the file the API stores.
    button = page.get_by_role("button", name="Download checkpoint (v2)")
    wait_for(page, "() => !document.getElementById('ft-download').disabled", timeout_s=30)
    with page.expect_download() as info:
        button.click()
    download = info.value
    assert download.suggested_filename == "Toy garden-v2.safetensors"
    stored = site["api"].get(f"/scenes/{sid}/checkpoints/2")
    assert stored.status_code == 200 and len(stored.content) > 1000
    with open(download.path(), "rb") as f:
        assert f.read() == stored.content


def test_3_compare_shows_what_enhance_returned_and_the_slider_moves(session, site, toy):
    from PIL import Image

    from roguenerf import flip, psnr, ssim
    from roguenerf.imageio import read_image

    page, sid, api = session["page"], session["scene_id"], site["api"]
    page.get_by_role("link", name="Compare").click()
    wait_for(page, "() => document.getElementById('compare').dataset.ready === 'true'", timeout_s=120)
    _assert_no_broken_images(page)
    # "fit": the 64x48 view is scaled up to fill the dark box's width or height, aspect kept.
    _assert_fills_box(page, 64, 48)
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
    assert _text(page, "#m-enhanced-flip") == f"{float(flip(enh, photo)[0]):.4f}"
    assert _text(page, "#m-render-flip") == f"{float(flip(scene.render(t0)[None], photo)[0]):.4f}"
    refined = set(filter(None, answer["headers"]["x-pose-refined"].split(",")))
    assert _text(page, "#cmp-neighbours") == ", ".join(
        f"{n} (pose refined)" if n in refined else n for n in answer["headers"]["x-neighbours"].split(","))
    assert len(answer["headers"]["x-neighbours"].split(",")) == 2
    assert _text(page, "#cmp-version") == "v2" == "v" + answer["headers"]["x-checkpoint-version"]
    sent = answer["headers"].get("x-colour-offset")
    if sent is None:
        assert _text(page, "#cmp-colour") == "no (the neighbours did not agree enough)"
    else:
        shown = _text(page, "#cmp-colour")
        assert shown.startswith("yes, offset R "), shown
        values = [float(x.replace("−", "-")) for x in shown.split()[3::2]]
        assert values == pytest.approx([float(x) for x in sent.split(",")], abs=1e-4)
    # Two neighbours were used, so the agreement was measured and the share kept is shown with it.
    kept, agree = float(answer["headers"]["x-trust"]), float(answer["headers"]["x-neighbour-agreement"])
    assert 0 <= kept <= 1 and 0 <= agree <= 1
    assert _text(page, "#cmp-trust") == (f"{round(kept * 100)} % (the neighbours agree on "
                                         f"{round(agree * 100)} % of the view)")

    # The enhanced view downloads as the PNG /enhance returned.
    with page.expect_download() as info:
        page.get_by_role("link", name="Download enhanced PNG").click()
    name0 = api.get(f"/scenes/{sid}/views", params={"split": "test"}).json()["items"][0]["name"]
    assert info.value.suggested_filename == f"Toy garden-{name0}-enhanced-v2.png"
    with open(info.value.path(), "rb") as f:
        assert f.read() == returned

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


def _assert_no_broken_images(page) -> None:
    """Every <img> that has a source shows a decoded image (none is a broken-image icon)."""
    broken = page.evaluate("""() => [...document.images].filter(i => i.getAttribute('src'))
        .filter(i => !i.complete || i.naturalWidth === 0).map(i => i.id)""")
    assert broken == [], f"broken images: {broken}"


def _assert_fills_box(page, width: int, height: int) -> None:
    """At zoom "fit" the stage fills its box's inner width or height (within a pixel), with the
    view's aspect ratio."""
    box = page.evaluate("""() => { const b = document.getElementById('stage-scroll'), cs = getComputedStyle(b);
        return [b.clientWidth - parseFloat(cs.paddingLeft) - parseFloat(cs.paddingRight),
                parseFloat(cs.maxHeight) - parseFloat(cs.paddingTop) - parseFloat(cs.paddingBottom)]; }""")
    stage = page.locator("#stage").bounding_box()
    assert abs(stage["width"] - box[0]) <= 1 or abs(stage["height"] - box[1]) <= 1, (stage, box)
    assert stage["width"] <= box[0] + 1 and stage["height"] <= box[1] + 1, (stage, box)
    assert abs(stage["width"] / stage["height"] - width / height) < 0.02
    assert stage["width"] > width  # scaled up, not drawn small in a large box


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
        for screen in ("scenes", "finetune", "compare", "videos"):
            page.get_by_role("link", name={"scenes": "Scenes", "finetune": "Fine-tuning",
                                           "compare": "Compare", "videos": "Videos"}[screen]).click()
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
        for _ in range(30):   # from wherever the focus was: through the page, round to the nav
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


# ----------------------------------------------------------------------------- issue 38: the page
OVER_CAPACITY = {"error": {"code": "over_capacity",
                           "message": "all 1 enhancement slots are busy; retry shortly"}}
"""The body of service/routers/enhance.py's refusal when every enhancement slot is taken."""


def _open(chromium, site, *, width=1280, height=800, hash_=""):
    context = chromium.new_context(viewport={"width": width, "height": height}, device_scale_factor=1)
    page = context.new_page()
    page.goto(site["url"] + "/")
    page.evaluate(f"sessionStorage.setItem('roguenerf.apiKey', {json.dumps(KEY)})")
    page.goto(site["url"] + "/" + hash_)
    page.reload()
    page.locator("#scenes-table tbody tr").first.wait_for(state="attached", timeout=30_000)
    return context, page


def _camera_of(request) -> dict:
    """The ``camera`` field of a multipart POST /enhance the page sent."""
    body = request.post_data_buffer
    start = body.index(b'name="camera"')
    start = body.index(b"\r\n\r\n", start) + 4
    return json.loads(body[start:body.index(b"\r\n--", start)])


def _direct_enhance(api, sid: str, view: dict) -> bytes:
    """The same view enhanced outside the browser (RGB bytes of the answer)."""
    from PIL import Image

    index = view["index"]
    r = api.post("/enhance", data={"scene_id": sid, "camera": json.dumps(view["camera"])},
                 files={"render": ("r.png", api.get(f"/scenes/{sid}/views/{index}/render").content, "image/png"),
                        "depth": ("d.npy", api.get(f"/scenes/{sid}/views/{index}/depth").content, "x/y")})
    assert r.status_code == 200, r.text
    return Image.open(io.BytesIO(r.content)).convert("RGB").tobytes()


def test_6_compare_retries_over_capacity_and_the_newest_view_wins(chromium, site, session):
    """Issue 38 as the user hit it: every enhancement slot busy. The page retries with a visible
    countdown and recovers on its own; no image is ever broken; a view picked while another one
    waits cancels the older one, and the newer view's enhancement is what is shown."""
    sid, api = session["scene_id"], site["api"]
    test_views = api.get(f"/scenes/{sid}/views", params={"split": "test"}).json()["items"]
    v0, v1 = test_views
    state = {"refuse": 10**6, "calls": []}

    def busy_then_through(route):
        state["calls"].append(_camera_of(route.request))
        if state["refuse"] > 0:
            state["refuse"] -= 1
            route.fulfill(status=503, headers={"Retry-After": "1", "Content-Type": "application/json"},
                          body=json.dumps(OVER_CAPACITY))
        else:
            route.fulfill(response=route.fetch())

    context, page = _open(chromium, site)
    try:
        page.route("**/enhance", busy_then_through)
        page.evaluate("""() => { window.statusSeen = [];
            const status = document.getElementById('cmp-status');
            new MutationObserver(() => window.statusSeen.push(status.textContent))
              .observe(status, {childList: true, characterData: true, subtree: true}); }""")
        page.get_by_role("link", name="Compare").click()
        # Always busy: the page keeps retrying (never stuck on an error), the render and photo
        # of the view are shown, nothing is broken, and no enhanced image is made up.
        wait_for(page, "() => document.getElementById('compare').dataset.busy === 'true'", timeout_s=60)
        wait_for(page, "() => window.statusSeen.filter(t => t.includes('retrying in')).length >= 3", timeout_s=30)
        assert page.locator("#cmp-error").is_hidden()
        assert "all enhancement slots are busy; retrying in" in _text(page, "#cmp-status")
        assert "busy, retrying in" in _text(page, "#stage-note")
        assert page.locator("#cmp-after").is_hidden() and page.locator("#cmp-download").is_hidden()
        assert page.locator("#img-enhanced").get_attribute("src") is None
        _assert_no_broken_images(page)
        assert page.locator("#img-render").get_attribute("src") and page.locator("#img-photo").get_attribute("src")
        tries = len(state["calls"])
        assert tries >= 3 and all(c == v0["camera"] for c in state["calls"])

        # The user picks the other view while the first still waits: the first one's retries
        # stop; the second view waits in turn until the server answers again, and its
        # enhancement is what is shown.
        page.get_by_label("Test view").select_option(str(v1["index"]))
        wait_for(page, "(n) => document.getElementById('cmp-status').textContent.startsWith(n + ': all')",
                 arg=v1["name"], timeout_s=30)
        state["refuse"] = 0
        wait_for(page, "(name) => document.getElementById('compare').dataset.ready === 'true' && "
                       "document.getElementById('cmp-status').textContent.startsWith(name + ':')",
                 arg=v1["name"], timeout_s=120)
        page.wait_for_timeout(4500)   # longer than the first view's next retry would have waited
        first_v1 = state["calls"].index(v1["camera"])
        assert first_v1 >= tries
        assert all(c == v1["camera"] for c in state["calls"][first_v1:]), "a stale request for the first view"
        assert pixels_of_img(page, "#img-enhanced")[2] == _direct_enhance(api, sid, v1)
        _assert_no_broken_images(page)
        assert page.locator("#cmp-error").is_hidden() and page.locator("#stage-note").is_hidden()

        # Back to the first view: busy for three answers, then the page recovers by itself.
        state["refuse"], start = 3, len(state["calls"])
        page.get_by_label("Test view").select_option(str(v0["index"]))
        wait_for(page, "(name) => document.getElementById('compare').dataset.ready === 'true' && "
                       "document.getElementById('cmp-status').textContent.startsWith(name + ':')",
                 arg=v0["name"], timeout_s=120)
        assert state["calls"][start:] == [v0["camera"]] * 4
        waits = [t for t in page.evaluate("window.statusSeen")[-12:] if "retrying in" in t]
        assert any("retrying in 0.5 s (try 2)" in t for t in waits), waits
        assert any("retrying in 2 s (try 4)" in t for t in waits), waits
        assert pixels_of_img(page, "#img-enhanced")[2] == _direct_enhance(api, sid, v0)
        assert pixels_of_img(page, "#cmp-after")[2] == _direct_enhance(api, sid, v0)
        _assert_no_broken_images(page)
        assert page.locator("#cmp-error").is_hidden() and page.locator("#cmp-after").is_visible()
    finally:
        context.close()


def test_7_job_shows_its_phase(chromium, site, session):
    """The API's state and phase in words: measuring before, training (step, ETA), measuring
    after. A real job's answers, with the fields of each phase put in turn."""
    sid, api = session["scene_id"], site["api"]
    job = api.get("/jobs", params={"scene_id": sid, "state": "succeeded"}).json()["items"][-1]
    script = [
        {"state": "running", "phase": None, "step": None, "total_steps": None, "eta_s": None, "progress": 0},
        {"state": "running", "phase": "evaluating", "step": None, "total_steps": None, "eta_s": None, "progress": 0},
        {"state": "running", "phase": "training", "step": 3, "total_steps": 10, "eta_s": 12.4, "progress": 0.3},
        {"state": "running", "phase": "evaluating", "step": 10, "total_steps": 10, "eta_s": None, "progress": 1.0},
        None,   # the real answer: succeeded
    ]
    at = {"i": 0}

    def scripted(route):
        answer = route.fetch()
        body = answer.json()
        if script[at["i"]] is not None:
            body.update(script[at["i"]])
        route.fulfill(response=answer, body=json.dumps(body))

    context, page = _open(chromium, site)
    try:
        page.evaluate(f"sessionStorage.setItem('roguenerf.jobs', {json.dumps(json.dumps({sid: job['id']}))})")
        page.route(f"**/jobs/{job['id']}", scripted)
        page.get_by_role("link", name="Fine-tuning").click()
        expected = [("loading the scene", "–", "–"),
                    ("measuring before", "–", "measuring the held-out views"),
                    ("training", "3 of 10", "12 s"),
                    ("measuring after", "10 of 10", "measuring the held-out views"),
                    ("–", f"{job['step']} of {job['total_steps']}", "–")]
        for i, (phase, step, eta) in enumerate(expected):
            at["i"] = i
            wait_for(page, "(p) => document.getElementById('job-phase').textContent === p", arg=phase, timeout_s=30)
            assert (_text(page, "#job-step"), _text(page, "#job-eta")) == (step, eta), phase
            assert _text(page, "#job-state") == ("running" if i < 4 else "succeeded")
    finally:
        context.close()


def test_8_small_view_fits_and_the_divider_stays_in_view_at_4x(chromium, site, tmp_path):
    """A 504x378 view fills the box at "fit"; at 4x (2016x1512, larger than the box) the
    divider is in sight after the zoom and follows when the user pans to either edge."""
    api = site["api"]
    make_scene(tmp_path / "wide", seed=3, height=378, width=504, n_train=3, n_test=1)
    ckpt = make_checkpoint(tmp_path / "m.safetensors").read_bytes()
    r = api.post("/scenes", files={"archive": ("wide-504.zip", zip_folder(tmp_path / "wide"), "application/zip"),
                                   "checkpoint": ("m.safetensors", ckpt, "application/octet-stream")})
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    assert r.json()["name"] == "wide-504"
    context, page = _open(chromium, site)

    def with_flip(route):
        # A score endpoint that also reports FLIP: the page gives any further metric a column.
        answer = route.fetch()
        route.fulfill(response=answer, body=json.dumps({**answer.json(), "flip": 0.125}))

    try:
        page.route("**/score", with_flip)
        page.get_by_role("button", name="Compare scene wide-504").click()
        wait_for(page, "() => document.getElementById('compare').dataset.ready === 'true'", timeout_s=180)
        _assert_no_broken_images(page)
        _assert_fills_box(page, 504, 378)
        assert page.locator("#cmp-after").evaluate("e => getComputedStyle(e).imageRendering") == "pixelated"
        assert page.locator("#cmp-metrics thead th").all_inner_texts()[1:] == ["PSNR (dB)", "SSIM", "FLIP"]
        assert page.locator("#cmp-metrics tbody tr").nth(1).locator("td").all_inner_texts()[2] == "0.1250"

        page.get_by_label("Zoom").select_option("4")
        box = page.locator("#stage-scroll")
        box.scroll_into_view_if_needed()
        stage = page.locator("#stage").bounding_box()
        assert (round(stage["width"]), round(stage["height"])) == (2016, 1512)

        def divider_in_view() -> bool:
            h, b = page.locator("#cmp-handle").bounding_box(), box.bounding_box()
            grip = page.evaluate("""() => { const h = document.getElementById('cmp-handle');
                return h.getBoundingClientRect().top + parseFloat(getComputedStyle(h).getPropertyValue('--grip')); }""")
            inside_box = b["x"] <= h["x"] <= b["x"] + b["width"] and b["y"] <= grip <= b["y"] + b["height"]
            inside_window = 0 <= h["x"] <= 1280 and h["y"] < 800 and h["y"] + h["height"] > 0
            return inside_box and inside_window

        assert divider_in_view()
        assert page.locator("#cmp-handle").get_attribute("aria-valuenow") == "50"
        for scroll in ("0", "1e9"):   # pan to the far left, then the far right
            box.evaluate(f"b => {{ b.scrollLeft = {scroll}; b.scrollTop = {scroll}; }}")
            wait_until(divider_in_view, timeout=5, what=f"the divider in view after panning to {scroll}")
        assert int(page.locator("#cmp-handle").get_attribute("aria-valuenow")) > 50
        _assert_no_broken_images(page)
    finally:
        context.close()
        api.delete(f"/scenes/{sid}")


def test_9_videos_tab_lists_plays_and_downloads_path_jobs(chromium, site, session, toy):
    sid, api = session["scene_id"], site["api"]
    archive, frames = path_zip(toy["scene"], seed=2)
    r = api.post(f"/scenes/{sid}/paths", files={"archive": ("path.zip", archive, "application/zip")})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    context, page = _open(chromium, site, hash_="#videos")
    try:
        page.get_by_role("link", name="Videos").click()
        row = page.locator(f"#videos-table tr[data-job='{job_id}']")
        row.wait_for(timeout=30_000)
        assert "Toy garden" in row.locator("td").first.inner_text()
        wait_for(page, f"() => document.querySelector(\"#videos-table tr[data-job='{job_id}']\").dataset.state"
                       " === 'succeeded'", timeout_s=180)
        job = api.get(f"/jobs/{job_id}").json()
        # one step per frame and pass: the frames are blended both ways (TemporalConfig.both_ways)
        assert job["state"] == "succeeded" and job["step"] == job["total_steps"] == 2 * frames
        assert row.locator("progress").evaluate("e => e.value") == 1
        assert f"step {2 * frames} of {2 * frames}" in row.inner_text()

        row.get_by_role("button", name="Play").click()
        wait_for(page, "() => document.getElementById('video-player').readyState >= 1 || "
                       "!document.getElementById('videos-error').hidden", timeout_s=60)
        assert page.locator("#videos-error").is_hidden(), _text(page, "#videos-error")
        player = page.locator("#video-player")
        assert player.evaluate("v => [v.videoWidth, v.videoHeight]") == [64, 48]
        assert player.evaluate("v => v.duration") == pytest.approx(frames / 10, abs=0.15)

        video = api.get(f"/jobs/{job_id}/result")
        assert video.headers["content-type"] == "video/mp4"
        with page.expect_download() as info:
            row.get_by_role("button", name="Download").click()
        assert info.value.suggested_filename == f"Toy garden-path-{job_id[:8]}.mp4"
        with open(info.value.path(), "rb") as f:
            assert f.read() == video.content
    finally:
        context.close()


def test_a_delete_a_scene_refused_while_busy(chromium, site, toy):
    api = site["api"]
    files = {"archive": ("doomed.zip", toy["zip"], "application/zip"),
             "checkpoint": ("m.safetensors", toy["ckpt"].read_bytes(), "application/octet-stream")}
    r = api.post("/scenes", files=files, data={"name": "Doomed scene"})
    sid = r.json()["id"]
    job = api.post(f"/scenes/{sid}/finetune", json={"steps": 10_000}).json()
    context, page = _open(chromium, site)
    try:
        row = page.locator(f"#scenes-table tr[data-scene='{sid}']")
        assert row.locator("td").first.inner_text() == f"Doomed scene\n{sid}"
        # Renamed on the page: PATCH /scenes/{id}; the API's rules (too long: its 422 as worded).
        page.once("dialog", lambda d: d.accept("x" * 121))
        row.get_by_role("button", name="Rename scene Doomed scene").click()
        page.locator("#scenes-error").wait_for(state="visible", timeout=30_000)
        assert _text(page, "#scenes-error .msg") == "name: at most 120 characters, got 121"
        page.once("dialog", lambda d: d.accept("  Doomed,   renamed "))
        row.get_by_role("button", name="Rename scene Doomed scene").click()
        wait_for(page, f"() => document.querySelector(\"tr[data-scene='{sid}'] .scene-name\").textContent"
                       " === 'Doomed, renamed'", timeout_s=30)
        assert api.get(f"/scenes/{sid}").json()["name"] == "Doomed, renamed"
        assert page.locator("#scenes-error").is_hidden()
        page.once("dialog", lambda d: d.accept())
        row.get_by_role("button", name="Delete scene Doomed, renamed").click()
        page.locator("#scenes-error").wait_for(state="visible", timeout=30_000)
        assert _text(page, "#scenes-error .code") == "scene_busy"
        assert job["id"] in _text(page, "#scenes-error .msg")
        assert api.get(f"/scenes/{sid}").status_code == 200

        api.post(f"/jobs/{job['id']}/cancel")
        wait_until(lambda: api.get(f"/jobs/{job['id']}").json()["state"] == "cancelled", timeout=60,
                   what="the job cancelled")
        page.once("dialog", lambda d: d.dismiss())   # "Cancel" in the confirmation: nothing happens
        row.get_by_role("button", name="Delete scene Doomed, renamed").click()
        page.wait_for_timeout(500)
        assert api.get(f"/scenes/{sid}").status_code == 200 and row.count() == 1
        page.once("dialog", lambda d: d.accept())
        row.get_by_role("button", name="Delete scene Doomed, renamed").click()
        row.wait_for(state="detached", timeout=30_000)
        assert api.get(f"/scenes/{sid}").status_code == 404
        assert _text(page, "#upload-status") == 'deleted "Doomed, renamed"'
        assert page.locator("#scenes-error").is_hidden()
        assert not (site["data"] / "scenes" / sid).exists()
    finally:
        context.close()


def test_b_videos_tab_shows_each_jobs_state_and_flicker(chromium, site, session, toy):
    """Issue 49: a finished path job showed "–" for its state; now succeeded, failed or cancelled
    in words, and the flicker figure (render -> enhanced, the ratio) of a succeeded one. The failed
    and cancelled rows are the real job's answer with those states put in (as test 7 does)."""
    sid, api = session["scene_id"], site["api"]
    archive, frames = path_zip(toy["scene"], seed=2)
    r = api.post(f"/scenes/{sid}/paths", files={"archive": ("path.zip", archive, "application/zip")})
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    job = wait_until(lambda: (j := api.get(f"/jobs/{job_id}").json())["state"] in ("succeeded", "failed") and j,
                     timeout=180, what="the path job finished")
    assert job["state"] == "succeeded", job
    failed = {**job, "id": "f" * 32, "state": "failed", "result": None,
              "error": {"code": "invalid_input", "message": "frames[2] (0002.png): not a PNG"}}
    cancelled = {**job, "id": "c" * 32, "state": "cancelled", "result": None,
                 "error": {"code": "cancelled", "message": "cancelled after 2 frames"}}

    def listed(route):
        answer = route.fetch()
        body = answer.json()
        body["items"] = [failed, cancelled] + body["items"]
        route.fulfill(response=answer, body=json.dumps(body))

    context, page = _open(chromium, site, hash_="#videos")
    try:
        page.route(lambda url: "/jobs?" in url, listed)
        page.get_by_role("link", name="Videos").click()
        page.get_by_role("button", name="Refresh").click()
        row = page.locator(f"#videos-table tr[data-job='{job_id}']")
        row.wait_for(timeout=30_000)
        flicker = job["result"]["flicker"]
        assert row.locator(".job-state").inner_text() == "succeeded"
        assert f"step {2 * frames} of {2 * frames}" in row.inner_text()
        assert flicker["neighbour_changes"] > 0  # the toy path changes its neighbours: the page says how it fares there
        want = (f"{flicker['render']:.4f} → {flicker['enhanced']:.4f} (×{flicker['ratio']:.2f}); "
                f"×{flicker['ratio_sharpened']:.2f} of the render sharpened alike; "
                f"×{flicker['ratio_changed']:.2f} across the {flicker['neighbour_changes']} frame pairs "
                "where the neighbour photos changed")
        assert row.locator("td[data-label='Flicker']").inner_text() == want
        bad = page.locator("#videos-table tr[data-job='" + "f" * 32 + "']")
        assert bad.locator(".job-state").inner_text() == "failed"
        assert "failed: frames[2] (0002.png): not a PNG (invalid_input)" in bad.inner_text()
        assert bad.locator("td[data-label='Flicker']").inner_text() == "–"
        stopped = page.locator("#videos-table tr[data-job='" + "c" * 32 + "']")
        assert stopped.locator(".job-state").inner_text() == "cancelled"
        assert "cancelled: cancelled after 2 frames" in stopped.inner_text()
        assert page.get_by_role("columnheader", name="Flicker (render → enhanced)").count() == 1
    finally:
        context.close()


def test_c_finetune_tab_keeps_a_finished_job_after_a_reload_and_no_404(chromium, site, session):
    """Issue 49: a tab that did not start the job (a reload in a new tab, a job started by another
    client) showed nothing for a finished fine-tuning job; the page now asks the API for the
    scene's newest fine-tuning job. And the page's icon is served: no 404 for /favicon.ico."""
    sid, api = session["scene_id"], site["api"]
    started = api.post(f"/scenes/{sid}/finetune", json={"steps": 1})
    assert started.status_code == 202, started.text
    job_id = started.json()["id"]
    job = wait_until(lambda: (j := api.get(f"/jobs/{job_id}").json())["state"] not in ("queued", "running") and j,
                     timeout=240, what="the fine-tuning job finished")
    assert job["state"] == "succeeded" and job["before"] and job["after"], job
    context, page = _open(chromium, site)
    failures: list = []
    page.on("response", lambda r: failures.append((r.status, r.url)) if r.status >= 400 else None)
    try:
        for reloaded in (False, True):
            if reloaded:
                page.reload()
            page.get_by_role("link", name="Fine-tuning").click()
            page.locator("#finetune").get_by_label("Scene", exact=True).select_option(sid)
            wait_for(page, "(id) => document.getElementById('job-id').textContent === id && "
                           "!document.getElementById('job').hidden", arg=job_id, timeout_s=30)
            assert _text(page, "#job-state") == "succeeded"
            assert _text(page, "#job-step") == "1 of 1"
            rows = page.locator("#job-metrics tbody tr")
            assert rows.count() == 3
            shown = [rows.nth(i).locator("td").all_inner_texts() for i in range(3)]
            wanted = [job["before"]["render"], job["before"]["enhanced"], job["after"]["enhanced"]]
            assert shown == [[f"{m['psnr']:.2f}", f"{m['ssim']:.4f}"] for m in wanted]
            assert page.locator("#loss-curve").get_attribute("data-points") == "1"
        icon = page.locator("link[rel='icon']").get_attribute("href")
        for path in (icon, "/favicon.ico"):
            r = httpx.get(site["url"] + path, timeout=30)   # no key: a public file, like the page
            assert r.status_code == 200 and r.headers["content-type"].startswith("image/"), (path, r.text)
        assert not failures, failures
    finally:
        context.close()


def test_d_a_3dgs_dataset_zip_and_its_ply_upload_as_a_scene(chromium, site, tmp_path):
    """Issue 49: the page took only a ready scene zip; a COLMAP dataset zip plus its trained
    point_cloud.ply now become a scene (POST /scenes/import: the worker renders every view)."""
    api = site["api"]
    splats = splat_dataset(tmp_path)
    archive = tmp_path / "Splat garden.zip"
    archive.write_bytes(zip_folder(splats["dataset"], prefix="garden"))
    context, page = _open(chromium, site)
    try:
        page.get_by_label("Scene zip").set_input_files(str(archive))
        page.get_by_label("3DGS .ply").set_input_files(str(splats["ply"]))
        page.get_by_role("button", name="Upload", exact=True).click()
        wait_for(page, "() => document.getElementById('upload-status').textContent.startsWith('imported') || "
                       "!document.getElementById('scenes-error').hidden", timeout_s=180)
        assert page.locator("#scenes-error").is_hidden(), _text(page, "#scenes-error")
        assert _text(page, "#upload-status") == 'imported "Splat garden" (9 views)'
        scene = next(s for s in api.get("/scenes").json()["items"] if s["name"] == "Splat garden")
        assert (scene["views"], scene["train_views"], scene["test_views"]) == (9, 7, 2)
        row = page.locator(f"#scenes-table tr[data-scene='{scene['id']}']")
        assert row.locator("td").first.inner_text() == f"Splat garden\n{scene['id']}"
        assert page.locator("#finetune").get_by_label("Scene", exact=True).input_value() == scene["id"]
        page.get_by_role("link", name="Fine-tuning").click()   # the import job is not a fine-tuning job
        page.wait_for_timeout(1000)
        assert page.locator("#job").is_hidden()
        page.get_by_role("link", name="Scenes").click()
        # The same dataset zip without its .ply: refused, saying where it goes.
        page.get_by_label("Scene zip").set_input_files(str(archive))
        page.get_by_role("button", name="Upload", exact=True).click()
        page.locator("#scenes-error").wait_for(state="visible", timeout=30_000)
        assert _text(page, "#scenes-error .code") == "invalid_scene"
        assert "POST /scenes/import" in _text(page, "#scenes-error .msg")
    finally:
        context.close()
