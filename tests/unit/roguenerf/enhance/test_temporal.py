"""The temporal filter of camera-path videos (roguenerf.enhance.temporal): known answers."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from roguenerf.enhance.temporal import TemporalConfig, TemporalFilter, settling
from roguenerf.errors import InputError
from tests.geometry_helpers import turned

H, W = 20, 24
K = torch.tensor([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
DEPTH = torch.full((1, H, W), 3.0)
POSE = torch.eye(4, dtype=torch.float64)


def _frame(seed: int):
    g = torch.Generator().manual_seed(seed)
    render = 0.25 + 0.5 * torch.rand(3, H, W, generator=g)
    enhanced = (render + 0.1 * torch.randn(3, H, W, generator=g)).clamp(0, 1)
    return render, enhanced


def test_first_frame_is_its_own_and_a_still_camera_averages_the_residuals():
    f = TemporalFilter(TemporalConfig(weight=0.5, blend="residual", reject=0.0))  # the blend alone
    r1, e1 = _frame(1)
    assert torch.equal(f(r1, e1, DEPTH, K, POSE), e1)
    assert f.last_share == 0.0
    r2, e2 = _frame(2)
    out = f(r2, e2, DEPTH, K, POSE)
    # the same camera: every pixel sees the previous frame, at the same place
    assert f.last_share == pytest.approx(1.0)
    expected = (r2 + 0.5 * (e2 - r2) + 0.5 * (e1 - r1)).clamp(0, 1)
    assert torch.allclose(out, expected, atol=1e-5)
    # recursive: the third frame weighs the first by 1/4
    r3, e3 = _frame(3)
    out3 = f(r3, e3, DEPTH, K, POSE)
    expected3 = (r3 + 0.5 * (e3 - r3) + 0.5 * (expected - r2)).clamp(0, 1)
    assert torch.allclose(out3, expected3, atol=1e-5)


def test_a_cut_keeps_the_frame_and_weight_zero_changes_nothing():
    f = TemporalFilter()
    r1, e1 = _frame(1)
    f(r1, e1, DEPTH, K, POSE)
    r2, e2 = _frame(2)
    assert torch.equal(f(r2, e2, DEPTH, K, turned(POSE, 180.0)), e2)  # sees nothing of the last frame
    assert f.last_share == 0.0
    still = TemporalFilter(TemporalConfig(weight=0.0))
    still(r1, e1, DEPTH, K, POSE)
    assert torch.equal(still(r2, e2, DEPTH, K, POSE), e2)
    f.reset()
    assert torch.equal(f(r1, e1, DEPTH, K, POSE), e1)


def test_a_moving_camera_carries_the_residual_to_where_the_point_went():
    """A camera moved sideways by one pixel's worth: a residual spike at pixel (10, 8) lands at
    (10, 7) in the next frame (z = 3, f = 30: 0.1 units to the right is one pixel to the left).
    No fade: the weight is the configured one (the fade is tested below)."""
    f = TemporalFilter(TemporalConfig(weight=0.5, blend="residual", fade_deg=0.0))
    render = torch.full((3, H, W), 0.5)
    spike = render.clone()
    spike[:, 10, 8] = 0.9
    f(render, spike, DEPTH, K, POSE)
    moved = POSE.clone()
    moved[0, 3] = 0.1
    out = f(render, render, DEPTH, K, moved)
    assert float(out[0, 10, 7]) == pytest.approx(0.5 + 0.5 * 0.4, abs=1e-4)
    assert float(out[0, 10, 8]) == pytest.approx(0.5, abs=1e-4)


@pytest.mark.parametrize("weight", [1.0, -0.1, float("nan"), "0.5"])
def test_bad_weights_are_refused(weight):
    with pytest.raises(InputError, match="weight"):
        TemporalConfig(weight=weight)


def test_shapes_are_checked():
    f = TemporalFilter()
    r, e = _frame(1)
    with pytest.raises(InputError, match="same"):
        f(r, e[:, :-1], DEPTH, K, POSE)
    with pytest.raises(InputError, match="depth"):
        f(r, e, DEPTH[:, :-1], K, POSE)


def test_sticky_neighbours_keep_what_is_still_near():
    from roguenerf.enhance.temporal import sticky_neighbours

    assert sticky_neighbours(None, [3, 4], [3, 4, 5, 6]) == [3, 4]  # the first frame: the rule's choice
    # 7 is still among the nearest: kept; 8 is not: the rule's first choice not kept takes its place
    assert sticky_neighbours([7, 8], [3, 4], [3, 7, 4, 5]) == [7, 3]
    assert sticky_neighbours([3, 4], [4, 5], [3, 4, 5, 6]) == [3, 4]  # both still near: no change
    # the rule now takes 3: two kept, one added; then 1: only the first kept one
    assert sticky_neighbours([3, 4], [5, 6, 7], [3, 4, 5, 6]) == [3, 4, 5]
    assert sticky_neighbours([3, 4], [5], [3, 4, 5, 6]) == [3]
    assert sticky_neighbours([3, 4], [], [3, 4]) == []


@pytest.mark.parametrize("keep", [-1, 2.5, True])
def test_bad_keep_within_is_refused(keep):
    with pytest.raises(InputError, match="keep_within"):
        TemporalConfig(keep_within=keep)


def test_a_neighbour_change_settles_over_change_frames():
    """The frame whose neighbour set changed and the change_frames - 1 after it take change_weight."""
    changes = [5, 20]
    assert [t for t in range(30) if settling(changes, t, 3)] == [5, 6, 7, 20, 21, 22]
    assert [t for t in range(30) if settling(changes, t, 1)] == [5, 20]
    assert not any(settling(changes, t, 0) for t in range(30))
    assert [t for t in range(12) if settling([5, 7], t, 3)] == [5, 6, 7, 8, 9]  # a second change restarts it
    assert not any(settling([], t, 3) for t in range(30))


@pytest.mark.parametrize("frames", [-1, 2.5, True, "3"])
def test_bad_change_frames_is_refused(frames):
    with pytest.raises(InputError, match="change_frames"):
        TemporalConfig(change_frames=frames)


def test_blending_the_image_averages_the_frames_themselves():
    """blend="image": the enhanced frames are averaged (a render's own flicker too), not the change."""
    f = TemporalFilter(TemporalConfig(weight=0.5, blend="image", reject=0.0))
    r1, e1 = _frame(1)
    assert torch.equal(f(r1, e1, DEPTH, K, POSE), e1)
    r2, e2 = _frame(2)
    assert torch.allclose(f(r2, e2, DEPTH, K, POSE), 0.5 * e2 + 0.5 * e1, atol=1e-5)
    with pytest.raises(InputError, match="blend"):
        TemporalConfig(blend="pixels")


def test_a_last_frame_further_along_the_path_weighs_less():
    """frames_apart = k: the last frame kept weighs weight ** k (a moving average over k frames
    would leave it that much); the change weight the same way; k must be a whole number >= 1."""
    r1, e1 = _frame(1)
    r2, e2 = _frame(2)
    for changed, w in ((False, 0.8), (True, 0.9)):
        f = TemporalFilter(TemporalConfig(weight=0.8, change_weight=0.9, blend="image", reject=0.0))
        f(r1, e1, DEPTH, K, POSE)
        out = f(r2, e2, DEPTH, K, POSE, changed=changed, frames_apart=4)
        assert torch.allclose(out, (1 - w ** 4) * e2 + w ** 4 * e1, atol=1e-5)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(InputError, match="frames_apart"):
            f(r2, e2, DEPTH, K, POSE, frames_apart=bad)


# --- issue 51: frames between the model's carry the last one -----------------------------------


@pytest.mark.parametrize("blend", ["image", "residual"])
def test_a_carried_frame_is_the_last_result_moved_and_the_render_where_it_is_not_seen(blend):
    """A camera moved sideways by one pixel (z = 3, f = 30): the last frame's result lands one
    pixel to the left; the last column, which the last frame does not see, is the render's."""
    f = TemporalFilter(TemporalConfig(blend=blend, model_every=2, min_seen=0.9, reject=0.0, carry_agreement=0.0,
                                      carry_from="last"))
    r1, e1 = _frame(1)
    f(r1, e1, DEPTH, K, POSE)
    assert not f.model_due(1) and f.model_due(2) and f.model_due(1, changed=True)
    moved = POSE.clone()
    moved[0, 3] = 0.1
    r2, _ = _frame(2)
    out = f.carry(r2, DEPTH, K, moved)
    carried = e1[:, :, 1:] if blend == "image" else r2[:, :, :-1] + (e1 - r1)[:, :, 1:]
    assert torch.allclose(out[:, :, :-1], carried.clamp(0, 1), atol=1e-5)
    assert torch.equal(out[:, :, -1], r2[:, :, -1])
    assert f.last_share == pytest.approx(1 - 1 / W)
    # the carried frame is the last one now: carried again, it moves on by another pixel
    further = POSE.clone()
    further[0, 3] = 0.2
    again = f.carry(r2, DEPTH, K, further)
    assert torch.allclose(again[:, :, :-2], out[:, :, 1:-1] if blend == "image"
                          else (r2[:, :, :-2] + (out - r2)[:, :, 1:-1]).clamp(0, 1), atol=1e-5)


def test_a_frame_the_last_one_barely_sees_is_not_carried():
    f = TemporalFilter(TemporalConfig(model_every=3))
    r1, e1 = _frame(1)
    assert f.model_due(1) and f.carry(r1, DEPTH, K, POSE) is None  # no last frame yet
    f(r1, e1, DEPTH, K, POSE)
    assert f.carry(r1, DEPTH, K, turned(POSE, 180.0)) is None and f.last_share == 0.0  # a cut
    moved = POSE.clone()
    moved[0, 3] = 0.5  # five pixels: 5 / 24 of the frame unseen, more than 1 - min_seen
    assert f.carry(r1, DEPTH, K, moved) is None
    assert f.last_share == pytest.approx(1 - 5 / W)
    assert torch.allclose(f.carry(r1, DEPTH, K, POSE), e1, atol=1e-6)  # nothing kept by the refusals: frame 1


@pytest.mark.parametrize("field,value", [("model_every", 0), ("model_every", 1.5), ("model_every", True),
                                         ("min_seen", 1.5), ("min_seen", -0.1)])
def test_bad_carry_settings_are_refused(field, value):
    with pytest.raises(InputError, match=field):
        TemporalConfig(**{field: value})


def _wave(shift: float):
    """A sine of period 4 pixels along x, moved by ``shift`` pixels, ``(3, H, W)``."""
    x = torch.arange(W, dtype=torch.float32)
    return (0.5 + 0.3 * torch.sin(2 * torch.pi * (x + shift) / 4)).expand(3, H, W)

def test_bicubic_resampling_keeps_the_detail_a_half_pixel_move_blurs():
    """A sine of period 4 pixels moved by half a pixel: bilinear sampling averages neighbouring
    pixels (amplitude x0.71); bicubic lands within a fifth of its error of the true moved sine."""
    moved = POSE.clone()
    moved[0, 3] = 0.05  # half a pixel: the points land half a pixel further right in the last frame
    errors = {}
    for resample in ("bilinear", "bicubic"):
        f = TemporalFilter(TemporalConfig(model_every=2, min_seen=0.5, resample=resample, reject=0.0,
                                          carry_agreement=0.0))
        f(_wave(0.0), _wave(0.0), DEPTH, K, POSE)
        out = f.carry(torch.zeros(3, H, W), DEPTH, K, moved)
        errors[resample] = float((out - _wave(0.5))[:, :, 2:-2].abs().max())  # away from the edges
    assert errors["bilinear"] > 0.06  # 0.3 * 0.71 * (1 - 0.71): the samples sit at 0.71 of the peak
    assert errors["bicubic"] < errors["bilinear"] / 5
    with pytest.raises(InputError, match="resample"):
        TemporalConfig(resample="nearest")



def test_carried_from_the_model_frame_is_resampled_once():
    """Two carried frames after a model frame, each half a pixel further (a sine of period 4
    pixels): carried from the last frame, the second is resampled twice and loses some of the
    wave; carried from the model frame, it is the model frame moved by a whole pixel, exact.
    The frame before it is the last frame either way, so the first carry is the same; the
    flicker report's warp is kept only for a move from the last frame."""
    half, whole = POSE.clone(), POSE.clone()
    half[0, 3], whole[0, 3] = 0.05, 0.1
    out = {}
    for source in ("last", "model"):
        f = TemporalFilter(TemporalConfig(model_every=3, min_seen=0.5, reject=0.0, carry_from=source,
                                          carry_agreement=0.0))
        f(_wave(0.0), _wave(0.0), DEPTH, K, POSE)
        first = f.carry(torch.zeros(3, H, W), DEPTH, K, half)
        assert f.last_warp is not None
        f.remember(torch.zeros(3, H, W), first, DEPTH, K, half, model=False)
        out[source] = (first, f.carry(torch.zeros(3, H, W), DEPTH, K, whole))
        assert (f.last_warp is None) == (source == "model")
    assert torch.equal(out["last"][0], out["model"][0])
    inner = (slice(None), slice(None), slice(3, -3))  # away from the edges
    assert float((out["model"][1] - _wave(1.0))[inner].abs().max()) < 1e-4
    assert float((out["last"][1] - _wave(1.0))[inner].abs().max()) > 0.005
    with pytest.raises(InputError, match="carry_from"):
        TemporalConfig(carry_from="first")


def test_a_frame_between_two_model_frames_mixes_them_by_how_near_each_is():
    """Model frames at x = 0 and x = 0.3 (three pixels apart), a frame between at x = 0.1 (a
    third of the way): the two results moved into it and mixed 2/3 : 1/3 where both see; its
    first two columns only the first sees (the second's view starts two pixels to their right),
    its last column only the second: each is that one's alone. A frame the two do not see
    enough of together is refused."""
    f = TemporalFilter(TemporalConfig(model_every=3, carry_between=True, reject=0.0, min_seen=0.9))
    render = torch.full((3, H, W), 0.5)
    before_pose, after_pose, here = POSE.clone(), POSE.clone(), POSE.clone()
    after_pose[0, 3], here[0, 3] = 0.3, 0.1
    f.remember(render, torch.full((3, H, W), 0.2), DEPTH, K, before_pose)
    before = f.kept
    f.remember(render, torch.full((3, H, W), 0.8), DEPTH, K, after_pose)
    after = f.kept
    f.restore(before)
    out = f.carry(render, DEPTH, K, here, between=(before, after, 1 / 3))
    assert torch.allclose(out[:, :, 2:-1], torch.full((3, H, W - 3), 0.4), atol=1e-5)  # 2/3 0.2 + 1/3 0.8
    assert torch.allclose(out[:, :, :2], torch.full((3, H, 2), 0.2), atol=1e-5)  # only the first sees
    assert torch.allclose(out[:, :, -1], torch.full((3, H), 0.8), atol=1e-5)  # only the second
    assert f.last_warp is None and f.last_share == pytest.approx(1.0)
    # between_agreement: the two moved results against each other where both see (0.2 against 0.8:
    # 10 log10(1 / 0.36) = 4.44 dB), beside the renders' gate (equal renders: passed); a frame the
    # two disagree on is not carried
    for gate, carried in ((10.0, False), (4.0, True)):
        judged = TemporalFilter(TemporalConfig(model_every=3, reject=0.0, min_seen=0.9, between_agreement=gate,
                                               carry_agreement=46.0))
        judged.restore(before)
        assert (judged.carry(render, DEPTH, K, here, between=(before, after, 1 / 3)) is not None) == carried
        assert judged.last_mutual == pytest.approx(4.437, abs=1e-3) and judged.last_agreement > 100
    far = POSE.clone()
    far[0, 3] = 1.5  # 15 pixels on: neither sees enough of it
    assert f.carry(render, DEPTH, K, far, between=(before, after, 0.5)) is None
    with pytest.raises(InputError, match="position"):
        f.carry(render, DEPTH, K, here, between=(before, after, 1.0))
    with pytest.raises(InputError, match="carry_between"):
        TemporalConfig(carry_between=True, keep_within=4, model_every=2)
    assert TemporalConfig(keep_within=4).carry_between  # nothing is carried at model_every 1
    with pytest.raises(InputError, match="carry_between"):
        TemporalConfig(carry_between=1)
    with pytest.raises(InputError, match="between_agreement"):
        TemporalConfig(between_agreement=-1.0)


def test_a_frame_whose_render_the_last_one_does_not_predict_is_not_carried():
    """The last frame's render moved into this frame (a still camera: not moved) against this
    frame's render: equal renders agree (carried), a render darker by 0.1 everywhere agrees to
    20 dB exactly (10 log10(1 / 0.01)): below a 30 dB gate the model must run, above a 15 dB
    one it is carried."""
    r1, e1 = _frame(1)
    darker = r1 - 0.1
    for gate, carried in ((30.0, False), (15.0, True)):
        f = TemporalFilter(TemporalConfig(model_every=2, reject=0.0, carry_agreement=gate))
        f(r1, e1, DEPTH, K, POSE)
        assert torch.allclose(f.carry(r1, DEPTH, K, POSE), e1, atol=1e-6) and f.last_agreement > 100
        f(r1, e1, DEPTH, K, POSE)
        out = f.carry(darker, DEPTH, K, POSE)
        assert f.last_agreement == pytest.approx(20.0, abs=1e-3)
        assert (out is not None) == carried
    f = TemporalFilter(TemporalConfig(model_every=2, carry_agreement=0.0))
    f(r1, e1, DEPTH, K, POSE)
    f.carry(darker, DEPTH, K, POSE)
    assert f.last_agreement is None  # no gate: not measured
    for bad in (-1.0, float("inf"), True, "30"):
        with pytest.raises(InputError, match="carry_agreement"):
            TemporalConfig(carry_agreement=bad)

def test_the_share_gate_weighs_the_renders_miss_against_the_enhancers_change():
    """``carry_share``: a frame enhanced by +0.1 over its render everywhere (a change of 20 dB,
    mean square 0.01) and a next render darker by 0.01 (a miss of 40 dB, mean square 1e-4 = 0.01
    of the change): carried with a share of 0.02, not with 0.005; a change of 0.2 (mean square
    0.04) lets the same miss through at 0.005. Between two kept frames the changes' mean squares
    mix by position (0.01 and 0.04 at 1/3: 0.02, 16.99 dB). The absolute gate, off, does not judge."""
    r1 = torch.full((3, H, W), 0.5)
    darker = r1 - 0.01
    for change, share, carried in ((0.1, 0.02, True), (0.1, 0.005, False), (0.2, 0.005, True)):
        f = TemporalFilter(TemporalConfig(model_every=2, reject=0.0, carry_agreement=0.0, carry_share=share))
        f(r1, r1 + change, DEPTH, K, POSE)
        out = f.carry(darker, DEPTH, K, POSE)
        assert f.last_agreement == pytest.approx(40.0, abs=1e-3)
        assert f.last_change == pytest.approx(-10 * math.log10(change ** 2), abs=1e-3)
        assert (out is not None) == carried
    f = TemporalFilter(TemporalConfig(model_every=3, reject=0.0, carry_agreement=0.0, carry_share=0.02))
    f.remember(r1, r1 + 0.1, DEPTH, K, POSE)
    before = f.kept
    f.remember(r1, r1 + 0.2, DEPTH, K, POSE)  # as made: not blended with the one before
    after = f.kept
    assert f.carry(darker, DEPTH, K, POSE, between=(before, after, 1 / 3)) is not None
    assert f.last_change == pytest.approx(-10 * math.log10(2 / 3 * 0.01 + 1 / 3 * 0.04), abs=1e-3)
    f = TemporalFilter(TemporalConfig(model_every=2, carry_agreement=0.0))
    f(r1, r1 + 0.1, DEPTH, K, POSE)
    f.carry(darker, DEPTH, K, POSE)
    assert f.last_change is None  # no gate: not measured
    for bad in (-0.1, float("nan"), True, "0.1"):
        with pytest.raises(InputError, match="carry_share"):
            TemporalConfig(carry_share=bad)


def test_a_carry_the_renders_refuse_never_samples_the_frame(monkeypatch):
    """The gate reads the moved renders only: a carry it refuses (the darker render, 20 dB below
    a 30 dB gate) pays no bicubic sampling of the kept frame, alone or between two; one it lets
    through samples each kept frame once."""
    import roguenerf.reprojection as reprojection

    calls = []
    real = reprojection.sample_at
    monkeypatch.setattr(reprojection, "sample_at", lambda *a, **k: calls.append(k.get("mode")) or real(*a, **k))
    r1, e1 = _frame(1)
    f = TemporalFilter(TemporalConfig(model_every=2, reject=0.0, carry_agreement=30.0))
    f(r1, e1, DEPTH, K, POSE)
    calls.clear()
    assert f.carry(r1 - 0.1, DEPTH, K, POSE) is None and calls == []
    kept = f.kept
    assert f.carry(r1 - 0.1, DEPTH, K, POSE, between=(kept, kept, 0.5)) is None and calls == []
    assert torch.allclose(f.carry(r1, DEPTH, K, POSE, between=(kept, kept, 0.5)), e1, atol=1e-6)
    assert calls == ["bicubic", "bicubic"]


def test_a_kept_frame_moved_into_several_gives_each_what_a_fresh_move_gives():
    """The kept frames' sampling sources are built once and reused: two model frames carried
    into three frames between them (each camera moved sideways), by one filter, equal the carries
    of a fresh filter per frame, to the bit."""
    r1, e1 = _frame(1)
    r2, e2 = _frame(2)
    config = TemporalConfig(model_every=4, carry_agreement=0.0)

    def anchors(f):
        f(r1, e1, DEPTH, K, POSE)
        before = f.kept
        moved = POSE.clone()
        moved[0, 3] = 0.4
        f(r2, e2, DEPTH, K, moved)
        return before, f.kept

    shared = TemporalFilter(config)
    before, after = anchors(shared)
    for step in (1, 2, 3):
        pose = POSE.clone()
        pose[0, 3] = 0.1 * step
        fresh = TemporalFilter(config)
        fresh_anchors = anchors(fresh)
        position = step / 4
        out = shared.carry(r1, DEPTH, K, pose, between=(before, after, position))
        assert torch.equal(out, fresh.carry(r1, DEPTH, K, pose, between=(*fresh_anchors, position)))
        shared.restore(after)


def _angle(a, b) -> float:
    import math

    dot = sum(x * y for x, y in zip(a, b))
    return math.degrees(math.acos(dot / (math.dist(a, (0, 0, 0)) * math.dist(b, (0, 0, 0)))))


def test_parallax_is_the_angle_between_the_two_rays_at_the_point():
    from roguenerf.enhance.temporal import parallax_deg

    depth = DEPTH.clone()
    depth[0, 0, 0] = 0.0  # unknown
    angles = parallax_deg(depth, K, POSE, torch.tensor([3.0, 0.0, 0.0]))
    # pixel (row 10, column 12): its centre (12.5, 10.5) is the point (0.05, 0.05, 3) at z = 3
    assert float(angles[0, 10, 12]) == pytest.approx(_angle((0.05, 0.05, 3), (-2.95, 0.05, 3)), abs=1e-4)
    assert float(angles[0, 0, 0]) == 0.0
    assert float(parallax_deg(DEPTH, K, POSE, torch.zeros(3)).abs().max()) < 1e-9  # the same centre


def test_parallax_far_from_the_origin_matches_the_float64_angle():
    """Cameras 5000 units from the origin, 0.05 apart, turned: the float32 per-pixel form agrees
    with the float64 angle between the two rays on a grid of pixels to 1e-4 degrees, and unknown
    depth (NaN, 0) gives 0."""
    import math

    from roguenerf.enhance.temporal import parallax_deg
    from roguenerf.geometry.noise import axis_angle_to_matrix

    g = torch.Generator().manual_seed(3)
    h, w = 24, 32
    intrinsics = torch.tensor([[40.0, 0.2, 15.0], [0.0, 42.0, 13.0], [0.0, 0.0, 1.0]])
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64))
    pose[:3, 3] = torch.tensor([5e3, -2e3, 1e3], dtype=torch.float64)
    other = pose[:3, 3] + torch.tensor([0.05, 0.01, -0.02], dtype=torch.float64)
    depth = torch.rand(1, h, w, generator=g) * 3 + 0.5
    depth[0, 0, :4] = float("nan")
    depth[0, 1, :4] = 0.0
    angles = parallax_deg(depth, intrinsics, pose, other)
    inv = torch.linalg.inv(intrinsics.double())
    worst = 0.0
    for v in range(2, h, 3):
        for u in range(0, w, 5):
            point = pose[:3, :3] @ (inv @ torch.tensor([u + 0.5, v + 0.5, 1.0], dtype=torch.float64)) * depth[0, v, u]
            point = point + pose[:3, 3]
            a, b = point - pose[:3, 3], point - other
            expected = math.degrees(math.acos(float(a @ b / (a.norm() * b.norm()))))
            worst = max(worst, abs(float(angles[0, v, u]) - expected))
    assert worst < 1e-4
    assert float(angles[0, :2, :4].abs().max()) == 0.0
    assert float(angles.max()) > 0.5  # the test has parallax to get wrong


