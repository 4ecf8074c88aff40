"""Request and response bodies, one family per resource (``SceneXxx``, ``JobXxx``, ``Camera``)."""

from __future__ import annotations

import math
from datetime import datetime, timezone
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pydantic_core import PydanticCustomError


def iso(ts: float | None) -> str | None:
    return None if ts is None else datetime.fromtimestamp(ts, timezone.utc).isoformat()


class ErrorInfo(BaseModel):
    code: str
    message: str


class ErrorBody(BaseModel):
    """Every 4xx/5xx answer has this shape."""

    error: ErrorInfo


class ScenePublic(BaseModel):
    id: str
    name: str | None = None
    """A person's label (the upload's ``name`` field, or the zip's file name without ``.zip``);
    None for scenes registered before scenes had names."""
    views: int
    """All views (train + test)."""
    train_views: int
    test_views: int
    width: int
    height: int
    created_at: str
    active_version: int
    """Checkpoint /enhance uses: N means checkpoints/vN.safetensors, 0 the default checkpoint."""
    checkpoint_versions: list[int]
    """Every stored version (older ones are kept)."""
    active_job: str | None
    """Id of the queued or running fine-tuning job, if any."""
    warnings: list[str] = []
    """Only in the registration's answer: problems that did not stop it, e.g. each unusable view
    ("NAME (train): depth has no usable values (all zeros ...)")."""


class SceneUpdate(BaseModel):
    """``PATCH /scenes/{id}``: a new name (whitespace runs become one space; at most 120 characters)."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(max_length=1000, description="the scene's new name")


class ScenePage(BaseModel):
    """One page of ``GET /scenes``, newest first."""

    items: list[ScenePublic]
    next_cursor: str | None
    """Pass as ``cursor`` for the next (older) page; None on the last page."""


class ViewCamera(BaseModel):
    """A view's camera in the form ``POST /enhance`` takes (its ``camera`` field)."""

    transform_matrix: list[list[float]]
    convention: Literal["opengl"]
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    depth_type: Literal["z"]
    """The ``depth`` of ``GET /scenes/{id}/views/{index}/depth`` is z-depth."""
    w: int
    h: int


class ViewPublic(BaseModel):
    index: int
    """Position in the scene; the ``{index}`` of the view routes."""
    name: str
    split: str
    width: int
    height: int
    has_photo: bool
    has_render: bool
    has_depth: bool
    camera: ViewCamera


class ViewList(BaseModel):
    items: list[ViewPublic]


class ImageScore(BaseModel):
    """An image compared with a view's photo (the library's ``psnr``, ``ssim`` and ``flip``)."""

    psnr: float | None
    """dB; null when the image equals the photo (infinite PSNR)."""
    ssim: float
    flip: float
    """Mean LDR-FLIP error (NVIDIA's perceptual error of rendered images), 0 to 1, lower is better."""


class JobCreate(BaseModel):
    """A fine-tuning budget: exactly one of ``steps`` or ``minutes``."""

    # The "exactly one" rule is published in the schema too, so generated clients and
    # fuzzers know that {} or both budgets at once are invalid.
    model_config = ConfigDict(extra="forbid", json_schema_extra={"oneOf": [
        {"required": ["steps"], "properties": {"steps": {"type": "integer"}, "minutes": {"type": "null"}}},
        {"required": ["minutes"], "properties": {"minutes": {"type": "number"}, "steps": {"type": "null"}}},
    ]})

    # The bounds are published in the schema too; the rules are the library's (_budget).
    steps: Annotated[int, Field(json_schema_extra={"exclusiveMinimum": 0})] | None = Field(
        default=None, description="optimiser steps")
    minutes: Annotated[float, Field(json_schema_extra={"exclusiveMinimum": 0})] | None = Field(
        default=None, description="wall-clock budget")

    @field_validator("steps", "minutes")
    @classmethod
    def _one_field(cls, value, info):
        """Each field alone, so a 422 names it (its ``loc``)."""
        budget = {"steps": None, "minutes": None, info.field_name: value}
        _budget(budget["steps"], budget["minutes"], field=info.field_name)
        return value

    @model_validator(mode="after")
    def _both_fields(self) -> JobCreate:
        """Exactly one of them: a queued job states its own length."""
        _budget(self.steps, self.minutes, required=True)
        return self


