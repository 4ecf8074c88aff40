"""Every knob of the worker and the service, from ``ROGUENERF_*`` environment variables.

Each field reads the environment variable ``ROGUENERF_<FIELD>`` (case-insensitive), e.g.
``ROGUENERF_DATA_DIR=/srv/roguenerf``. Lists (``cors_origins``) are JSON:
``ROGUENERF_CORS_ORIGINS='["https://app.example"]'``.

:class:`WorkerSettings` holds what the fine-tuning worker needs (data, job table, queue,
training, liveness); :class:`Settings` extends it with the API's own knobs, so one set of
variables configures both processes. Both live here, below the service and the worker: the
service re-exports :class:`Settings` (``service.settings``) and the workers package never
imports ``service``. This module imports only pydantic.
"""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


def _unset_if_empty(value):
    # docker compose passes ${VAR:-} as an empty string; that means "not configured".
    if isinstance(value, str) and not value.strip():
        return None
    if isinstance(value, SecretStr) and not value.get_secret_value().strip():
        return None
    return value


class WorkerSettings(BaseSettings):
    """Configuration of the fine-tuning worker: data, job table, queue, training, liveness."""

    model_config = SettingsConfigDict(env_prefix="ROGUENERF_", extra="ignore")

    data_dir: Path = Path("./data")
    """Scenes, checkpoints, job outputs, the SQLite job table and the SQLite queue live here."""
    redis_url: str | None = None
    """``redis://host:6379/0``: use RedisHuey for the queue; unset: SqliteHuey in data_dir."""
    database_url: str | None = None
    """Job/scene table: ``sqlite:///path.db`` (default: data_dir/roguenerf.db, WAL mode) or
    ``postgresql://user:pass@host/db`` (psycopg 3: the ``postgresql`` extra)."""
    default_checkpoint: Path | None = None
    """Checkpoint for scenes registered without one (default: the library's bundled weights)."""

    finetune_crop: int | None = Field(default=None, ge=8)
    """Training crop side for fine-tuning jobs (None: the library's default)."""
    finetune_batch: int = Field(default=4, ge=1)
    finetune_variant: str | None = None
    """Model variant for scenes fine-tuned without a checkpoint (None: the library's default)."""
    finetune_lr: float | None = Field(default=None, gt=0)
    """Adam learning rate for fine-tuning jobs (None: the library plan's, 5e-4 on a CPU, 1e-4 on a GPU)."""
    finetune_evaluate: bool = True
    """Measure the held-out views before and after fine-tuning (GET /jobs shows both)."""
    checkpoint_every_s: float = Field(default=60.0, gt=0)
    """Fine-tuning saves its state this often; a killed job resumes from there."""

    heartbeat_period: float = Field(default=5.0, gt=0)
    """A running job writes its heartbeat this often."""
    heartbeat_timeout: float = Field(default=60.0, gt=0)
    """A running job whose heartbeat is older than this is considered lost."""
    sweeper_period: float = Field(default=15.0, gt=0)
    """How often a worker looks for lost jobs."""
    max_attempts: int = Field(default=3, ge=1)
    """A lost job is requeued until it has been started this many times, then failed."""
    worker_poll_max_delay: float = Field(default=2.0, gt=0)
    """Longest pause between queue polls of an idle worker."""
    drain_timeout: float = Field(default=120.0, gt=0)
    """On SIGINT a worker asks its job to checkpoint and stop; it waits this long at most."""

    stale_temp_after_s: float = Field(default=6 * 3600, gt=0)
    """At start, temp files and folders older than this (a killed writer's) are swept from
    the data directory. Several machines share it: younger ones may be another process's
    upload in progress and are left alone."""

    @field_validator("redis_url", "database_url", mode="before")
    @classmethod
    def _empty_is_unset(cls, value):
        return _unset_if_empty(value)

    @field_validator("data_dir")
    @classmethod
    def _absolute(cls, value: Path) -> Path:
        return value.expanduser().resolve()

    @model_validator(mode="after")
    def _consistent(self):
        if self.heartbeat_timeout <= self.heartbeat_period:
            raise ValueError(
                f"heartbeat_timeout ({self.heartbeat_timeout}) must exceed heartbeat_period "
                f"({self.heartbeat_period}), or every running job would look lost"
            )
        return self

    @property
    def db_url(self) -> str:
        return self.database_url or f"sqlite:///{self.data_dir / 'roguenerf.db'}"

    @property
    def queue_path(self) -> Path:
        return self.data_dir / "queue.db"

    def env(self) -> dict[str, str]:
        """These settings as ``ROGUENERF_*`` variables, for a sibling worker process."""
        out: dict[str, str] = {}
        for name, value in self.model_dump().items():
            if value is None:
                continue
            if isinstance(value, SecretStr):
                value = value.get_secret_value()
            if isinstance(value, list):
                value = json.dumps(value)
            out[f"ROGUENERF_{name.upper()}"] = str(value)
        return out


class Settings(WorkerSettings):
    """Configuration of the API and the fine-tuning worker (env prefix ``ROGUENERF_``)."""

    api_key: SecretStr | None = None
    """When set, every route but /healthz needs ``Authorization: Bearer <key>``."""

    max_body_bytes: int = Field(default=1 << 30, ge=1024)
    """Largest request body (a zipped scene upload), chunked bodies included."""
    max_upload_pixels: int = Field(default=4096 * 4096, ge=1)
    """Largest render / depth accepted by /enhance (H * W)."""
    max_scene_files: int = Field(default=20_000, ge=1)
    """Largest number of members of a scene zip."""
    max_scene_bytes: int = Field(default=4 << 30, ge=1024)
    """Largest total uncompressed size of a scene zip."""
    max_checkpoint_bytes: int = Field(default=512 << 20, ge=1024)

    enhance_concurrency: int = Field(default=1, ge=1)
    """/enhance calls computed at once; more answer 503 with Retry-After at once."""
    enhancer_cache_size: int = Field(default=4, ge=1)
    """SceneEnhancers (one per scene and checkpoint version) kept in memory."""

    max_queued_jobs: int = Field(default=64, ge=1)
    """Fine-tuning jobs waiting in the queue at most; more answer 503 with Retry-After."""
    max_job_steps: int = Field(default=200_000, ge=1)
    max_job_minutes: float = Field(default=24 * 60, gt=0)

    cors_origins: list[str] = []
    """Origins allowed by CORS; empty: no CORS headers at all. Credentials are never allowed."""

    @field_validator("api_key", mode="before")
    @classmethod
    def _empty_key_is_unset(cls, value):
        return _unset_if_empty(value)
