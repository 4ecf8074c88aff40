"""The API's settings: the shared :class:`~jobs.settings.JobSettings` plus the API's own
knobs, in one class (env prefix ``ROGUENERF_``, e.g. ``ROGUENERF_API_KEY``).

The service owns these; the worker reads only its part (:class:`JobSettings` ignores the
others), and :meth:`Settings.env` hands all of them to a sibling worker process.
"""

from __future__ import annotations

from pydantic import Field, SecretStr, field_validator

from jobs.settings import JobSettings, unset_if_empty

__all__ = ["JobSettings", "Settings"]


class Settings(JobSettings):
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
        return unset_if_empty(value)
