"""Shared fixtures of the bench tests."""

from __future__ import annotations

import pytest


@pytest.fixture
def bright_toy(tmp_path):
    """``(folder, checkpoint)``: a toy scene at ``tmp_path/toy`` whose test views' renders come
    out too bright (as from a field that learned another exposure: colour matching changes them),
    and a fresh nano enhancer (the identity) saved as ``tmp_path/m.safetensors``."""
    from roguenerf.checkpoint import save_checkpoint
    from roguenerf.data.toy import make_toy_scene
    from roguenerf.imageio import read_image, write_png
    from roguenerf.models import Enhancer, make_config

    make_toy_scene(tmp_path / "toy", seed=2, n_train=6, n_test=2, height=72, width=96)
    for png in (tmp_path / "toy" / "renders").glob("test_*.png"):
        write_png(png, (read_image(png.read_bytes()) + 0.06).clamp(0, 1))
    ckpt = save_checkpoint(tmp_path / "m.safetensors", Enhancer(make_config("nano", num_neighbours=2)))
    return tmp_path / "toy", ckpt
