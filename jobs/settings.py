"""Every knob the job processes share, from ``ROGUENERF_*`` environment variables.

Each field reads the environment variable ``ROGUENERF_<FIELD>`` (case-insensitive), e.g.
``ROGUENERF_DATA_DIR=/srv/roguenerf``. Lists (``cors_origins``) are JSON:
``ROGUENERF_CORS_ORIGINS='["https://app.example"]'``.

:class:`JobSettings` holds what the fine-tuning worker needs (data, job table, queue,
training, liveness); ``python -m workers`` reads it, and the API's
:class:`service.settings.Settings` extends it with its own knobs, so one set of variables
configures both processes (``jobs`` imports neither ``service`` nor ``workers``). This module
imports only pydantic.
"""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


def unset_if_empty(value):
    # docker compose passes ${VAR:-} as an empty string; that means "not configured".
    if isinstance(value, str) and not value.strip():
        return None
    if isinstance(value, SecretStr) and not value.get_secret_value().strip():
        return None
    return value


class JobSettings(BaseSettings):
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
        return unset_if_empty(value)

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