def test_the_blend_fades_with_parallax():
    """The spike of the moving-camera test, with ``fade_deg`` set to the parallax at the pixel it
    lands on: half the blend's weight there (0.25 of the last frame instead of 0.5)."""
    moved = POSE.clone()
    moved[0, 3] = 0.1
    # pixel (10, 7) of the moved camera: the point (-0.45, 0.05, 3) in it, (-0.35, 0.05, 3) in the world
    fade = _angle((-0.45, 0.05, 3), (-0.35, 0.05, 3))
    render = torch.full((3, H, W), 0.5)
    spike = render.clone()
    spike[:, 10, 8] = 0.9
    outs = []
    for fade_deg in (0.0, fade):
        f = TemporalFilter(TemporalConfig(weight=0.5, fade_deg=fade_deg))
        f(render, spike, DEPTH, K, POSE)
        outs.append(f(render, render, DEPTH, K, moved))
    assert float(outs[0][0, 10, 7]) == pytest.approx(0.5 + 0.5 * 0.4, abs=1e-4)
    assert float(outs[1][0, 10, 7]) == pytest.approx(0.5 + 0.25 * 0.4, abs=1e-4)
    # a still camera has no parallax: the fade changes nothing
    still = [TemporalFilter(TemporalConfig(fade_deg=d)) for d in (0.0, 1.0)]
    r1, e1 = _frame(1)
    r2, e2 = _frame(2)
    for f in still:
        f(r1, e1, DEPTH, K, POSE)
    assert torch.equal(still[0](r2, e2, DEPTH, K, POSE), still[1](r2, e2, DEPTH, K, POSE))


