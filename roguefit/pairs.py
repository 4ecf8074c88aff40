"""Make pairs with any kind of field: split, fit (or cross-fit), render every view, write the scene folder.

``make_pairs(photos_dir, output, config)`` is the whole tool. It reads the posed photo set
(every ``config.hold``-th view held out), looks ``config.kind`` up in
:data:`roguefit.registry.FITTERS` and drives that :class:`~roguefit.fitter.Fitter`: it resumes an
interrupted fit from ``output/.fit/`` (each fitter saves its state there), renders every view
(RGB, z-depth, opacity), writes the scene folder that ``roguenerf`` reads and ``fit.json`` (the
report); a finished output folder (``fit.json`` with the same configuration) is left as it is.
With ``config.folds = K > 1`` it cross-fits: K fields, each rendering the views it never saw.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file
from torch import Tensor

from roguefit.fit import FitConfig
from roguefit.fitter import FieldConfig, Progress, ShouldStop
from roguefit.photos import PhotoSet, read_photo_set
from roguefit.registry import fitter_type
from roguenerf.errors import InputError, TrainingCancelled
from roguenerf.imageio import atomic_write, check_output_folder

log = logging.getLogger("roguefit")

STATE_DIR = ".fit"
"""The fitters' resume state, inside the output folder (``foldF/`` per fold when cross-fitting)."""
FIT_FILE = "fit.json"
FORMAT_VERSION = 1
"""Of ``fit.json``."""


def _metrics(renders: Tensor, photos: Tensor) -> dict:
    from roguenerf.metrics import psnr, ssim

    return {"psnr": float(psnr(renders, photos).mean()), "ssim": float(ssim(renders, photos).mean()),
            "views": int(renders.shape[0])}


def fold_of_views(ps: PhotoSet, folds: int) -> list[int | None]:
    """Cross-fitting's folds: the k-th training view (in view order) is in fold ``k % folds``; a
    held-out view is in none (``None``): no fold's field sees it, fold 0's renders it."""
    out: list[int | None] = [None] * len(ps.names)
    for k, i in enumerate(ps.indices("train")):
        out[i] = k % folds
    return out


def _fit_and_render(ps: PhotoSet, config: FieldConfig, state_dir: Path, views: list[int], *,
                    progress, should_stop, render_progress, rendered: int, total: int):
    """One field fitted to ``ps``'s training views (resumed from ``state_dir``), rendering ``views``."""
    fitter = fitter_type(config)(ps, config, state_dir)
    if fitter.load():
        log.info("resuming the fit at step %d (%.0f s done)", fitter.step, fitter.elapsed)
    fitter.run(progress, should_stop)
    t0 = time.perf_counter()
    renders, depths, accs = [], [], []
    for k in views:
        rgb, depth, acc = fitter.render_view(k)
        renders.append(rgb), depths.append(depth), accs.append(acc)
        rendered += 1
        if render_progress is not None:
            render_progress(rendered, total)
        if should_stop is not None and should_stop():
            raise TrainingCancelled("stopped while rendering; run again to resume (the fit is saved)")
    return fitter, (torch.stack(renders), torch.stack(depths), torch.stack(accs)), time.perf_counter() - t0


def _cross_fit(ps: PhotoSet, config: FieldConfig, state_dir: Path, *, progress, should_stop,
               render_progress) -> tuple[Tensor, Tensor, Tensor, dict]:
    """Every view rendered by a field that never saw it: ``config.folds`` fields, fold ``f``'s
    fitted to the training views outside fold ``f`` and rendering fold ``f`` (fold 0 also the
    held-out views). A finished fold's renders are kept in ``state_dir/foldF/renders.safetensors``,
    so a stopped run resumes at the fold it was in."""
    folds = fold_of_views(ps, config.folds)
    n = len(ps.names)
    renders = torch.zeros(n, 3, ps.height, ps.width)
    depths = torch.zeros(n, 1, ps.height, ps.width)
    accs = torch.zeros(n, 1, ps.height, ps.width)
    report = {"folds": config.folds, "fit_seconds": 0.0, "render_seconds": 0.0, "steps": 0, "fold_train_psnr": []}
    rendered = 0
    budget = config.steps
    for f in range(config.folds):
        views = [i for i in range(n) if folds[i] == f or (f == 0 and folds[i] is None)]
        last = f == config.folds - 1

        def fold_progress(p: dict, f=f) -> None:  # one bar over all folds: steps and fraction go on
            if progress is not None:
                progress({**p, "fold": f, "fraction": (f + p["fraction"]) / config.folds,
                          "step": p["step"] + (f * budget if budget is not None else 0)})

        def fold_render_progress(done: int, total: int, last=last) -> None:  # the views bar: last fold's
            if render_progress is not None and last:
                render_progress(done, total)

        fold_dir = state_dir / f"fold{f}"
        done = fold_dir / "renders.safetensors"
        sub = dataclasses.replace(ps, splits=["train" if folds[i] is not None and folds[i] != f else "test"
                                              for i in range(n)])
        saved, fold_report = None, None
        if done.is_file() and (fold_dir / "fold.json").is_file():  # a finished fold of this configuration
            fold_report = json.loads((fold_dir / "fold.json").read_text())
            saved = load_file(str(done)) if fold_report.get("config") == config.identity() else None
        if saved is not None and saved["views"].tolist() == views:
            rendered += len(views)
            fold_render_progress(rendered, n)
            rgb, depth, acc = saved["rgb"], saved["depth"], saved["acc"]
        else:
            fitter, (rgb, depth, acc), seconds = _fit_and_render(
                sub, config, fold_dir, views, progress=fold_progress, should_stop=should_stop,
                render_progress=fold_render_progress, rendered=rendered, total=n)
            rendered += len(views)
            own = sub.indices("train")[:3]  # how well this fold's field fits views it saw
            seen = torch.stack([fitter.render_view(i)[0] for i in own])
            fold_report = {"config": config.identity(), "steps": fitter.step, "fit_seconds": round(fitter.elapsed, 1),
                           "render_seconds": round(seconds, 1), "train_psnr": _metrics(seen, ps.photos[own])["psnr"]}
            save_file({"views": torch.as_tensor(views), "rgb": rgb.contiguous(), "depth": depth.contiguous(),
                       "acc": acc.contiguous()}, str(done.with_suffix(".tmp")))
            done.with_suffix(".tmp").replace(done)
            atomic_write(fold_dir / "fold.json", json.dumps(fold_report).encode())
        index = torch.as_tensor(views)
        renders[index], depths[index], accs[index] = rgb, depth, acc
        report["fit_seconds"] += fold_report["fit_seconds"]
        report["render_seconds"] += fold_report["render_seconds"]
        report["steps"] += fold_report["steps"]
        report["fold_train_psnr"].append(round(fold_report["train_psnr"], 3))
    report["fit_seconds"] = round(report["fit_seconds"], 1)
    report["render_seconds"] = round(report["render_seconds"], 1)
    return renders, depths, accs, report


