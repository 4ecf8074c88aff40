"""POST /scenes/{id}/paths -> job -> GET /jobs/{id}/result: the MP4 round trip over real HTTP.

The API runs in uvicorn (a thread); the worker's task runs in this process (``run_job``), so the
test controls when it starts. Bad uploads get a 4xx and store nothing; a queued and a running
path job can be cancelled.
"""

from __future__ import annotations

import io
import threading
import zipfile

import pytest

from roguenerf.video import read_video_info
from service.settings import Settings
from tests.service_helpers import (
    FAST,
    LiveServer,
    make_checkpoint,
    path_zip,
    register,
    tree_digest,
    wait_until,
    zip_folder,
)
from workers.dispatch import run_job
from workers.worker import build_worker

H, W, SEED = 24, 32, 0


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    from roguenerf import make_toy_scene

    root = tmp_path_factory.mktemp("paths")
    scene = make_toy_scene(root / "scene", seed=SEED, n_train=5, n_test=1, height=H, width=W)
    ckpt = make_checkpoint(root / "micro.safetensors")
    settings = Settings(data_dir=root / "data", **FAST)
    with LiveServer(settings) as live:
        ctx, _queue, _store = build_worker(settings)
        with live.client() as client:
            r = register(client, zip_folder(root / "scene"), ckpt.read_bytes())
            assert r.status_code == 201, r.text
            yield {"client": client, "ctx": ctx, "scene": scene, "scene_id": r.json()["id"],
                   "data": settings.data_dir}


def post_path(client, scene_id, archive, **form):
    return client.post(f"/scenes/{scene_id}/paths", files={"archive": ("path.zip", archive, "application/zip")},
                       data={k: str(v) for k, v in form.items()})


def stored(data) -> dict:
    return {k: tree_digest(data / k) for k in ("scenes", "tmp", "jobs")}


def jobs_of(client, scene_id):
    return client.get("/jobs", params={"scene_id": scene_id}).json()["items"]


def test_path_job_round_trip(setup, tmp_path):
    client, scene_id = setup["client"], setup["scene_id"]
    archive, frames = path_zip(setup["scene"], seed=SEED)
    r = post_path(client, scene_id, archive, quality=28)
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["state"] == "queued" and r.headers["location"] == f"/jobs/{job['id']}"
    assert job["request"]["kind"] == "path" and job["request"]["frames"] == frames
    assert client.get(f"/jobs/{job['id']}/result").status_code == 409  # not finished yet
    assert run_job(setup["ctx"], job["id"]) == "succeeded"
    done = client.get(f"/jobs/{job['id']}").json()
    # The service blends both ways by default: one step per frame and pass.
    assert done["state"] == "succeeded" and done["progress"] == 1.0
    assert done["step"] == done["total_steps"] == 2 * frames
    flicker = done["result"]["flicker"]
    assert flicker["pairs"] == frames - 1 and flicker["render"] > 0 and flicker["enhanced"] > 0
    assert done["result"]["psnr"]["frames_with_photos"] == 3

    video = client.get(f"/jobs/{job['id']}/result")
    assert video.status_code == 200 and video.headers["content-type"] == "video/mp4"
    (tmp_path / "v.mp4").write_bytes(video.content)
    info = read_video_info(tmp_path / "v.mp4")
    assert (info["frames"], info["width"], info["height"]) == (frames, W, H)
    side = client.get(f"/jobs/{job['id']}/result", params={"what": "side_by_side"})
    (tmp_path / "s.mp4").write_bytes(side.content)
    assert read_video_info(tmp_path / "s.mp4")["width"] == 2 * W
    zipped = client.get(f"/jobs/{job['id']}/result", params={"what": "frames"})
    with zipfile.ZipFile(io.BytesIO(zipped.content)) as zf:
        assert sorted(zf.namelist()) == [f"frames/{t:05d}.png" for t in range(frames)]
    report = client.get(f"/jobs/{job['id']}/result", params={"what": "flicker"}).json()
    assert len(report["per_pair"]) == frames - 1
    assert client.get(f"/jobs/{job['id']}/result", params={"what": "nope"}).status_code == 422