def _budget(steps, minutes, *, required: bool = False, field: str | None = None) -> None:
    """The training budget's rules, from the library (:meth:`TrainConfig.validate_budget`);
    broken, they answer 422 with the library's message (less the field's name when the error
    names the ``field`` already)."""
    from roguenerf import InputError, TrainConfig

    try:
        TrainConfig.validate_budget(steps, minutes, required=required)
    except InputError as exc:
        message = str(exc)
        if field is not None:
            message = message.removeprefix(f"{field}: ").removeprefix(f"{field} ")
        raise PydanticCustomError("invalid_budget", "{message}", {"message": message}) from None


class JobPublic(BaseModel):
    id: str
    scene_id: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    phase: Literal["training", "evaluating"] | None = None
    """While running: ``training`` (optimiser steps; progress, ETA) or ``evaluating`` (measuring
    the held-out views before the first step or after the last; no ETA). None otherwise, and
    while a job loads its scene."""
    request: dict
    progress: float
    """0 to 1."""
    eta_s: float | None
    step: int | None
    total_steps: int | None
    loss: float | None
    """Most recent training loss."""
    recent_losses: list[tuple[int, float]]
    """``[step, loss]`` pairs, oldest first (the last 20 reported)."""
    attempt: int
    cancel_requested: bool
    error: ErrorInfo | None
    before: dict | None
    """Metrics of the scene's held-out views before fine-tuning (when the library reports them)."""
    after: dict | None
    result: dict | None
    """Training summary: steps, seconds, final_loss, loss_kind, config."""
    checkpoint_version: int | None
    """The scene checkpoint version this job produced (succeeded jobs)."""
    created_at: str
    started_at: str | None
    finished_at: str | None
    heartbeat_at: str | None

    @classmethod
    def from_row(cls, row: dict) -> JobPublic:
        result = row.get("result") or None
        error = None
        if row["error_code"]:
            error = ErrorInfo(code=row["error_code"], message=row["error_message"] or "")
        summary = None
        if result is not None:
            summary = {k: v for k, v in result.items() if k not in ("before", "after")}
        return cls(
            id=row["id"], scene_id=row["scene_id"], state=row["state"], phase=row.get("phase"),
            request=row["request"],
            progress=row["progress"], eta_s=row["eta_s"], step=row["step"], total_steps=row["total_steps"],
            loss=row["loss"], recent_losses=[tuple(x) for x in (row["losses"] or [])],
            attempt=row["attempt"], cancel_requested=row["cancel_requested"], error=error,
            before=(result or {}).get("before"), after=(result or {}).get("after"), result=summary,
            checkpoint_version=row["checkpoint_version"], created_at=iso(row["created_at"]),
            started_at=iso(row["started_at"]), finished_at=iso(row["finished_at"]),
            heartbeat_at=iso(row["heartbeat_at"]),
        )


class JobPage(BaseModel):
    """One page of ``GET /jobs``, newest first."""

    items: list[JobPublic]
    next_cursor: str | None
    """Pass as ``cursor`` for the next (older) page; None on the last page."""


class Camera(BaseModel):
    """Pose and intrinsics of the render sent to /enhance (the ``camera`` form field, JSON)."""

    model_config = ConfigDict(extra="forbid")

    transform_matrix: list[list[float]] = Field(
        description="4x4 camera-to-world, or its top 3 rows (3x4, as most tools print poses)")
    convention: Literal["opengl", "opencv"] = Field(
        description="opengl: nerfstudio/Blender (x right, y up, -z forward); opencv: x right, y down, z forward")
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    depth_type: Literal["z", "ray"] = Field(
        description="z: distance along the optical axis; ray: distance along each pixel's ray")
    w: int | None = Field(default=None, description="optional; must match the render's width")
    h: int | None = Field(default=None, description="optional; must match the render's height")

    @field_validator("transform_matrix")
    @classmethod
    def _four_by_four(cls, value):
        if len(value) not in (3, 4) or any(len(row) != 4 for row in value):
            shape = f"{len(value)} rows of lengths {[len(r) for r in value]}"
            raise ValueError(f"expected 4x4 or 3x4 (4 or 3 rows of 4 numbers), got {shape}")
        if not all(math.isfinite(x) for row in value for x in row):
            raise ValueError("contains NaN or infinite values")
        return value