def test_the_fade_along_the_path_adds_what_the_last_frame_carried():
    """``fade_along``: a camera moved sideways twice by one pixel's worth over a plane (z = 3,
    f = 30: 0.1 units), uniform images. At a pixel the second frame takes the first's weight by
    its parallax ``a1``, ``w2 = 0.5 * 0.5 ** (a1 / f)``, and keeps ``w2 * a1`` as what it carries;
    the third, at the pixel one to the left (where the point went), fades by ``a2 + w2 * a1``
    (the plain fade: by ``a2`` alone)."""
    from roguenerf.enhance.temporal import parallax_deg

    fade = 2.0
    poses = []
    for step in range(3):
        pose = POSE.clone()
        pose[0, 3] = 0.1 * step
        poses.append(pose)
    values = (0.2, 0.6, 0.4)
    outs = {}
    for along in (False, True):
        f = TemporalFilter(TemporalConfig(weight=0.5, fade_deg=fade, reject=0.0, fade_along=along))
        frames = []
        for pose, value in zip(poses, values):
            image = torch.full((3, H, W), value)
            frames.append(f(torch.full((3, H, W), 0.5), image, DEPTH, K, pose))
            remembered = f.last_parallax
            f.remember(torch.full((3, H, W), 0.5), frames[-1], DEPTH, K, pose, parallax=remembered)
            if along:
                assert remembered is not None and remembered.shape == (1, H, W)
            else:
                assert remembered is None
        outs[along] = frames
    y, x = 10, 5  # seen by the frame before in both moves (the camera moves right: it sees the left)
    a1 = float(parallax_deg(DEPTH, K, poses[1], poses[0][:3, 3])[0, y, x])
    a2 = float(parallax_deg(DEPTH, K, poses[2], poses[1][:3, 3])[0, y, x - 1])
    assert a1 > 0.5 and a2 > 0.5
    w2 = 0.5 * 0.5 ** (a1 / fade)
    second = (1 - w2) * 0.6 + w2 * 0.2
    for along in (False, True):
        assert float(outs[along][1][0, y, x]) == pytest.approx(second, abs=1e-5)  # the same: nothing carried yet
    for along, angle in ((False, a2), (True, a2 + w2 * a1)):
        w3 = 0.5 * 0.5 ** (angle / fade)
        assert float(outs[along][2][0, y, x - 1]) == pytest.approx((1 - w3) * 0.4 + w3 * second, abs=1e-5)
    # a frame read back (nothing remembered of what it carried) starts afresh
    f = TemporalFilter(TemporalConfig(weight=0.5, fade_deg=fade, reject=0.0, fade_along=True))
    f.remember(torch.full((3, H, W), 0.5), outs[True][1], DEPTH, K, poses[1])
    plain = TemporalFilter(TemporalConfig(weight=0.5, fade_deg=fade, reject=0.0))
    plain.remember(torch.full((3, H, W), 0.5), outs[True][1], DEPTH, K, poses[1])
    image = torch.full((3, H, W), 0.4)
    assert torch.equal(f(torch.full((3, H, W), 0.5), image, DEPTH, K, poses[2]),
                       plain(torch.full((3, H, W), 0.5), image, DEPTH, K, poses[2]))
    with pytest.raises(InputError, match="fade_along"):
        TemporalConfig(fade_along=1)