def _is_fit(folder: Path) -> bool:
    """An earlier make-pairs output, finished (fit.json) or interrupted (its resume state)."""
    return (folder / FIT_FILE).is_file() or (folder / STATE_DIR).is_dir()


def make_pairs(photos_dir: str | Path, output: str | Path, config: FieldConfig = FitConfig(), *,
               progress: Progress | None = None, should_stop: ShouldStop | None = None,
               render_progress: Callable[[int, int], None] | None = None) -> dict:
    """Fit a field to ``photos_dir``'s training views and write the scene folder ``output``.

    Returns the fit report (also written as ``output/fit.json``): configuration, steps, seconds,
    and the renders' PSNR/SSIM on the training and held-out views, with the kind's own entries
    (:meth:`~roguefit.fitter.Fitter.summary`). ``config`` is any kind's (:data:`roguefit.PRESETS`,
    :data:`roguefit.registry.FITTERS`): a :class:`~roguefit.splats.SplatConfig` fits Gaussian
    splats, and writes their ``point_cloud.ply`` too.

    With ``config.folds = K > 1`` the renders are **cross-fitted**: K fields, each fitted to all
    training views but one fold's, render that fold, so every view's render is a novel view of
    a field that never saw its photo, with the field's real geometry error (K times the fitting
    time; the renders' cost is unchanged). The report's ``train`` metrics are then those of
    novel views, and ``fold_train_psnr`` says how well each fold's field fits views it saw.
    """
    from roguenerf.data.writers import write_scene_folder

    fitter_type(config)  # a kind nobody registered is refused before any work
    output = Path(output)
    # A posed photo set given as its own output (or any folder of the user's) is never written into:
    # write_scene_folder would overwrite its transforms.json and photos.
    check_output_folder(output, _is_fit, "output")
    done = output / FIT_FILE
    if done.is_file() and (output / "transforms.json").is_file():
        try:
            report = json.loads(done.read_text())
            if report.get("config") == config.identity():
                log.info("%s is complete (fit.json has this configuration): nothing to do", output)
                return report
        except (OSError, json.JSONDecodeError):
            pass
    ps = read_photo_set(photos_dir, hold=config.hold)
    if config.folds > 1:
        if len(ps.indices("train")) < 2 * config.folds:
            raise InputError(f"folds: {config.folds} folds need at least {2 * config.folds} training views, "
                             f"the photo set has {len(ps.indices('train'))}")
        renders, depths, accs, cross = _cross_fit(ps, config, output / STATE_DIR, progress=progress,
                                                  should_stop=should_stop, render_progress=render_progress)
        extras = {"folds": cross["folds"], "fold_train_psnr": cross["fold_train_psnr"]}
        steps, fit_seconds, render_seconds = cross["steps"], cross["fit_seconds"], cross["render_seconds"]
    else:
        fitter, (renders, depths, accs), render_seconds = _fit_and_render(
            ps, config, output / STATE_DIR, list(range(len(ps.names))), progress=progress,
            should_stop=should_stop, render_progress=render_progress, rendered=0, total=len(ps.names))
        fitter.write_extras(output)
        extras = fitter.summary()
        steps, fit_seconds = fitter.step, round(fitter.elapsed, 1)
    write_scene_folder(output, names=ps.names, photos=ps.photos, renders=renders, depths=depths,
                       world_from_cam=ps.world_from_cam, K=ps.K, splits=ps.splits, acc=accs)
    train, test = ps.indices("train"), ps.indices("test")
    report = {
        "format_version": FORMAT_VERSION,
        "photos": str(Path(photos_dir)),
        "config": config.identity(),
        "steps": steps,
        "fit_seconds": fit_seconds,
        "render_seconds": round(render_seconds, 1),
        **extras,
        "bounds": ps.bounds_note,
        "train": _metrics(renders[train], ps.photos[train]),
        "test": _metrics(renders[test], ps.photos[test]) if test else None,
    }
    atomic_write(done, json.dumps(report, indent=1).encode())
    return report