def test_a_path_job_with_model_every_carries_the_frames_between(setup):
    """model_every=2 and carry_agreement=0 (carry wherever the last frame sees enough): the
    worker runs the model on the even frames and carries the others (counted in the result); a
    value out of range is a 422 before anything is stored."""
    client, scene_id = setup["client"], setup["scene_id"]
    archive, frames = path_zip(setup["scene"], seed=SEED)
    r = post_path(client, scene_id, archive, model_every=2, carry_agreement=0)
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["request"]["model_every"] == 2 and job["request"]["carry_agreement"] == 0
    assert job["request"]["carry_between"] is True  # the library's default: from both model frames around
    assert job["request"]["between_agreement"] == 0 and job["request"]["carry_share"] == 0
    assert run_job(setup["ctx"], job["id"]) == "succeeded"
    result = client.get(f"/jobs/{job['id']}").json()["result"]
    report = client.get(f"/jobs/{job['id']}/result", params={"what": "flicker"}).json()
    carried = [f["frame"] for f in report["per_frame"] if f.get("carried")]
    assert result["carried"] == len(carried) > 0 and all(t % 2 == 1 for t in carried)
    before = stored(setup["data"])
    bad = post_path(client, scene_id, path_zip(setup["scene"], seed=SEED)[0], model_every=0)
    assert bad.status_code == 422 and "model_every" in bad.json()["error"]["message"]
    from roguenerf.enhance.temporal import TemporalConfig
    from service.routers.paths import CARRY_AGREEMENT

    assert CARRY_AGREEMENT == TemporalConfig().carry_agreement  # the form's default is the library's
    assert TemporalConfig().carry_between is True  # as the form's
    from service.routers.paths import BETWEEN_AGREEMENT

    assert BETWEEN_AGREEMENT == TemporalConfig().between_agreement
    from service.routers.paths import CARRY_SHARE

    assert CARRY_SHARE == TemporalConfig().carry_share
    from service.routers.paths import CARRY_NEARER

    assert CARRY_NEARER == TemporalConfig().carry_nearer
    from service.routers.paths import SCHEDULE

    assert SCHEDULE == TemporalConfig().schedule and job["request"]["schedule"] == "fixed"
    bad = post_path(client, scene_id, path_zip(setup["scene"], seed=SEED)[0], model_every=2, schedule="sometimes")
    assert bad.status_code == 422 and "schedule" in bad.json()["error"]["message"]
    bad = post_path(client, scene_id, path_zip(setup["scene"], seed=SEED)[0], model_every=2, schedule="gate",
                    carry_between=False)
    assert bad.status_code == 422 and "carry_between" in bad.json()["error"]["message"]
    assert job["request"]["carry_nearer"] == 0
    bad = post_path(client, scene_id, path_zip(setup["scene"], seed=SEED)[0], model_every=2, carry_nearer=-1)
    assert bad.status_code == 422 and "carry_nearer" in bad.json()["error"]["message"]
    bad = post_path(client, scene_id, path_zip(setup["scene"], seed=SEED)[0], model_every=2, carry_share=-1)
    assert bad.status_code == 422 and "carry_share" in bad.json()["error"]["message"]
    bad = post_path(client, scene_id, path_zip(setup["scene"], seed=SEED)[0], model_every=2, carry_agreement=-1)
    assert bad.status_code == 422 and "carry_agreement" in bad.json()["error"]["message"]
    assert stored(setup["data"]) == before


def test_a_path_job_in_the_fast_setting_runs_one_pass(setup):
    """The CLI's --fast as form fields (TemporalConfig.FAST: model_every=4, carry_nearer=1,
    both_ways=false): one pass, one step per frame, the frames between judged by how far their
    model frames are against the nearest photo; the form's both_ways defaults to the library's."""
    from roguenerf.enhance.temporal import FAST, TemporalConfig

    client, scene_id = setup["client"], setup["scene_id"]
    archive, frames = path_zip(setup["scene"], seed=SEED)
    r = post_path(client, scene_id, archive, **FAST)
    assert r.status_code == 202, r.text
    job = r.json()
    assert {k: job["request"][k] for k in FAST} == FAST
    assert run_job(setup["ctx"], job["id"]) == "succeeded"
    done = client.get(f"/jobs/{job['id']}").json()
    assert done["step"] == done["total_steps"] == frames
    report = client.get(f"/jobs/{job['id']}/result", params={"what": "flicker"}).json()
    judged = [f for f in report["per_frame"] if "carry_nearer" in f]
    assert judged and all(f["carried"] == (f["carry_nearer"] <= 1) for f in judged)
    assert all(not f["carried"] for f in report["per_frame"] if f["frame"] % 4 == 0)
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    form = next(v for k, v in schemas.items() if k.startswith("Body_create_path_job"))
    assert form["properties"]["both_ways"]["default"] is TemporalConfig().both_ways is True


def test_a_path_in_the_wrong_axes_is_refused_at_upload_saying_why(setup):
    """The library's camera-path check runs in the router, before anything is stored (issue 49:
    it answered 202 and the job failed 2 s later, advising a --force the API did not have);
    its advice names the API's field, and force=true goes on."""
    client, scene_id, data = setup["client"], setup["scene_id"], setup["data"]
    before, jobs_before = stored(data), jobs_of(client, scene_id)
    archive, _frames = path_zip(setup["scene"], seed=SEED, opencv_axes=True)
    r = post_path(client, scene_id, archive)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "wrong_convention", error
    message = error["message"]
    assert message.startswith("the camera path does not fit the scene: ") and "worst: camera" in message
    assert "OpenGL vs OpenCV" in message and "with the y and z axes flipped" in message
    assert message.endswith("To enhance it anyway: force=true (a form field of this upload)"), message
    assert "--force" not in message and str(data) not in message
    assert stored(data) == before and jobs_of(client, scene_id) == jobs_before
    forced = post_path(client, scene_id, archive, force="true")
    assert forced.status_code == 202, forced.text
    assert forced.json()["request"]["force"] is True
    assert run_job(setup["ctx"], forced.json()["id"]) == "succeeded"


