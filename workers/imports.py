"""The 3DGS import task: a dataset (COLMAP or transforms.json with photos) plus a trained
``point_cloud.ply`` become a scene, through the library's ``import_3dgs``.

The API stores the validated upload in the job's folder (``input/dataset/``,
``input/point_cloud.ply``, optionally ``input/checkpoint.safetensors``) and a job whose
``scene_id`` is the id the new scene will have. This task renders every view (RGB, z-depth,
opacity) into a temporary folder, checks the result as an upload is checked, moves it to
``scenes/<id>/`` in one rename and only then adds the scene's row: until the job succeeds there
is no scene. Rendering starts over when a job is requeued (``import_3dgs`` replaces its own
partial output); a cancelled or failed job leaves nothing behind.
"""

from __future__ import annotations

import logging
import time
import traceback

from workers.layout import IMPORT_CHECKPOINT as CHECKPOINT
from workers.layout import IMPORT_DATASET as DATASET
from workers.layout import IMPORT_PLY as PLY
from workers.layout import copy_atomic, public_message
from workers.runtime import cancel_poller, jsonable

log = logging.getLogger("roguenerf.worker")


class _Stopped(Exception):
    """Raised from the progress callback: cancel, drain or a lost lease."""

    def __init__(self, done: int):
        self.done = done
        super().__init__(f"import stopped after {done} views")


def run_import_job(ctx, job: dict, lease: str, beat) -> str:
    from roguenerf import RoGUENeRFError, import_3dgs, load_scene, unusable_views

    store, layout = ctx.store, ctx.layout
    job_id, scene_id, request = job["id"], job["scene_id"], job["request"]
    inputs = layout.job_dir(job_id) / "input"
    tmp = layout.temp_dir()

    def fail(code: str, message: str) -> str:
        log.warning("import job %s failed: %s: %s", job_id, code, message)
        public = public_message(message.replace(str(tmp / "scene"), "the imported scene"), root=inputs / DATASET,
                                data_dir=layout.root)
        if store.finish(job_id, lease, "failed", error_code=code, error_message=public):
            layout.remove_tree(layout.job_dir(job_id))
        return "failed"

    if store.get_scene(scene_id) is not None:  # an earlier attempt got as far as adding the scene
        store.finish(job_id, lease, "succeeded", result={"kind": "import", "scene_id": scene_id})
        return "succeeded"
    should_stop = cancel_poller(ctx, beat, store, job_id, lease)
    started = time.monotonic()

    def progress(done: int, total: int) -> None:
        rate = done / max(time.monotonic() - started, 1e-6)
        try:
            if not store.record_frames(job_id, lease, done=done, total=total, eta_s=(total - done) / rate):
                beat.lost.set()
        except Exception:
            log.exception("import job %s: could not record progress", job_id)
        if should_stop():
            raise _Stopped(done)

    try:
        try:
            import_3dgs(inputs / DATASET, inputs / PLY, tmp / "scene", hold=int(request.get("hold", 8)),
                        progress=progress)
            scene = load_scene(tmp / "scene", confine=True)
        except _Stopped as exc:
            if beat.lost.is_set():
                log.warning("import job %s: lost its lease; stopped after %s views", job_id, exc.done)
                return "lost"
            current = store.get_job(job_id)
            if current is not None and current["cancel_requested"]:
                if store.finish(job_id, lease, "cancelled", error_code="cancelled",
                                error_message=f"cancelled after {exc.done} views"):
                    layout.remove_tree(layout.job_dir(job_id))
                return "cancelled"
            if ctx.draining.is_set() and store.release(job_id, lease):
                ctx.enqueue(job_id)
                return "requeued"
            return fail("internal_error", f"import stopped without a reason after {exc.done} views")
        except RoGUENeRFError as exc:
            return fail("invalid_input", str(exc))
        train = len(scene.indices("train"))
        if train == 0:
            return fail("invalid_input", "the imported scene has no 'train' views: neighbours come from them "
                                         "(hold: every N-th view is a test view; use a larger N or 0)")
        warnings = [public_message(f"unusable view {v}", root=tmp / "scene") for v in unusable_views(scene)]
        version = 0
        if (inputs / CHECKPOINT).is_file():
            copy_atomic(inputs / CHECKPOINT, tmp / "checkpoints" / "v1.safetensors")
            version = 1
        first = scene.frames[0]
        destination = layout.scene_dir(scene_id)
        destination.parent.mkdir(parents=True, exist_ok=True)
        tmp.rename(destination)
        try:
            store.create_scene(scene_id, views=len(scene.frames), train_views=train,
                               test_views=len(scene.indices("test")), width=int(first.width),
                               height=int(first.height), active_version=version, name=request.get("name"))
        except BaseException:
            layout.remove_tree(destination)
            raise
    except Exception as exc:
        log.error("import job %s crashed:\n%s", job_id, traceback.format_exc())
        return fail("internal_error", f"{type(exc).__name__}: {exc}")
    finally:
        if tmp.exists():
            layout.remove_tree(tmp)

    summary = {"kind": "import", "scene_id": scene_id, "views": len(scene.frames), "train_views": train,
               "test_views": len(scene.indices("test")), "checkpoint_version": version, "warnings": warnings}
    if not store.finish(job_id, lease, "succeeded", result=jsonable(summary)):
        log.warning("import job %s finished after losing its lease", job_id)
        return "lost"
    layout.remove_tree(layout.job_dir(job_id))
    log.info("import job %s succeeded: scene %s, %d views", job_id, scene_id, len(scene.frames))
    return "succeeded"
