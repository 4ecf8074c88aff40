"""Per-view and mean PSNR/SSIM/FLIP of renders and enhanced images against the photos."""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

from roguenerf.errors import InputError


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


def evaluate(scene, model, *, split: str = "test", num_neighbours: int | None = None,
             max_views: int | None = None, device: str | torch.device = "cpu",
             progress: Callable[[int, int], None] | None = None, align=None,
             colour=None, trust=None) -> dict:
    """Compare renders and enhanced renders of ``split`` views with their photos.

    Neighbours always come from the scene's TRAIN views (a train view never uses itself).

    Args:
        scene: a Scene with photos, renders and depths for ``split``.
        model: an Enhancer, or a :class:`~roguenerf.inference.SceneEnhancer` of this scene.
        split: "test", "train" or "all".
        num_neighbours: override of the model's default.
        max_views: evaluate only the first views of the split (quick benchmarks).
        align: neighbour pose refinement (``SceneEnhancer``'s ``align``; default on). Ignored
            when ``model`` is a SceneEnhancer already.
        colour: colour matching to the neighbours (``SceneEnhancer``'s ``colour``; default on).
            Ignored when ``model`` is a SceneEnhancer already.
        trust: scale the enhancer's change down where the neighbours mostly disagree
            (``SceneEnhancer``'s ``trust``; default on). Ignored when ``model`` is a SceneEnhancer.
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
        enhancer = model
    else:
        was_training = model.training
        enhancer = SceneEnhancer(scene, model, num_neighbours=num_neighbours, device=device, align=align,
                                 colour=colour, trust=trust)
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