@pytest.mark.parametrize("case", ["no_camera", "missing_frame", "not_zip", "bad_quality", "unknown_scene"])
def test_bad_path_upload_is_a_clear_4xx_and_stores_nothing(setup, case):
    client, scene_id, data = setup["client"], setup["scene_id"], setup["data"]
    before, jobs_before = stored(data), jobs_of(client, scene_id)
    archive, _ = path_zip(setup["scene"], seed=SEED, drop_camera=case == "no_camera",
                          drop_frame=case == "missing_frame")
    target = "0" * 32 if case == "unknown_scene" else scene_id
    form = {"quality": 99} if case == "bad_quality" else {}
    r = post_path(client, target, b"not a zip" if case == "not_zip" else archive, **form)
    want = {"no_camera": 422, "missing_frame": 422, "not_zip": 422, "bad_quality": 422, "unknown_scene": 404}[case]
    assert r.status_code == want, r.text
    message = r.json()["error"]["message"]
    assert {"no_camera": "camera path", "missing_frame": "without both", "not_zip": "not a zip",
            "bad_quality": "quality", "unknown_scene": "not found"}[case] in message
    assert str(data) not in message
    if case == "missing_frame":  # issue 49: the upload is the path archive, not "the scene"
        assert message == "the path archive: frames without both a render and a depth: 0001"
    assert stored(data) == before and jobs_of(client, scene_id) == jobs_before


def test_cancel_queued_and_running_path_jobs(setup, monkeypatch):
    client, scene_id, data = setup["client"], setup["scene_id"], setup["data"]
    archive, frames = path_zip(setup["scene"], seed=SEED, frames_per_segment=3)
    queued = post_path(client, scene_id, archive).json()
    assert (data / "jobs" / queued["id"] / "input").is_dir()
    r = client.post(f"/jobs/{queued['id']}/cancel")
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    assert not (data / "jobs" / queued["id"]).exists()
    assert run_job(setup["ctx"], queued["id"]) == "skipped"

    from roguenerf.inference import SceneEnhancer

    slow = SceneEnhancer.enhance
    monkeypatch.setattr(SceneEnhancer, "enhance",
                        lambda self, *a, **k: (threading.Event().wait(0.4), slow(self, *a, **k))[1])
    running = post_path(client, scene_id, archive).json()
    outcome = {}
    worker = threading.Thread(target=lambda: outcome.setdefault("r", run_job(setup["ctx"], running["id"])))
    worker.start()
    wait_until(lambda: (client.get(f"/jobs/{running['id']}").json()["step"] or 0) >= 1, timeout=60,
               what="the first frame")
    r = client.post(f"/jobs/{running['id']}/cancel")
    assert r.status_code == 202, r.text
    worker.join(60)
    assert outcome["r"] == "cancelled"
    job = client.get(f"/jobs/{running['id']}").json()
    assert job["state"] == "cancelled" and job["step"] < 2 * frames
    assert not (data / "jobs" / running["id"]).exists()
    assert client.get(f"/jobs/{running['id']}/result").status_code == 409


def test_video_served_in_ranges_and_deleted_with_its_scene(setup, tmp_path):
    """The MP4 as a browser's <video> asks for it (byte ranges, 206), and a deleted scene takes
    its finished path jobs with it: rows, folders, videos."""
    client, data = setup["client"], setup["data"]
    ckpt = make_checkpoint(tmp_path / "m.safetensors")
    r = register(client, zip_folder(setup["scene"].root), ckpt.read_bytes())
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    archive, _ = path_zip(setup["scene"], seed=SEED)
    job = post_path(client, sid, archive).json()
    assert run_job(setup["ctx"], job["id"]) == "succeeded"
    url = f"/jobs/{job['id']}/result"
    whole = client.get(url)
    assert whole.status_code == 200 and whole.headers["accept-ranges"] == "bytes"
    size = len(whole.content)
    assert size > 200 and int(whole.headers["content-length"]) == size
    part = client.get(url, headers={"Range": "bytes=100-199"})
    assert part.status_code == 206 and part.content == whole.content[100:200]
    assert part.headers["content-range"] == f"bytes 100-199/{size}"
    assert part.headers["content-type"] == "video/mp4"
    tail = client.get(url, headers={"Range": "bytes=-50"})
    assert tail.status_code == 206 and tail.content == whole.content[-50:]
    assert client.get(url, headers={"Range": f"bytes={size + 10}-"}).status_code == 416

    assert (data / "jobs" / job["id"] / "output" / "enhanced.mp4").is_file()
    assert client.delete(f"/scenes/{sid}").status_code == 204
    assert client.get(f"/jobs/{job['id']}").status_code == 404
    assert client.get(url).status_code == 404
    assert not (data / "jobs" / job["id"]).exists() and not (data / "scenes" / sid).exists()
    assert all(j["scene_id"] != sid for j in client.get("/jobs", params={"limit": 200}).json()["items"])
