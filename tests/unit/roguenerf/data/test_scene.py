"""Scene: lookups, lazy cached loaders with a byte-bounded LRU, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from roguenerf.data.scene import Frame, Scene
from roguenerf.errors import InputError
from roguenerf.imageio import write_png

H, W = 4, 6
IMAGE_BYTES = 3 * H * W * 4


def _scene(tmp_path, n=4, cache_bytes=10**9, renders=True) -> Scene:
    frames = []
    for i in range(n):
        image = tmp_path / f"img{i}.png"
        write_png(image, torch.full((3, H, W), i / 10))
        render = None
        if renders:
            render = tmp_path / f"ren{i}.png"
            write_png(render, torch.full((3, H, W), i / 20))
        depth = tmp_path / f"d{i}.npy"
        np.save(depth, np.full((H, W), 1.0 + i, dtype=np.float32))
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = float(i)
        K = torch.tensor([[5.0, 0, 3], [0, 5.0, 2], [0, 0, 1]], dtype=torch.float64)
        frames.append(Frame(f"view{i}", pose, K, W, H, "test" if i % 2 else "train", image, render, depth))
    return Scene(tmp_path, frames, meta={"format": "scene-folder"}, cache_bytes=cache_bytes)


def test_lookup_and_stacks(tmp_path):
    scene = _scene(tmp_path)
    assert len(scene) == 4
    assert scene.indices("train") == [0, 2] and scene.indices("test") == [1, 3]
    assert scene.indices("all") == [0, 1, 2, 3]
    assert scene.index("view2") == 2
    assert scene.poses().shape == (4, 4, 4) and scene.poses()[3, 0, 3] == 3.0
    assert scene.poses([1, "view3"])[:, 0, 3].tolist() == [1.0, 3.0]
    assert scene.intrinsics().shape == (4, 3, 3) and scene.intrinsics().dtype == torch.float64
    with pytest.raises(InputError, match="no view named 'nope'"):
        scene.index("nope")
    with pytest.raises(InputError, match="split must be"):
        scene.indices("val")
    with pytest.raises(InputError, match="out of range"):
        scene.photo(4)


def test_loaders_values_by_index_and_name(tmp_path):
    scene = _scene(tmp_path)
    assert torch.allclose(scene.photo(2), torch.full((3, H, W), round(0.2 * 255) / 255))
    assert torch.allclose(scene.render("view2"), torch.full((3, H, W), round(0.1 * 255) / 255))
    assert torch.equal(scene.depth(-1), torch.full((1, H, W), 4.0))


def test_cache_hit_returns_copies_and_skips_disk(tmp_path):
    scene = _scene(tmp_path)
    first = scene.photo(1)
    first.zero_()  # a caller modifying its tensor must not corrupt the cache
    (tmp_path / "img1.png").unlink()  # a cache hit does not touch the disk
    again = scene.photo(1)
    assert torch.allclose(again, torch.full((3, H, W), round(0.1 * 255) / 255))
    scene.clear_cache()
    with pytest.raises(InputError, match="img1.png"):
        scene.photo(1)


def test_cache_bounded_in_bytes_lru_order(tmp_path):
    scene = _scene(tmp_path, cache_bytes=2 * IMAGE_BYTES)
    scene.photo(0)
    scene.photo(1)
    scene.photo(0)  # 0 becomes most recent
    scene.photo(2)  # evicts 1
    assert scene._cache.nbytes <= 2 * IMAGE_BYTES
    assert len(scene._cache) == 2
    (tmp_path / "img1.png").unlink()
    scene.photo(0)  # still cached
    with pytest.raises(InputError):
        scene.photo(1)


def test_zero_cache_never_stores(tmp_path):
    scene = _scene(tmp_path, cache_bytes=0)
    scene.photo(0)
    assert len(scene._cache) == 0 and scene._cache.nbytes == 0


def test_missing_renders_reported(tmp_path):
    scene = _scene(tmp_path, renders=False)
    assert not scene.has_renders and scene.has_depths
    with pytest.raises(InputError, match="view 'view0' .* has no radiance-field render"):
        scene.render(0)


def test_repr_is_readable(tmp_path):
    text = repr(_scene(tmp_path))
    assert "4 views (2 train, 2 test), 6x4" in text
    assert "format=scene-folder" in text and "renders=yes" in text
    assert "Frame(" not in text


def test_invalid_frames_rejected(tmp_path):
    scene = _scene(tmp_path)
    frames = scene.frames + [scene.frames[0]]
    with pytest.raises(InputError, match="unique"):
        Scene(tmp_path, frames)
    bad = Frame("x", torch.eye(4, dtype=torch.float64), torch.eye(3, dtype=torch.float64), W, H, "val")
    with pytest.raises(InputError, match="split 'val'"):
        Scene(tmp_path, [bad])


def test_unusable_views_of_the_files_a_command_reads_fill_the_read_cache(tmp_path):
    """A one-view command checks the files it then reads (``reads``): through the scene's cache,
    so each is decoded once (issue 51), and no other file is read or kept; a check of the whole
    scene or of some views keeps nothing (it would evict what the cache holds)."""
    from roguenerf.data.scene import unusable_views

    scene = _scene(tmp_path)
    ramp = torch.linspace(0, 1, W).expand(3, H, W)  # not blank
    for i in range(4):
        write_png(tmp_path / f"img{i}.png", ramp)
        write_png(tmp_path / f"ren{i}.png", ramp.flip(-1))
    np.save(tmp_path / "d2.npy", np.zeros((H, W), dtype=np.float32))
    write_png(tmp_path / "ren2.png", torch.full((3, H, W), 0.5))  # blank, but not read below
    assert [v.name for v in unusable_views(scene)] == ["view2"]
    assert [v.name for v in unusable_views(scene, indices=[1, 2])] == ["view2"]
    assert len(scene._cache) == 0
    bad = unusable_views(scene, reads={1: ("render", "depth"), "view2": ("photo", "depth")})
    assert [(v.name, v.reason) for v in bad] == [
        ("view2", "depth has no usable values (all zeros; known: finite, > 1e-6 and < 1e10)")]
    assert len(scene._cache) == 4  # view 1's render and depth, view 2's photo and depth
    for name in ("ren1.png", "d1.npy", "img2.png"):
        (tmp_path / name).unlink()  # what the command reads next comes from the cache
    assert torch.equal(scene.depth(1), torch.full((1, H, W), 2.0))
    assert torch.allclose(scene.render(1), ramp.flip(-1), atol=0.5 / 255)
    assert torch.allclose(scene.photo(2), ramp, atol=0.5 / 255)
    # a file that cannot be read is named, and nothing of it is kept
    (tmp_path / "img3.png").write_bytes(b"not a png")
    [broken] = unusable_views(scene, reads={3: ("photo",)})
    assert broken.name == "view3" and "photo img3.png cannot be read" in broken.reason
    assert scene._cache.get(("photo", 3)) is None
    with pytest.raises(InputError, match="expected files among"):
        unusable_views(scene, reads={0: ("photos",)})
    with pytest.raises(InputError, match="indices or reads, not both"):
        unusable_views(scene, indices=[0], reads={0: ("photo",)})
