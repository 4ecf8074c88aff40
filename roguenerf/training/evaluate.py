"""Per-view and mean PSNR/SSIM/FLIP of renders and enhanced images against the photos."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from roguenerf.errors import InputError

if TYPE_CHECKING:
    import torch


def _metrics_of(image, photo) -> dict:
    from roguenerf import metrics

    a, b = image[None].clamp(0, 1), photo[None]
    out = {"psnr": float(metrics.psnr(a, b)[0]), "ssim": float(metrics.ssim(a, b)[0]),
           "flip": float(metrics.flip(a, b)[0])}
    available = getattr(metrics, "lpips_available", None)
    if callable(available) and available():
        out["lpips"] = float(metrics.lpips(a, b)[0])
    return out


def _mean(views: list[dict], key: str) -> dict:
    if not views:
        return {}
    names = views[0][key].keys()
    return {m: sum(v[key][m] for v in views) / len(views) for m in names}


def evaluate(scene, model, *, split: str = "test", options=None, max_views: int | None = None,
             device: str | torch.device = "cpu", progress: Callable[[int, int], None] | None = None) -> dict:
    """Compare renders and enhanced renders of ``split`` views with their photos.

    Neighbours always come from the scene's TRAIN views (a train view never uses itself).

    Args:
        scene: a Scene with photos, renders and depths for ``split``.
        model: an Enhancer, or a :class:`~roguenerf.inference.SceneEnhancer` of this scene.
        split: "test", "train" or "all".
        options: the :class:`~roguenerf.enhance.EnhanceOptions` (neighbour rule and stages;
            default ``EnhanceOptions()``). Refused when ``model`` is a SceneEnhancer already
            (it has its own).
        max_views: evaluate only the first views of the split (quick benchmarks).
        progress: called as ``progress(done, total)`` before the first view and after each.
    Returns:
        ``{"split", "views": [{"name", "render": {"psnr", "ssim", "flip"}, "enhanced": {...},
        "neighbours", "seconds"}], "render": {mean psnr, ssim, flip}, "enhanced": {...},
        "seconds_per_view"}`` (plus "lpips" wherever LPIPS weights are available). "flip" is
        the mean LDR-FLIP error (:func:`roguenerf.metrics.flip`, lower is better).
    """
    from roguenerf.inference import SceneEnhancer

    indices = scene.indices(split)
    if not indices:
        raise InputError(f"scene {scene.root} has no {split!r} views to evaluate")
    if max_views is not None:
        indices = indices[: max(1, int(max_views))]
    if isinstance(model, SceneEnhancer):
        if options is not None:
            raise InputError("options: a SceneEnhancer has its own; pass the model, or give the options to the "
                             "SceneEnhancer")
        enhancer = model
    else:
        was_training = model.training
        enhancer = SceneEnhancer(scene, model, options=options, device=device)
    views = []
    if progress is not None:
        progress(0, len(indices))
    try:
        for i in indices:
            photo = scene.photo(i)
            render = scene.render(i)
            t0 = time.perf_counter()
            result = enhancer.enhance_view(i)
            seconds = time.perf_counter() - t0
            views.append({"name": scene.frames[i].name,
                          "render": _metrics_of(render, photo),
                          "enhanced": _metrics_of(result.image, photo),
                          "neighbours": result.neighbours,
                          "aligned": result.aligned,
                          "colour_offset": result.colour_offset,
                          "agreement": result.agreement,
                          "trust": result.trust,
                          "seconds": seconds})
            if progress is not None:
                progress(len(views), len(indices))
    finally:
        if not isinstance(model, SceneEnhancer) and was_training:
            model.train()
    return {"split": split, "views": views, "render": _mean(views, "render"),
            "enhanced": _mean(views, "enhanced"),
            "seconds_per_view": sum(v["seconds"] for v in views) / len(views)}
