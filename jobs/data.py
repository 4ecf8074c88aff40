"""The data directory as a process opens it, and the checkpoint a scene's version means.

The API (``service/app.py``) and a worker (``workers/worker.py``) open the same data directory
and job table the same way, through :func:`open_data`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from jobs.layout import Layout
from jobs.store import JobStore

log = logging.getLogger("roguenerf.jobs")


def open_data(settings) -> tuple[Layout, JobStore]:
    """The data directory (refused when it is not ours, created, its stale temp files of killed
    writers swept) and the job table (schema created or upgraded) that ``settings`` name."""
    layout = Layout(settings.data_dir)
    layout.ensure()
    for path in layout.sweep_stale_temp(settings.stale_temp_after_s):
        log.info("swept a stale temp file left by a killed writer: %s", path)
    store = JobStore(settings.db_url)
    store.init_schema()
    return layout, store


def base_checkpoint(settings, layout: Layout, scene_id: str, version: int) -> Path | None:
    """The checkpoint a scene's active ``version`` means: vN.safetensors, or for version 0
    the configured / bundled default (None when neither exists)."""
    if version > 0:
        return layout.checkpoint(scene_id, version)
    if settings.default_checkpoint is not None:
        return Path(settings.default_checkpoint)
    return bundled_checkpoint()


def bundled_checkpoint() -> Path | None:
    """The library's default checkpoint, or None when the package ships none."""
    from roguenerf import CheckpointError, default_checkpoint_path

    try:
        path = Path(default_checkpoint_path())
    except CheckpointError:
        return None
    return path if path.is_file() else None
