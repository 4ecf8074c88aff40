"""Tiled inference: tile layout, blending weights, agreement with untiled inference, no seams."""

from __future__ import annotations

import pytest
import torch

from roguenerf.errors import InputError
from roguenerf.models import build_enhancer
from roguenerf.models.tiling import axis_weights, enhance_tiled, tile_starts
from tests.model_helpers import make_views, randomise

pytestmark = pytest.mark.usefixtures("one_thread")


def test_tile_starts_known_answers():
    assert tile_starts(100, 128, 32) == [0]
    assert tile_starts(400, 256, 32, align=64) == [0, 192]
    assert tile_starts(400, 160, 32, align=64) == [0, 128, 256]
    # An alignment bigger than tile - overlap falls back to the flow grid (8).
    assert tile_starts(300, 128, 32, align=128) == [0, 96, 192]


@pytest.mark.parametrize(("size", "tile", "overlap"), [(400, 160, 32), (300, 128, 96), (97, 40, 17)])
def test_weights_are_a_partition_of_unity_and_zero_near_inner_borders(size, tile, overlap):
    starts = tile_starts(size, tile, overlap, align=8)
    weights = axis_weights(starts, tile, size, "cpu", torch.float64)
    total = torch.zeros(size, dtype=torch.float64)
    for s, wgt in zip(starts, weights):
        total[s:s + wgt.numel()] += wgt
    ends = [s + wgt.numel() for s, wgt in zip(starts, weights)]
    assert ends[-1] == size
    # Separate overlaps sum to exactly 1; overlaps that meet inside a tile (tile < 2 overlap)
    # only need a positive total, enhance_tiled divides by it.
    disjoint = all(ends[j] <= starts[j + 2] for j in range(len(starts) - 2))
    if disjoint:
        assert torch.allclose(total, torch.ones(size, dtype=torch.float64))
    assert (total > 0.1).all()
    for j, wgt in enumerate(weights):
        if j + 1 < len(starts):
            o = ends[j] - starts[j + 1]
            assert (wgt[-(o // 4):] == 0).all()
            if disjoint:
                assert wgt[-o - 1] == 1
        if j > 0:
            o = ends[j - 1] - starts[j]
            assert (wgt[:o // 4] == 0).all()


def test_small_images_are_not_tiled():
    torch.manual_seed(0)
    model = randomise(build_enhancer("micro"))
    r, d, K, P, nb = make_views(model, n=1, h=40, w=50)
    with torch.no_grad():
        assert torch.equal(enhance_tiled(model, r, d, K, P, nb, tile=64, overlap=16), model(r, d, K, P, nb))


def test_bad_tile_arguments():
    model = build_enhancer("micro")
    r, d, K, P, nb = make_views(model, n=0, h=40, w=50)
    with pytest.raises(InputError, match="tile: expected an integer >= 16"):
        enhance_tiled(model, r, d, K, P, nb, tile=8, overlap=2)
    with pytest.raises(InputError, match=r"overlap: expected an integer in \[0, tile=32\)"):
        enhance_tiled(model, r, d, K, P, nb, tile=32, overlap=32)


def test_tiled_equals_untiled_for_a_conv_model():
    """Exact agreement where it must hold.

    Configuration: ``use_uformer=False`` (the merged features go through one 3x3 conv) and
    ``use_refinement=False``. Every remaining operation is a 3x3 conv or per-pixel (the
    reprojection of the whole neighbour image into the tile's camera, whose K has cx, cy
    shifted by the tile offset), so the receptive field is 6 px (conv_I 2, attention 2,
    merge 1, output 1). With overlap 32 the blending gives zero weight to the outer 8 px of
    every inner tile border, so every pixel comes from tiles that see its full receptive
    field and tiled == untiled to float rounding. Zero-initialised layers are randomised
    first, otherwise both would trivially equal the render.
    """
    torch.manual_seed(0)
    model = randomise(build_enhancer("nano", use_uformer=False, use_refinement=False))
    r, d, K, P, nb = make_views(model, n=2, h=100, w=130)
    with torch.no_grad():
        full = model(r, d, K, P, nb)
        tiled = enhance_tiled(model, r, d, K, P, nb, tile=48, overlap=32)
    assert (full - r).abs().mean() > 0.01
    assert torch.allclose(tiled, full, atol=1e-4)


def test_tiled_equals_untiled_with_flow_refinement():
    """The flow network adds a large receptive field at 1/8 resolution.

    Configuration: ``use_uformer=False``, one flow iteration. Bound on the receptive field:
    the 1/8 flow at a cell depends on +-7 cells (encoder 2 convs, update input 1, GRU 2,
    increment head 2), bilinear upsampling adds 1 cell, the 8x8 pooling cell 7 px: +-71 px,
    plus conv_I 2 px, attention 2 + merge 1 + output 1 px, plus the flow displacement
    itself (asserted < 4 px here) = under 82 px. Overlap 336 gives zero weight to the outer
    84 px of every inner tile border; tile offsets are multiples of 8 (the model's
    ``tile_alignment``), so the pooling grids coincide and tiled == untiled to rounding.
    """
    torch.manual_seed(0)
    model = randomise(build_enhancer("micro", use_uformer=False, flow_iters=1))
    r, d, K, P, nb = make_views(model, n=1, h=96, w=400)
    assert model.tile_alignment == 8
    with torch.no_grad():
        flow = model.flow(model.encode_neighbours(torch.rand(1, 3, 96, 400)), model.conv_I(r))
        assert 0.1 < flow.abs().max() < 4.0
        full = model(r, d, K, P, nb)
        tiled = enhance_tiled(model, r, d, K, P, nb, tile=352, overlap=336)
    assert torch.allclose(tiled, full, atol=1e-4)


def _column_jumps(x: torch.Tensor) -> torch.Tensor:
    """``(B, 3, H, W)`` -> ``(W - 1,)`` mean absolute difference between neighbouring columns."""
    return (x[..., 1:] - x[..., :-1]).abs().mean(dim=(0, 1, 2))


@pytest.mark.parametrize("seed", [0, 1])
def test_full_model_tiling_is_close_and_seamless(seed):
    """With the Uformer the model is not translation-equivariant (windows, padding, global
    receptive field), so tiled inference can only be close. Tile offsets follow the model's
    ``tile_alignment`` (64 for nano), so windows and padding grids coincide and tiles differ
    from the whole image only through their missing context.

    Measured on randomised nano models (enhancement mean |out - render| ~ 0.05): tiled vs
    untiled differ by 0.1-0.4 % of the enhancement; the largest column-to-column jump that
    tiling adds to the output (jumps of tiled - untiled) is 2-7 % of the median column jump
    of the enhancement itself, so no seam can stand out. Thresholds: 2 % and 10 %. (The tiles
    agree so closely here that even a hard cut stays under 12 %; the blending weights
    themselves are tested above.)
    """
    torch.manual_seed(seed)
    model = randomise(build_enhancer("nano"), seed=seed)
    r, d, K, P, nb = make_views(model, n=1, h=64, w=320, seed=seed)
    with torch.no_grad():
        full = model(r, d, K, P, nb)
        tiled = enhance_tiled(model, r, d, K, P, nb, tile=192, overlap=64)
    assert tile_starts(320, 192, 64, model.tile_alignment) == [0, 128]
    change = (full - r).abs().mean()
    assert change > 0.01
    assert (tiled - full).abs().mean() < 0.02 * change
    assert _column_jumps(tiled - full).max() < 0.1 * _column_jumps(full - r).median()
