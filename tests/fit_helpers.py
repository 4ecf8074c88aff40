"""Toy posed photo sets for the fitter's tests (test_fit, test_fit_hash, test_splat_fit,
test_bench_kinds)."""

from __future__ import annotations

import json
from pathlib import Path

from roguenerf.data.toy import make_toy_world, render_toy_view, toy_camera_path, toy_intrinsics
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
