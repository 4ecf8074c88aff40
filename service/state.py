"""What the app holds between requests: stores, queue, the SceneEnhancer cache.

Built in the app's lifespan (never at import), reached from routes through the
``ServicesDep`` dependency so tests can swap parts with ``app.dependency_overrides``.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

from fastapi import Depends, Request

from jobs.data import base_checkpoint
from jobs.layout import Layout
from jobs.queue import JobQueue
from jobs.store import JobStore
from service.errors import ApiError
from service.settings import Settings

log = logging.getLogger("roguenerf.service")


class EnhancerCache:
    """LRU of SceneEnhancers keyed by ``(scene id, checkpoint version)``.

    A new checkpoint version is a new key, so /enhance switches to a promoted checkpoint on
    its next call; the neighbour features of each key are computed once (inside the
    SceneEnhancer). A per-key lock stops two requests from building the same entry twice.
    """

    def __init__(self, settings: Settings, layout: Layout, default_model=None):
        self.settings = settings
        self.layout = layout
        self.default_model = default_model
        self._entries: OrderedDict[tuple[str, int], object] = OrderedDict()
        self._lock = threading.Lock()
        self._building: dict[tuple[str, int], threading.Lock] = {}

    def get(self, scene_id: str, version: int):
        key = (scene_id, version)
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                return self._entries[key]
            build_lock = self._building.setdefault(key, threading.Lock())
        with build_lock:
            with self._lock:
                if key in self._entries:
                    return self._entries[key]
            enhancer = self._build(scene_id, version)
            with self._lock:
                self._entries[key] = enhancer
                self._building.pop(key, None)
                while len(self._entries) > self.settings.enhancer_cache_size:
                    self._entries.popitem(last=False)
            return enhancer

    def _build(self, scene_id: str, version: int):
        from roguenerf import EnhanceOptions, SceneEnhancer, load_checkpoint, load_scene

        scene = load_scene(self.layout.scene_files(scene_id), confine=True)
        if version == 0 and self.default_model is not None:
            model = self.default_model
        else:
            path = base_checkpoint(self.settings, self.layout, scene_id, version)
            if path is None or not Path(path).is_file():
                raise ApiError(
                    409, "no_checkpoint",
                    f"scene {scene_id} has no enhancer checkpoint: upload one with the scene "
                    "(field 'checkpoint'), fine-tune it (POST /scenes/{id}/finetune), or configure "
                    "ROGUENERF_DEFAULT_CHECKPOINT",
                )
            model, _ = load_checkpoint(path)
        log.info("SceneEnhancer built for scene %s, checkpoint v%s", scene_id, version)
        # the shipped defaults; the scene's pose judgements kept beside it, across restarts
        return SceneEnhancer(scene, model, options=EnhanceOptions(),
                             settled_file=self.layout.scene_dir(scene_id) / "settled.json")

    def evict(self, scene_id: str) -> None:
        with self._lock:
            for key in [k for k in self._entries if k[0] == scene_id]:
                del self._entries[key]

    def keys(self) -> list[tuple[str, int]]:
        with self._lock:
            return list(self._entries)


@dataclass
class Services:
    settings: Settings
    layout: Layout
    store: JobStore
    queue: JobQueue
    enhancers: EnhancerCache
    enhance_slots: asyncio.Semaphore
    extras: dict = field(default_factory=dict)


async def get_services(request: Request) -> Services:
    # async: FastAPI runs a plain ``def`` dependency in the thread pool, a hop per request
    # for an attribute read.
    return request.app.state.services


ServicesDep = Annotated[Services, Depends(get_services)]
