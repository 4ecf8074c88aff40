"""Service-side guards the library does not own: depth coverage and fine-tuning queue capacity.

Both answer before anything is computed or stored, with the error format of
:mod:`service.errors`.
"""

from __future__ import annotations

from service.errors import ApiError

MIN_VALID_DEPTH_FRACTION = 0.01
"""Below this share of known depth pixels (the library's rule,
:func:`roguenerf.geometry.depth.known_depth_mask`) a render cannot be reprojected
meaningfully: the request is refused instead of enhanced from a handful of points."""

QUEUE_FULL_RETRY_AFTER_S = 30


def check_depth_coverage(depth, *, field: str = "depth") -> float:
    """Share of usable pixels of ``depth`` ``(1, H, W)``; raises 422 when nearly all are missing.

    Known depth is the library's one rule (:func:`roguenerf.geometry.depth.known_depth_mask`:
    finite and 1e-6 < z < 1e10; zero, negative, non-finite and denormal values are unknown),
    so a map with a few unknown pixels is fine; one with almost nothing else is not.
    """
    import numpy as np

    from roguenerf import DEPTH_EPS, MAX_DEPTH, known_depth_mask

    # NumPy, single-threaded: a few torch element-wise ops on a render-sized map each enter an
    # OpenMP parallel region, which costs tens of ms when the cores are busy (e.g. with a
    # fine-tuning job). The float32 division is what torch's mean() gave, to the bit.
    values = depth.detach().cpu().numpy() if hasattr(depth, "detach") else np.asarray(depth)
    total = values.size
    count = int(np.count_nonzero(known_depth_mask(values)))
    fraction = float(np.float32(count) / np.float32(total)) if total else 0.0
    if fraction < MIN_VALID_DEPTH_FRACTION:
        raise ApiError(
            422, "invalid_input",
            f"{field}: only {count} of {total} pixels ({fraction:.2%}) are known depths (finite, "
            f"> {DEPTH_EPS:g} and < {MAX_DEPTH:g}); at least {MIN_VALID_DEPTH_FRACTION:.0%} must be "
            "(zero, negative, tiny, NaN and inf mean 'unknown')",
        )
    return fraction


def queue_full(exc) -> ApiError:
    """A :class:`jobs.store.QueueFull` refusal as 503 + Retry-After.

    The store counts waiting jobs and inserts the new one under one lock (one transaction),
    so ``max_queued_jobs`` holds under concurrent submissions to any number of API processes;
    a replay of an already accepted ``Idempotency-Key`` is never refused (it creates nothing).
    """
    return ApiError(
        503, "queue_full",
        f"{exc.waiting} fine-tuning jobs are already waiting (limit {exc.limit}, ROGUENERF_MAX_QUEUED_JOBS); "
        "retry later",
        headers={"Retry-After": str(QUEUE_FULL_RETRY_AFTER_S)},
    )


def decode_field(field: str, decode, data: bytes, **kwargs):
    """``decode(data, **kwargs)`` with library errors mapped to HTTP and prefixed by the form
    field: uploads arrive as bytes, so the library can only call them ``<N bytes>``."""
    from roguenerf import RoGUENeRFError
    from service.errors import library_error

    try:
        return decode(data, **kwargs)
    except RoGUENeRFError as exc:
        mapped = library_error(exc)
        mapped.message = f"{field}: {mapped.message}"
        mapped.args = (mapped.message,)
        raise mapped from None


def checkpoint_error(exc, path) -> ApiError:
    """A library checkpoint error as HTTP, naming the upload field instead of the server's
    temporary path (which is nobody's business outside the server)."""
    from service.errors import library_error

    mapped = library_error(exc)
    message = mapped.message.replace(str(path), "checkpoint")
    mapped.message = message if message.startswith("checkpoint") else f"checkpoint: {message}"
    mapped.args = (mapped.message,)
    return mapped
