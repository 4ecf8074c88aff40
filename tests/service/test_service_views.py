"""The endpoints the web page reads, over a real socket (uvicorn in a thread), no worker:
``GET /scenes`` (newest first, cursor pages), ``GET /scenes/{id}/views``, a view's render,
photo and depth files, ``POST .../score``; the page's static files at ``/`` and ``/ui/``.

Known answers come from the library on the same scene folder: the files are the scene's own
pixels, the camera sent back to ``/enhance`` gives exactly the library's enhancement, and a
score is the library's ``psnr``/``ssim`` against the photo.
"""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest
import torch

from tests.service_helpers import register

KEY = "views-key-0b7d1e"
# The shared fixtures' scene and server settings (tests/conftest.py, tests/service/conftest.py).
TOY_SCENE = {"seed": 5}
SERVER = {"api_key": KEY, "max_upload_pixels": 64 * 64}


def _error(r, status, code):
    assert r.status_code == status, r.text
    assert r.json()["error"]["code"] == code, r.text
    return r.json()["error"]["message"]


def test_scene_list_is_newest_first_in_cursor_pages(client, toy, scene_id):
    ids = [scene_id]
    for _ in range(4):
        r = register(client, toy["zip"])
        assert r.status_code == 201, r.text
        ids.append(r.json()["id"])
    newest_first = ids[::-1]
    seen, cursor, pages = [], None, 0
    while True:
        params = {"limit": 2, **({"cursor": cursor} if cursor else {})}
        page = client.get("/scenes", params=params).json()
        assert set(page) == {"items", "next_cursor"} and len(page["items"]) <= 2
        seen += [s["id"] for s in page["items"]]
        pages += 1
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert [i for i in seen if i in ids] == newest_first
    assert pages == 3 and len(seen) == len(set(seen)) == 5
    whole = client.get("/scenes").json()
    assert whole["next_cursor"] is None and [s["id"] for s in whole["items"]] == newest_first
    first = whole["items"][-1]
    assert first == client.get(f"/scenes/{scene_id}").json()  # the same description as GET /scenes/{id}
    for extra in ids[1:]:
        assert client.delete(f"/scenes/{extra}").status_code == 204
    assert [s["id"] for s in client.get("/scenes").json()["items"]] == [scene_id]


@pytest.mark.parametrize("params, status, code", [({"cursor": "bm90LWEtY3Vyc29y"}, 400, "invalid_cursor"),
                                                  ({"cursor": "%%%"}, 400, "invalid_cursor"),
                                                  ({"limit": 0}, 422, "validation_error"),
                                                  ({"limit": 201}, 422, "validation_error")])
def test_scene_list_refuses_bad_parameters(client, params, status, code):
    _error(client.get("/scenes", params=params), status, code)


def test_views_give_the_enhance_camera_of_each_view(client, toy, scene_id):
    from roguenerf import SceneEnhancer, load_checkpoint
    from roguenerf.geometry import intrinsics_matrix, opengl_to_opencv
    from roguenerf.imageio import encode_png, read_image

    scene = toy["scene"]
    every = client.get(f"/scenes/{scene_id}/views").json()["items"]
    assert [v["name"] for v in every] == [f.name for f in scene.frames]
    assert [v["index"] for v in every] == list(range(8))
    test = client.get(f"/scenes/{scene_id}/views", params={"split": "test"}).json()["items"]
    assert [v["index"] for v in test] == scene.indices("test") and len(test) == 2
    t = test[0]["index"]
    assert all(v["split"] == "test" and v["has_photo"] and v["has_render"] and v["has_depth"] for v in test)
    assert (test[0]["width"], test[0]["height"]) == (64, 48)

    # The camera, render and depth the API hands out, sent back to /enhance, give exactly the
    # library's enhancement of that view.
    view = test[0]
    render = client.get(f"/scenes/{scene_id}/views/{t}/render")
    depth = client.get(f"/scenes/{scene_id}/views/{t}/depth")
    assert render.headers["content-type"] == "image/png"
    r = client.post("/enhance", data={"scene_id": scene_id, "camera": json.dumps(view["camera"])},
                    files={"render": ("r.png", render.content, "image/png"),
                           "depth": ("d.npy", depth.content, "application/octet-stream")})
    assert r.status_code == 200, r.text
    cam = view["camera"]
    assert cam["convention"] == "opengl" and cam["depth_type"] == "z" and (cam["w"], cam["h"]) == (64, 48)
    K = intrinsics_matrix(cam["fl_x"], cam["fl_y"], cam["cx"], cam["cy"], dtype=torch.float64)
    assert torch.allclose(K.float(), scene.frames[t].K.float())
    pose = opengl_to_opencv(torch.tensor(cam["transform_matrix"], dtype=torch.float64))
    assert torch.allclose(pose.float(), scene.frames[t].world_from_cam.float(), atol=1e-6)
    model, _ = load_checkpoint(toy["ckpt"])
    direct = SceneEnhancer(scene, model).enhance(scene.render(t), scene.depth(t), K, pose)
    assert torch.equal(read_image(r.content), read_image(encode_png(direct.image)))
    assert r.headers["X-Neighbours"] == ",".join(direct.neighbours)
    assert r.headers["X-Pose-Refined"] == ",".join(n for n, a in zip(direct.neighbours, direct.aligned) if a)
    if direct.colour_offset is None:
        assert "X-Colour-Offset" not in r.headers
    else:
        sent = [float(x) for x in r.headers["X-Colour-Offset"].split(",")]
        assert sent == pytest.approx(direct.colour_offset, abs=1e-6)
    if direct.trust is None:  # fewer than two neighbours: nothing compared
        assert "X-Trust" not in r.headers and "X-Neighbour-Agreement" not in r.headers
    else:
        assert float(r.headers["X-Trust"]) == pytest.approx(direct.trust, abs=1e-4)
        assert float(r.headers["X-Neighbour-Agreement"]) == pytest.approx(direct.agreement, abs=1e-4)


