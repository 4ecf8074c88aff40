"""One image-dtype rule (roguenerf.images): image tensors are float in [0, 1]; integer and bool
tensors are refused with an InputError naming the argument, the dtype and the conversion,
never clamped (a uint8 render clamped to [0, 1] was an all-white image). Image files are
converted by read_image's documented rule (8-bit / 255, 16-bit / 65535, 1-bit 0/1)."""

from __future__ import annotations

import pytest
import torch

from roguenerf.data.degrade import Degradation
from roguenerf.data.toy import make_toy_scene
from roguenerf.data.writers import write_scene_folder
from roguenerf.errors import InputError
from roguenerf.imageio import encode_png, read_image
from roguenerf.inference import SceneEnhancer
from roguenerf.metrics import lpips, psnr, ssim
from roguenerf.models import build_enhancer

INTEGER_DTYPES = [torch.uint8, torch.int16, torch.bool]
HINT = {torch.uint8: r"x\.float\(\) / 255", torch.int16: r"x\.float\(\) / 65535", torch.bool: r"x\.float\(\)"}


def _as(image: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``image`` in [0, 1] the way users hold it in ``dtype``."""
    if dtype == torch.bool:
        return image > 0.5
    top = 255 if dtype == torch.uint8 else 32767
    return (image * top).round().to(dtype)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp("toy"), seed=3, n_train=4, n_test=1, height=24, width=32)


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return build_enhancer("micro", num_neighbours=2)


@pytest.mark.parametrize("dtype", INTEGER_DTYPES)
def test_scene_enhancer_refuses_integer_renders(scene, model, dtype):
    enhancer = SceneEnhancer(scene, model)
    i = scene.index("test_000")
    frame = scene.frames[i]
    render = _as(scene.render(i), dtype)
    pattern = rf"render: expected a floating-point image with values in \[0, 1\], got dtype {dtype}.*{HINT[dtype]}"
    with pytest.raises(InputError, match=pattern):
        enhancer.enhance(render, scene.depth(i), frame.K, frame.world_from_cam)
    # an integer depth map is refused too (its units are the caller's to state)
    with pytest.raises(InputError, match="depth: expected a floating-point z-depth"):
        enhancer.enhance(scene.render(i), scene.depth(i).to(torch.int32), frame.K, frame.world_from_cam)


def test_converted_uint8_render_equals_the_decoded_png(scene, model):
    """The documented conversion (x.float() / 255) gives what read_image gives for the PNG."""
    enhancer = SceneEnhancer(scene, model)
    i = scene.index("test_000")
    frame = scene.frames[i]
    u8 = _as(scene.render(i), torch.uint8)
    by_hand = enhancer.enhance(u8.float() / 255, scene.depth(i), frame.K, frame.world_from_cam)
    decoded = enhancer.enhance(read_image(encode_png(u8.float() / 255)), scene.depth(i), frame.K, frame.world_from_cam)
    assert torch.equal(by_hand.image, decoded.image)
    assert float(by_hand.image.mean()) < 0.9  # not the all-white image of the old clamp


@pytest.mark.parametrize("dtype", INTEGER_DTYPES)
def test_model_refuses_integer_renders_and_photos(model, dtype):
    render = _as(torch.rand(1, 3, 16, 16), dtype)
    depth = torch.full((1, 1, 16, 16), 2.0)
    K = torch.tensor([[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]])[None]
    with pytest.raises(InputError, match=rf"render: .*got dtype {dtype}"):
        model(render, depth, K, torch.eye(4)[None], None)
    with pytest.raises(InputError, match=rf"photos: .*got dtype {dtype}"):
        model.encode_neighbours(render)


@pytest.mark.parametrize("dtype", INTEGER_DTYPES)
def test_metrics_refuse_integer_images(dtype):
    a = _as(torch.rand(1, 3, 8, 8), dtype)
    for metric in (psnr, ssim, lpips):
        with pytest.raises(InputError, match=rf"{metric.__name__}: first image: .*got dtype {dtype}"):
            metric(a, a)
        with pytest.raises(InputError, match=rf"second image: .*got dtype {dtype}"):
            metric(a.float(), a)


@pytest.mark.parametrize("dtype", INTEGER_DTYPES)
def test_scene_writer_and_degradation_refuse_integer_images(tmp_path, dtype):
    photos = torch.rand(2, 3, 8, 8)
    common = dict(names=["a", "b"], depths=torch.ones(2, 1, 8, 8), world_from_cam=torch.eye(4).expand(2, 4, 4),
                  K=torch.tensor([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]), splits=["train", "test"])
    with pytest.raises(InputError, match=rf"photos: .*got dtype {dtype}"):
        write_scene_folder(tmp_path / "a", photos=_as(photos, dtype), renders=photos, **common)
    with pytest.raises(InputError, match=rf"renders: .*got dtype {dtype}"):
        write_scene_folder(tmp_path / "b", photos=photos, renders=_as(photos, dtype), **common)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    with pytest.raises(InputError, match=rf"photos: .*got dtype {dtype}"):
        Degradation()(_as(photos, dtype), torch.ones(2, 1, 8, 8), torch.Generator())
    with pytest.raises(InputError, match=rf"image: .*got dtype {str(dtype).removeprefix('torch.')}"):
        encode_png(_as(photos[0], dtype).numpy())
