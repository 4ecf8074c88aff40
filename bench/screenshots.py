"""Screenshots of each screen of the web page (docs/screenshots/*.png).

Starts the embedded server (API + worker) on loopback in a temporary data dir, drives
Debian's headless Chromium with Playwright like a user: upload a toy scene (with the bundled
default checkpoint), fine-tune it for a few steps, open a test view in Compare, enhance a
camera path (Videos). Takes each screen at 1280x800 and the compare screen at 390x844 too.
Nothing leaves the machine.

    ./dev python -m bench.screenshots [--out docs/screenshots] [--steps 20] [--size 160x120]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from tests.browser_helpers import CHROMIUM_ARGS, chromium_path, embedded_server, path_zip, wait_for
from tests.service_helpers import zip_folder

ROOT = Path(__file__).resolve().parents[1]

KEY = "screenshot-key"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshots")
    parser.add_argument("--steps", type=int, default=20, help="fine-tuning steps of the shown job")
    parser.add_argument("--size", default="160x120", help="toy scene WxH")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    exe = chromium_path()
    if exe is None:
        sys.exit("chromium not found: apt-get install -y chromium (or set ROGUENERF_CHROMIUM)")
    import httpx
    from playwright.sync_api import sync_playwright

    from roguenerf import make_toy_scene

    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene = make_toy_scene(tmp / "scene", seed=7, n_train=8, n_test=3, height=height, width=width)
        (tmp / "toy-scene.zip").write_bytes(zip_folder(tmp / "scene"))
        with embedded_server(tmp / "data", log_path=tmp / "server.log", api_key=KEY, finetune_crop=48,
                             finetune_batch=2, finetune_evaluate="true") as url, sync_playwright() as p:
            browser = p.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS, headless=True)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            foreign: list[str] = []
            page.on("request", lambda r: None if r.url.startswith((url + "/", "blob:")) else foreign.append(r.url))
            page.goto(url + "/")
            page.get_by_label("API key").fill(KEY)
            page.get_by_label("API key").press("Enter")
            page.get_by_label("Scene zip").set_input_files(str(tmp / "toy-scene.zip"))
            page.get_by_label("Name (optional)").fill("Toy garden")
            page.get_by_role("button", name="Upload", exact=True).click()
            page.locator("#scenes-table tbody tr").first.wait_for(timeout=120_000)
            page.screenshot(path=str(args.out / "scenes.png"))

            page.get_by_role("link", name="Fine-tuning").click()
            page.get_by_label("Budget").fill(str(args.steps))
            page.get_by_label("Unit").select_option("steps")
            page.get_by_role("button", name="Start fine-tuning").click()
            wait_for(page, "() => document.getElementById('job').dataset.state === 'running' && "
                           "Number(document.getElementById('loss-curve').dataset.points || 0) >= 3", timeout_s=300)
            page.screenshot(path=str(args.out / "finetune-running.png"))
            wait_for(page, "() => ['succeeded', 'failed', 'cancelled']"
                           ".includes(document.getElementById('job').dataset.state)", timeout_s=600)
            page.screenshot(path=str(args.out / "finetune.png"))

            page.get_by_role("link", name="Compare").click()
            wait_for(page, "() => document.getElementById('compare').dataset.ready === 'true'", timeout_s=300)
            page.get_by_label("Zoom").select_option("4")
            page.locator("#cmp-handle").focus()
            for _ in range(15):
                page.keyboard.press("ArrowLeft")
            page.locator("#cmp-handle").blur()
            page.screenshot(path=str(args.out / "compare.png"))
            page.get_by_label("Zoom").select_option("fit")
            page.screenshot(path=str(args.out / "compare-fit.png"))
            page.set_viewport_size({"width": 390, "height": 844})
            page.get_by_label("Zoom").select_option("2")
            page.screenshot(path=str(args.out / "compare-390x844.png"), full_page=True)
            page.set_viewport_size({"width": 1280, "height": 800})

            with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {KEY}"}, timeout=120) as api:
                sid = api.get("/scenes").json()["items"][0]["id"]
                archive, _ = path_zip(scene, seed=7, frames_per_segment=8)
                r = api.post(f"/scenes/{sid}/paths", files={"archive": ("path.zip", archive, "application/zip")})
                r.raise_for_status()
                job_id = r.json()["id"]
            page.get_by_role("link", name="Videos").click()
            wait_for(page, f"() => document.querySelector(\"#videos-table tr[data-job='{job_id}']\")"
                           "?.dataset.state === 'succeeded'", timeout_s=600)
            page.locator(f"#videos-table tr[data-job='{job_id}']").get_by_role("button", name="Play").click()
            wait_for(page, "() => document.getElementById('video-player').readyState >= 2", timeout_s=60)
            page.locator("#video-player").evaluate("v => { v.pause(); v.currentTime = v.duration / 2; }")
            page.wait_for_timeout(500)
            page.screenshot(path=str(args.out / "videos.png"), full_page=True)
            browser.close()
            if foreign:
                sys.exit(f"the page contacted other origins: {foreign}")
    for name in sorted(args.out.glob("*.png")):
        print(name.relative_to(ROOT) if name.is_relative_to(ROOT) else name)


if __name__ == "__main__":
    main()