@pytest.mark.parametrize("fade", [-1.0, float("nan"), float("inf"), "2"])
def test_bad_fades_are_refused(fade):
    with pytest.raises(InputError, match="fade_deg"):
        TemporalConfig(fade_deg=fade)


def test_the_blend_rejects_the_last_frame_where_the_renders_disagree():
    """A still camera: where the two renders differ by ``reject`` the blend weight halves (0.25
    of the last frame), where they agree it stays 0.5; the disagreement is a 3 x 3 mean."""
    f = TemporalFilter(TemporalConfig(weight=0.5, reject=0.1))
    r1, e1 = _frame(1)
    _, e2 = _frame(2)
    r2 = r1.clone()
    r2[:, :, 12:] += 0.1  # the right half's render changed by 0.1
    f(r1, e1, DEPTH, K, POSE)
    out = f(r2, e2, DEPTH, K, POSE)
    assert torch.allclose(out[:, :, :11], (0.5 * e2 + 0.5 * e1)[:, :, :11], atol=1e-5)
    assert torch.allclose(out[:, :, 13:], (0.75 * e2 + 0.25 * e1)[:, :, 13:], atol=1e-5)
    # at the edge the 3 x 3 mean sees a third changed: 0.5 * 0.5 ** (1 / 3) ** 2
    w = 0.5 * 0.5 ** (1 / 9)
    assert torch.allclose(out[:, 1:-1, 11], ((1 - w) * e2 + w * e1)[:, 1:-1, 11], atol=1e-5)
    # no rejection: the weight is the same everywhere
    plain = TemporalFilter(TemporalConfig(weight=0.5, reject=0.0))
    plain(r1, e1, DEPTH, K, POSE)
    assert torch.allclose(plain(r2, e2, DEPTH, K, POSE), 0.5 * e2 + 0.5 * e1, atol=1e-5)


