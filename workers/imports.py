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

from jobs.layout import IMPORT_CHECKPOINT as CHECKPOINT
from jobs.layout import IMPORT_DATASET as DATASET
from jobs.layout import IMPORT_PLY as PLY
from jobs.layout import copy_atomic, public_message
from jobs.lifecycle import JobRun, JobStopped, Task

log = logging.getLogger("roguenerf.worker")


def run_import_job(run: JobRun) -> str:
    """Render the uploaded dataset's views from the splats into a new scene (``run.scene_id``)."""
    from roguenerf import import_3dgs, load_scene, unusable_views

    store, layout, scene_id = run.store, run.layout, run.scene_id
    inputs = run.job_dir / "input"
    if store.get_scene(scene_id) is not None:  # an earlier attempt got as far as adding the scene
        return run.succeed({"kind": "import", "scene_id": scene_id}, keep_files=True)
    tmp = layout.temp_dir()
    run.root, run.aliases[str(tmp / "scene")], run.clean_on_failure = inputs / DATASET, "the imported scene", True
    started = time.monotonic()

    def progress(done: int, total: int) -> None:
        rate = done / max(time.monotonic() - started, 1e-6)
        run.record(store.record_frames, done=done, total=total, eta_s=(total - done) / rate if rate > 0 else None)
        if run.should_stop():
            raise JobStopped(f"after {done} views")

    try:
        import_3dgs(inputs / DATASET, inputs / PLY, tmp / "scene", hold=int(run.request.get("hold", 8)),
                    progress=progress)
        scene = load_scene(tmp / "scene", confine=True)
        train = len(scene.indices("train"))
        if train == 0:
            return run.fail("invalid_input", "the imported scene has no 'train' views: neighbours come from them "
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
                               height=int(first.height), active_version=version, name=run.request.get("name"))
        except BaseException:
            layout.remove_tree(destination)
            raise
    finally:
        if tmp.exists():
            layout.remove_tree(tmp)

    summary = {"kind": "import", "scene_id": scene_id, "views": len(scene.frames), "train_views": train,
               "test_views": len(scene.indices("test")), "checkpoint_version": version, "warnings": warnings}
    outcome = run.succeed(summary)
    if outcome == "succeeded":
        log.info("import job %s succeeded: scene %s, %d views", run.id, scene_id, len(scene.frames))
    return outcome


IMPORT = Task(run_import_job, label="import job", work="import")