def test_view_files_are_the_scene_pixels(client, toy, scene_id):
    from roguenerf.imageio import read_image

    scene = toy["scene"]
    for index in (0, 7):
        photo = client.get(f"/scenes/{scene_id}/views/{index}/photo")
        render = client.get(f"/scenes/{scene_id}/views/{index}/render")
        depth = client.get(f"/scenes/{scene_id}/views/{index}/depth")
        assert torch.equal(read_image(photo.content), scene.photo(index))
        assert torch.equal(read_image(render.content), scene.render(index))
        array = np.load(io.BytesIO(depth.content), allow_pickle=False)
        assert array.dtype == np.float32 and array.shape == (48, 64)
        assert np.array_equal(array, scene.depth(index)[0].numpy())
    assert not torch.equal(read_image(client.get(f"/scenes/{scene_id}/views/6/photo").content),
                           read_image(client.get(f"/scenes/{scene_id}/views/6/render").content))


def test_score_is_the_library_metrics_against_the_photo(client, toy, scene_id):
    from roguenerf import flip, psnr, ssim
    from roguenerf.imageio import encode_png

    scene = toy["scene"]
    render = client.get(f"/scenes/{scene_id}/views/7/render").content
    got = client.post(f"/scenes/{scene_id}/views/7/score", files={"image": ("x.png", render, "image/png")}).json()
    photo = scene.photo(7)[None]
    assert got["psnr"] == pytest.approx(float(psnr(scene.render(7)[None], photo)[0]), abs=1e-9)
    assert got["ssim"] == pytest.approx(float(ssim(scene.render(7)[None], photo)[0]), abs=1e-9)
    assert got["flip"] == pytest.approx(float(flip(scene.render(7)[None], photo)[0]), abs=1e-6)
    assert 5 < got["psnr"] < 60 and 0 < got["ssim"] < 1 and 0 < got["flip"] < 1
    same = client.post(f"/scenes/{scene_id}/views/7/score",
                       files={"image": ("p.png", encode_png(scene.photo(7)), "image/png")}).json()
    assert same["psnr"] is None and same["ssim"] == pytest.approx(1.0, abs=1e-6)  # identical: infinite PSNR
    assert same["flip"] == 0.0
    assert not math.isclose(got["ssim"], same["ssim"])


def test_view_errors_are_api_errors(client, scene_id):
    other = "0" * 32
    assert "no view 8" in _error(client.get(f"/scenes/{scene_id}/views/8/render"), 404, "not_found")
    _error(client.get(f"/scenes/{scene_id}/views/-1/photo"), 404, "not_found")
    _error(client.get(f"/scenes/{other}/views"), 404, "not_found")
    _error(client.get(f"/scenes/{other}/views/0/depth"), 404, "not_found")
    _error(client.get(f"/scenes/{scene_id}/views/x/render"), 422, "validation_error")
    _error(client.get(f"/scenes/{scene_id}/views", params={"split": "val"}), 422, "validation_error")
    small = client.get(f"/scenes/{scene_id}/views/0/render").content
    wrong = client.post(f"/scenes/{scene_id}/views/1/score", files={"image": ("t.txt", b"not an image", "text/plain")})
    assert _error(wrong, 422, "invalid_input").startswith("image:")
    from roguenerf.imageio import encode_png

    half = encode_png(torch.zeros(3, 24, 32))
    msg = _error(client.post(f"/scenes/{scene_id}/views/1/score", files={"image": ("h.png", half, "image/png")}),
                 422, "invalid_input")
    assert "expected 64x48" in msg and "got 32x24" in msg
    scored = client.post(f"/scenes/{scene_id}/views/1/score", files={"image": ("r.png", small, "image/png")})
    assert scored.status_code == 200


def test_new_routes_need_the_key_and_the_page_does_not(server, scene_id):
    import httpx

    with httpx.Client(base_url=server.url, timeout=30) as anon:
        view = f"/scenes/{scene_id}/views/0"
        for method, path in [("GET", "/scenes"), ("GET", f"/scenes/{scene_id}/views"),
                             ("GET", f"{view}/render"), ("GET", f"{view}/photo"),
                             ("GET", f"{view}/depth"), ("POST", f"{view}/score"),
                             ("POST", "/"), ("DELETE", "/ui/app.js"), ("GET", "/uix/app.js")]:
            r = anon.request(method, path)
            assert r.status_code == 401 and r.json()["error"]["code"] == "unauthorized", (method, path)
        page = anon.get("/")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert "default-src 'self'" in page.headers["content-security-policy"]
        assert scene_id not in page.text and KEY not in page.text
        for asset, kind in [("/ui/app.js", "javascript"), ("/ui/style.css", "text/css")]:
            r = anon.get(asset)
            assert r.status_code == 200 and kind in r.headers["content-type"], asset
            assert "default-src 'self'" in r.headers["content-security-policy"]
        missing = anon.get("/ui/nope.js")
        assert missing.status_code == 404 and missing.json()["error"]["code"] == "not_found"
        assert anon.get("/ui/../service/settings.py").status_code in (401, 404)


def test_the_page_loads_nothing_from_elsewhere(server):
    """No CDN, no remote font, no analytics: every URL in the page's files is this origin's."""
    import re

    from service.app import UI_DIR

    text = "".join(p.read_text() for p in sorted(UI_DIR.iterdir()))
    assert sorted(p.name for p in UI_DIR.iterdir()) == ["app.js", "index.html", "style.css"]
    assert not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}", text, re.I), "an absolute URL in the page"
    assert "@import" not in text and "eval(" not in text