@pytest.mark.parametrize("reject", [-0.1, float("nan"), float("inf"), "0.1"])
def test_bad_rejections_are_refused(reject):
    with pytest.raises(InputError, match="reject"):
        TemporalConfig(reject=reject)


def test_a_carried_frame_takes_the_render_where_the_renders_disagree():
    """``carry`` with ``reject``: the last result where the renders agree, half of it and half
    the render where they differ by ``reject``."""
    f = TemporalFilter(TemporalConfig(model_every=2, reject=0.1, carry_agreement=0.0))
    r1, e1 = _frame(1)
    r2 = r1.clone()
    r2[:, :, 12:] += 0.1
    f.remember(r1, e1, DEPTH, K, POSE)
    out = f.carry(r2, DEPTH, K, POSE)
    assert torch.allclose(out[:, :, :11], e1[:, :, :11], atol=1e-5)
    assert torch.allclose(out[:, :, 13:], (0.5 * e1 + 0.5 * r2)[:, :, 13:].clamp(0, 1), atol=1e-5)


@pytest.mark.parametrize("value", [1, "yes", None])
def test_both_ways_must_be_true_or_false(value):
    with pytest.raises(InputError, match="both_ways"):
        TemporalConfig(both_ways=value)


def test_the_fast_setting_is_the_defaults_but_for_its_own_fields_and_takes_changes():
    """TemporalConfig.fast(): FAST's fields (the model on one frame in 4, a frame carried only
    where its model frames are no farther than its nearest photo, one pass) over the defaults; a
    field given to it wins, and a bad one is refused as anywhere."""
    from roguenerf.enhance.temporal import FAST

    fast, shipped = TemporalConfig.fast(), TemporalConfig()
    assert (fast.model_every, fast.carry_nearer, fast.both_ways) == (4, 1.0, False) == tuple(FAST.values())
    assert dataclasses.replace(fast, **{k: getattr(shipped, k) for k in FAST}) == shipped
    assert TemporalConfig.fast(model_every=3, both_ways=True) == dataclasses.replace(fast, model_every=3,
                                                                                      both_ways=True)
    with pytest.raises(InputError, match="carry_nearer"):
        TemporalConfig.fast(carry_nearer=-1)


