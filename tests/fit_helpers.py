"""Toy posed photo sets for the fitter's tests (test_fit, test_fit_hash, test_splat_fit,
test_bench_kinds)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from roguefit import make_pairs, read_photo_set
from roguenerf.data.readers import load_scene
from roguenerf.data.toy import make_toy_world, render_toy_view, toy_camera_path, toy_intrinsics
from roguenerf.errors import TrainingCancelled
from roguenerf.geometry.cameras import opencv_to_opengl
from roguenerf.imageio import write_png

H, W, VIEWS = 30, 40, 17


def write_photo_set(root: Path, *, views: int = VIEWS, seed: int = 3, kind: str = "orbit") -> dict:
    """A toy photo set as ``../shared/data/real`` holds them (PNG photos, OpenGL poses, per-view
    near/far from the exact depth); returns the exact depths by view name. The orbit path's wide
    baseline pins the geometry down (a narrow forward-facing one leaves depth ambiguous at the
    test's tiny budget)."""
    world = make_toy_world(seed)
    poses = toy_camera_path(world, views, seed=seed, kind=kind)
    K = toy_intrinsics(H, W)
    frames, truth = [], {}
    (root / "images").mkdir(parents=True, exist_ok=True)
    for i, pose in enumerate(poses):
        rgb, depth = render_toy_view(world, pose, K, H, W)
        name = f"{i:03d}"
        write_png(root / "images" / f"{name}.png", rgb)
        truth[name] = depth
        frames.append({"file_path": f"images/{name}.png", "transform_matrix": opencv_to_opengl(pose).tolist(),
                       "near": float(depth.min()) * 0.8, "far": float(depth.max()) * 1.05})
    meta = {"w": W, "h": H, "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]),
            "cy": float(K[1, 2]), "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return truth


def constant_psnr(root: Path) -> float:
    """The PSNR of the photo set's training photos against their mean colour: what a field that
    learnt nothing but the average colour scores."""
    ps = read_photo_set(root)
    train = ps.indices("train")
    mean_colour = ps.photos[train].mean(dim=(0, 2, 3), keepdim=True)
    return float(-10 * torch.log10(((ps.photos[train] - mean_colour) ** 2).mean()))


def depth_errors(out: Path, truth: dict, *, acc: bool = True) -> tuple[list[torch.Tensor], list[float]]:
    """Per training view of the pair folder ``out``: the median relative error of its depth
    against the exact one (``truth``, from :func:`write_photo_set`) and the share of the near
    content it covers. Near is the floor, wall and boxes (exact depth < 8; the backdrop sphere at
    40 is ill-posed for any field); covered is where the field is opaque: its ``acc/<view>.png``
    over 0.5, or, for a field that writes none (``acc=False``), a depth over 0."""
    scene = load_scene(out)
    errors, coverage = [], []
    for i, frame in enumerate(scene.frames):
        if frame.split != "train":
            continue
        depth, true = scene.depth(i)[0], truth[frame.name][0]
        if acc:
            opacity = np.asarray(Image.open(out / "acc" / f"{frame.name}.png"), dtype=np.float32) / 255.0
            opaque = torch.from_numpy(opacity) > 0.5
        else:
            opaque = depth > 0
        near = true < 8.0
        ok = near & opaque
        coverage.append(float(ok.float().sum() / near.float().sum()))
        errors.append(((depth[ok] - true[ok]).abs() / true[ok]).median())
    return errors, coverage


@dataclass
class StoppedFit:
    """A fit run whole and the same fit stopped part way, then resumed (:func:`fit_stopped_and_resumed`)."""

    whole: dict
    """make_pairs' report of the uninterrupted run (into ``tmp_path/whole``)."""
    stopped: str
    """The message of the TrainingCancelled the stopped run raised."""
    folder: Path
    """``tmp_path``: the runs are in its ``whole`` and ``resumed``."""
    saved: list[str]
    """The files of the stopped run's state folder (``resumed/.fit``) when it stopped."""
    state_json: dict | None
    """Its ``state.json`` then (None where the kind writes none)."""
    resumed: dict
    """make_pairs' report of the run resumed to the end (into ``tmp_path/resumed``)."""

    def render_difference(self, view: int) -> float:
        """The largest difference of the two folders' renders of ``view``."""
        a = load_scene(self.folder / "whole").render(view)
        b = load_scene(self.folder / "resumed").render(view)
        return float((a - b).abs().max())


def fit_photo_set(tmp_path_factory, config, out_name: str, *, photos: str = "photos", views: int = VIEWS,
                  **options) -> tuple[Path, Path, dict, dict]:
    """A module's fitted toy photo set: :func:`write_photo_set` into a new folder named ``photos``,
    then ``make_pairs`` with ``config`` (and ``options``) into ``out_name`` beside it. Returns the
    photo folder, the pair folder, make_pairs' report and the set's truth."""
    root = tmp_path_factory.mktemp(photos)
    truth = write_photo_set(root, views=views)
    out = root.parent / out_name
    return root, out, make_pairs(root, out, config, **options), truth


def fit_stopped_and_resumed(tmp_path: Path, config, stop_at: int, *, progress=None) -> StoppedFit:
    """On a 9-view photo set, ``make_pairs`` with ``config`` run whole; then again into a second
    folder, stopped by ``should_stop`` on its ``stop_at``-th call (it must raise
    TrainingCancelled), and run once more to the end there (``progress`` sees that last run)."""
    root = tmp_path / "photos"
    write_photo_set(root, views=9)
    whole = make_pairs(root, tmp_path / "whole", config)
    calls = {"n": 0}

    def stop() -> bool:
        calls["n"] += 1
        return calls["n"] == stop_at

    with pytest.raises(TrainingCancelled) as stopped:
        make_pairs(root, tmp_path / "resumed", config, should_stop=stop)
    state = tmp_path / "resumed" / ".fit"
    saved = sorted(p.name for p in state.iterdir())
    state_json = json.loads((state / "state.json").read_text()) if "state.json" in saved else None
    resumed = make_pairs(root, tmp_path / "resumed", config, progress=progress)
    return StoppedFit(whole, str(stopped.value), tmp_path, saved, state_json, resumed)


def run_make_pairs(root: Path, out: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``roguenerf make-pairs ROOT --output OUT ARGS`` in a fresh process (``python -m roguecli``)."""
    return subprocess.run([sys.executable, "-m", "roguecli", "make-pairs", str(root), "--output", str(out), *args],
                          capture_output=True, text=True, timeout=timeout)


def ray_bundle(n: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``n`` random rays for a field's renderers: origins about (0, 0, -4), directions spread
    about +z, near 2 and far 7."""
    origins = torch.randn(n, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, -4.0])
    dirs = torch.cat([torch.randn(n, 2, generator=g) * 0.3, torch.ones(n, 1)], dim=1)
    return origins, dirs, torch.full((n,), 2.0), torch.full((n,), 7.0)