def test_a_frame_nearer_a_photo_than_its_model_frames_is_not_carried(monkeypatch):
    """``carry_nearer``: model frames 0.3 and 0.6 units from the frame (one third of the way
    from the first: 2/3 * 0.3 + 1/3 * 0.6 = 0.4 mixed by position), a photo 0.5 away: the ratio
    0.8 is carried at 1, not at 0.5, judged from the poses before anything is moved; without the
    photo's distance, or at 0, no such test."""
    import roguenerf.reprojection

    r1, e1 = _frame(1)
    at = lambda x: torch.tensor([[1.0, 0, 0, x], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],  # noqa: E731
                                dtype=torch.float64)
    for limit, carried in ((1.0, True), (0.5, False)):
        f = TemporalFilter(TemporalConfig(model_every=3, reject=0.0, min_seen=0.0, carry_nearer=limit))
        f.remember(r1, e1, DEPTH, K, at(-0.3))
        before = f.kept
        f.remember(r1, e1, DEPTH, K, at(0.6))
        after = f.kept
        out = f.carry(r1, DEPTH, K, POSE, between=(before, after, 1 / 3), photo_distance=0.5)
        assert f.last_nearer == pytest.approx(0.8) and (out is not None) == carried
    moved = []
    monkeypatch.setattr(roguenerf.reprojection, "reproject",
                        lambda *a, **k: moved.append(1) or (_ for _ in ()).throw(AssertionError("moved")))
    assert f.carry(r1, DEPTH, K, POSE, between=(before, after, 1 / 3), photo_distance=0.1) is None and not moved
    monkeypatch.undo()
    f.remember(r1, e1, DEPTH, K, POSE)
    assert f.carry(r1, DEPTH, K, POSE, photo_distance=0.0) is not None and f.last_nearer == 0.0  # nothing moved
    f = TemporalFilter(TemporalConfig(model_every=2, reject=0.0, min_seen=0.0))
    f.remember(r1, e1, DEPTH, K, at(0.2))
    assert f.carry(r1, DEPTH, K, POSE, photo_distance=0.01) is not None and f.last_nearer is None
    for bad in (-1.0, float("inf"), True):
        with pytest.raises(InputError, match="carry_nearer"):
            TemporalConfig(carry_nearer=bad)


def test_the_gated_schedule_places_model_frames_where_the_photos_call_for_them():
    """schedule "gate": ten cameras a unit apart on a line, a training photo where frame 5 stands
    (frame t is |t - 5| from it), at most 4 frames apart, carry_nearer 1. From 0, frame 4 lets
    1-3 pass (frame 3: 3/4 * 3 + 1/4 * 1 = 1.5 <= 2); from 4 no later frame lets frame 5 (on the
    photo) pass, so 5 is next; from 5, 7 lets 6 pass (1 <= 1) and 8 or 9 do not (6: 4/3, 1.5 > 1);
    from 7, 9 (the last). Without the test, every 4th frame and the last; at most 1 apart, all."""
    from roguenerf.enhance.temporal import gated_schedule, mixed_distance

    centres = torch.zeros(10, 3, dtype=torch.float64)
    centres[:, 0] = torch.arange(10, dtype=torch.float64)
    photos = [abs(t - 5.0) for t in range(10)]
    assert gated_schedule(centres, photos, 4, 1.0) == [0, 4, 5, 7, 9]
    assert gated_schedule(centres, photos, 4, 0.0) == [0, 4, 8, 9]
    assert gated_schedule(centres, [math.inf] * 10, 4, 1.0) == [0, 4, 8, 9]
    assert gated_schedule(centres, photos, 1, 1.0) == list(range(10))
    assert gated_schedule(centres[:1], [1.0], 4, 1.0) == [0] and gated_schedule(centres[:0], [], 4, 1.0) == []
    assert mixed_distance(centres, 3, 0, 4) == pytest.approx(1.5)
    with pytest.raises(InputError, match="most"):
        gated_schedule(centres, photos, 0, 1.0)
    with pytest.raises(InputError, match="photo_distances"):
        gated_schedule(centres, photos[:3], 4, 1.0)
    with pytest.raises(InputError, match="schedule"):
        TemporalConfig(schedule="adaptive")
    with pytest.raises(InputError, match="carry_between"):
        TemporalConfig(model_every=4, schedule="gate", carry_between=False)


def test_every_frame_the_gated_schedule_puts_between_is_carried_by_the_filter():
    """The schedule judges with TemporalFilter.carry's own test on the same numbers: on a path
    whose frames 3 and 6 stand 0.1 from photos, every frame between two scheduled model frames is
    carried (not refused by carry_nearer), and the frames the schedule makes model frames of
    would have been refused between the fixed ones."""
    from roguenerf.enhance.temporal import gated_schedule

    r1, e1 = _frame(1)
    T = 9
    poses = [torch.tensor([[1.0, 0, 0, 0.3 * t], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.float64)
             for t in range(T)]
    centres = torch.stack([p[:3, 3] for p in poses])
    photos = [min(abs(0.3 * t - 0.9), abs(0.3 * t - 1.8)) + 0.1 for t in range(T)]
    config = TemporalConfig(model_every=4, reject=0.0, min_seen=0.0, carry_nearer=1.0)
    frames = gated_schedule(centres, photos, 4, config.carry_nearer)
    assert frames != [0, 4, 8] and len(frames) < T

    def carried(schedule):
        out = []
        for a, b in zip(schedule, schedule[1:]):
            f = TemporalFilter(config)
            f.remember(r1, e1, DEPTH, K, poses[a])
            before = f.kept
            f.remember(r1, e1, DEPTH, K, poses[b])
            after = f.kept
            out += [f.carry(r1, DEPTH, K, poses[t], between=(before, after, (t - a) / (b - a)),
                            photo_distance=photos[t]) is not None for t in range(a + 1, b)]
        return out

    assert all(carried(frames))
    assert not all(carried([0, 4, 8]))
