"""Camera paths: nerfstudio camera_path.json in, enhanced frames + MP4 out, flicker measured, resumable."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
from kornia.filters import gaussian_blur2d
from typer.testing import CliRunner

from roguecli import app
from roguenerf.checkpoint import default_checkpoint_path, load_checkpoint
from roguenerf.data.exports import (
    DATAPARSER_FILE,
    DataparserTransform,
    write_depth_like,
)
from roguenerf.data.toy import (
    make_toy_scene,
    make_toy_world,
    render_toy_view,
    toy_camera_path,
)
from roguenerf.errors import InputError, PathCancelled
from roguenerf.geometry import opencv_to_opengl
from roguenerf.imageio import write_png
from roguenerf.inference import SceneEnhancer
from roguenerf.trajectory import (
    FLICKER_FILE,
    enhance_path,
    pair_flicker,
    read_camera_path,
    smooth_path,
)
from roguenerf.video import read_video_info

H, W, SEED, STEPS = 24, 32, 4, 3
PARSER = DataparserTransform(
    transform=torch.tensor([[0.0, -1.0, 0.0, 0.3], [1.0, 0.0, 0.0, -0.5], [0.0, 0.0, 1.0, 1.0]], dtype=torch.float64),
    scale=0.5)


def _ray_norm(K):
    u = torch.arange(W, dtype=torch.float64) + 0.5
    v = torch.arange(H, dtype=torch.float64) + 0.5
    return torch.sqrt(((u[None] - K[0, 2]) / K[0, 0]) ** 2 + ((v[:, None] - K[1, 2]) / K[1, 1]) ** 2 + 1)


@pytest.fixture(scope="module")
def toy_path(tmp_path_factory):
    """A toy scene, and a smooth path through three of its views with renders no photo was taken from."""
    root = tmp_path_factory.mktemp("path")
    scene = make_toy_scene(root / "scene", seed=SEED, n_train=6, n_test=1, height=H, width=W, kind="orbit")
    (root / "scene" / DATAPARSER_FILE).write_text(json.dumps(PARSER.to_json()))
    world = make_toy_world(SEED)
    assert torch.equal(toy_camera_path(world, 7, seed=SEED, kind="orbit"), scene.poses())
    keys = scene.poses([1, 2, 3])
    poses = smooth_path(keys, STEPS)
    K = scene.frames[0].K
    (root / "frames" / "rgb").mkdir(parents=True)
    (root / "frames" / "depth").mkdir()
    cams = []
    for t, pose in enumerate(poses):
        rgb, z = render_toy_view(world, pose, K, H, W)
        render = gaussian_blur2d(rgb[None], (5, 5), (1.0, 1.0), border_type="replicate")[0].clamp(0, 1)
        write_png(root / "frames" / "rgb" / f"frame_{t}.png", render)
        # nerfacto-like: distance along the ray, gzip'd (H, W, 1) as ns-render writes raw depth.
        write_depth_like(root / "frames" / "depth" / f"frame_{t}.npy.gz", (z[0].double() * _ray_norm(K)).numpy(),
                         kind="npy.gz")
        model_pose = PARSER.to_model(opencv_to_opengl(pose))
        fov = math.degrees(2 * math.atan(H / 2 / float(K[1, 1])))
        cams.append({"camera_to_world": model_pose.flatten().tolist(), "fov": fov, "aspect": W / H})
    (root / "camera_path.json").write_text(json.dumps(
        {"camera_type": "perspective", "render_height": H, "render_width": W, "fps": 12, "camera_path": cams}))
    return {"root": root, "scene": scene, "poses": poses}


@pytest.fixture(scope="module")
def enhancer(toy_path):
    model, _ = load_checkpoint(default_checkpoint_path())
    return SceneEnhancer(toy_path["scene"], model)


def test_nerfstudio_camera_path_maps_back_to_scene_poses(toy_path):
    cp = read_camera_path(toy_path["root"] / "camera_path.json", dataparser=PARSER)
    assert len(cp) == len(toy_path["poses"]) == 2 * STEPS + 1
    assert (cp.width, cp.height, cp.fps, cp.source) == (W, H, 12, "nerfstudio")
    torch.testing.assert_close(cp.world_from_cam, toy_path["poses"], rtol=0, atol=1e-9)
    torch.testing.assert_close(cp.K[0], toy_path["scene"].frames[0].K, rtol=1e-9, atol=1e-9)
    # smooth_path passes through its key poses and keeps rotations rotations.
    torch.testing.assert_close(toy_path["poses"][STEPS], toy_path["scene"].poses([2])[0])
    R = toy_path["poses"][:, :3, :3]
    torch.testing.assert_close(R.transpose(1, 2) @ R, torch.eye(3, dtype=torch.float64).expand_as(R))


def test_flicker_is_zero_for_a_static_world_and_positive_for_noise(toy_path):
    scene = toy_path["scene"]
    a, b = scene.indices("train")[:2]
    photos = [scene.photo(a)], [scene.photo(b)]
    args = (scene.depth(a), scene.depth(b), scene.frames[a].K, scene.frames[b].K,
            scene.frames[a].world_from_cam, scene.frames[b].world_from_cam)
    (clean,), fraction = pair_flicker(*photos, *args)
    assert fraction > 0.3 and clean < 0.03  # exact geometry: only resampling error
    noisy = [(scene.photo(a) + 0.1 * torch.randn(3, H, W, generator=torch.Generator().manual_seed(0))).clamp(0, 1)]
    (worse,), _ = pair_flicker(noisy, photos[1], *args)
    assert worse > clean + 0.03
    (none,), _ = pair_flicker([None], photos[1], *args)
    assert none is None


def _unsharp(image, amount):
    return (image + amount * (image - gaussian_blur2d(image[None], (7, 7), (1.0, 1.0), border_type="replicate")[0]))


def test_sharpening_finds_the_amount_of_an_unsharp_mask(toy_path):
    """The reference's amount is the one that gives the render the enhanced frame's detail: an
    unsharp mask's own amount back (kornia's blur, not the library's), 0 for the render itself or
    a blurrier frame."""
    from roguenerf.trajectory.flicker import sharpening

    scene = toy_path["scene"]
    render = gaussian_blur2d(scene.photo(1)[None], (5, 5), (1.0, 1.0), border_type="replicate")[0] * 0.8 + 0.1
    for amount in (0.5, 1.0, 2.0):
        found = sharpening(render, _unsharp(render, amount))  # in [0, 1] unclamped: 0.1 + 0.8 x keeps a margin
        assert found.amount == pytest.approx(amount, rel=0.1) and found.ratio > 1 + amount / 4
        torch.testing.assert_close(found.image(render), _unsharp(render, found.amount).clamp(0, 1))
    same = sharpening(render, render)
    assert same.amount == 0 and same.ratio == pytest.approx(1.0)
    blurrier = sharpening(render, gaussian_blur2d(render[None], (5, 5), (1.0, 1.0), border_type="replicate")[0])
    assert blurrier.amount == 0 and blurrier.ratio < 0.8


def test_a_consistent_sharpening_reads_as_flicker_but_not_against_the_sharpened_reference():
    """Resampling loses fine detail, so the flicker figure rises with sharpness alone. A texture on
    a plane facing the camera, the camera moved by half a pixel: each frame's render is the
    texture blurred, its "enhanced" frame the render under the same unsharp mask (nothing changes
    between the frames but the move). The sharpened frames score well above the renders' flicker,
    and level with the reference the report sets beside it."""
    from roguenerf.trajectory.flicker import sharpening

    h, w, focal, z, shift = 48, 64, 40.0, 2.0, 0.5
    gen = torch.Generator().manual_seed(3)
    freq = (torch.rand(40, 2, generator=gen, dtype=torch.float64) - 0.5) * 2.4  # up to 1.2 rad per pixel
    phase = torch.rand(40, generator=gen, dtype=torch.float64) * 2 * math.pi
    amp = 0.3 / 40 ** 0.5 * torch.randn(3, 40, generator=gen, dtype=torch.float64)

    def texture(dx):
        v, u = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5 + dx, indexing="ij")
        waves = torch.sin(u[..., None] * freq[:, 0] + v[..., None] * freq[:, 1] + phase)  # (h, w, 40)
        return (0.5 + torch.einsum("hwk,ck->chw", waves, amp)).float()

    K = torch.tensor([[focal, 0, w / 2], [0, focal, h / 2], [0, 0, 1]], dtype=torch.float32)
    pose_a = torch.eye(4, dtype=torch.float64)
    pose_b = pose_a.clone()
    pose_b[0, 3] = shift * z / focal  # the texture moves left by `shift` pixels
    depth = torch.full((1, h, w), z)
    renders = [gaussian_blur2d(texture(dx)[None], (7, 7), (1.0, 1.0), border_type="reflect")[0] for dx in (0, shift)]
    sharp = [_unsharp(r, 1.5).clamp(0, 1) for r in renders]
    found = [sharpening(r, s) for r, s in zip(renders, sharp)]
    amount = 0.5 * (found[0].amount + found[1].amount)
    reference = [f.image(r, amount) for f, r in zip(found, renders)]
    (render, enhanced, sharpened), fraction = pair_flicker(
        [renders[0], sharp[0], reference[0]], [renders[1], sharp[1], reference[1]], depth, depth, K, K, pose_a, pose_b)
    assert fraction > 0.9
    assert enhanced > 1.3 * render
    assert enhanced == pytest.approx(sharpened, rel=0.05)


def test_the_flicker_report_splits_the_pairs_where_the_neighbours_changed():
    """summarise_flicker: enhanced over render flicker on the pairs across which the frames' neighbour
    sets differ, and on the others; a frame that names none (carried) leaves its pairs out of both."""
    from roguenerf.trajectory.flicker import summarise_flicker

    frames = [{"frame": 0, "neighbours": ["a", "b"]}, {"frame": 1, "neighbours": ["b", "a"]},
              {"frame": 2, "neighbours": ["a", "c"]}, {"frame": 3, "neighbours": ["a", "c"]}, {"frame": 4}]
    pair = lambda t, render, enhanced: {"from": t, "to": t + 1, "render": render, "enhanced": enhanced,  # noqa: E731
                                        "photo": None, "sharpened": None}
    report = summarise_flicker([pair(0, 0.1, 0.1), pair(1, 0.1, 0.4), pair(2, 0.2, 0.1), pair(3, 0.1, 0.9)], frames)
    flicker = report["flicker"]
    assert flicker["neighbour_changes"] == 1 and flicker["ratio_changed"] == pytest.approx(4.0)
    assert flicker["ratio_steady"] == pytest.approx(0.1 / 0.15)  # pairs 0-1 (the same set, reordered) and 2-3
    assert flicker["ratio"] == pytest.approx(1.5 / 0.5)
    none = summarise_flicker([pair(0, 0.1, 0.1)], [{"frame": 0}, {"frame": 1}])["flicker"]
    assert none["neighbour_changes"] == 0 and none["ratio_changed"] is None and none["ratio_steady"] is None


def test_flicker_on_the_filters_move_is_the_flicker_reprojected_again(toy_path):
    """pair_flicker sampling at a reprojection it is given (the temporal filter's) measures what
    it measures reprojecting itself: the same valid pixels, the same errors to float rounding."""
    from roguenerf.reprojection import reproject

    scene = toy_path["scene"]
    a, b = scene.indices("train")[:2]
    noise = torch.rand(3, H, W, generator=torch.Generator().manual_seed(1))
    images_a = [scene.photo(a), noise, None]
    images_b = [scene.photo(b), scene.photo(b), scene.photo(b)]
    args = (scene.depth(a), scene.depth(b), scene.frames[a].K, scene.frames[b].K,
            scene.frames[a].world_from_cam, scene.frames[b].world_from_cam)
    rp = reproject(scene.depth(a)[None], scene.depth(a)[None], scene.depth(b)[None], args[2].float(),
                   args[3].float(), args[4].double(), args[5].double())
    again, fraction = pair_flicker(images_a, images_b, *args)
    shared, shared_fraction = pair_flicker(images_a, images_b, *args, warp=(rp.coords, rp.valid))
    assert 0.3 < fraction == shared_fraction and shared[2] is None is again[2]
    assert shared[:2] == pytest.approx(again[:2], rel=1e-5) and again[1] > again[0] + 0.1


def test_flicker_is_the_mean_absolute_difference_over_the_pixels_that_land(toy_path):
    """Each image's flicker is |frame t moved into t+1 - frame t+1|, averaged over the colour
    channels and then over the pixels whose points land in frame t (a part of the view does not),
    computed here from the reprojection directly, for two images at once and with an image missing."""
    from roguenerf.reprojection import reproject

    scene = toy_path["scene"]
    a, b = scene.indices("train")[:2]
    gen = torch.Generator().manual_seed(2)
    images_a = [scene.photo(a), torch.rand(3, H, W, generator=gen), None]
    images_b = [scene.photo(b), torch.rand(3, H, W, generator=gen), scene.photo(b)]
    args = (scene.depth(a), scene.depth(b), scene.frames[a].K, scene.frames[b].K,
            scene.frames[a].world_from_cam, scene.frames[b].world_from_cam)
    errors, fraction = pair_flicker(images_a, images_b, *args)
    rp = reproject(torch.cat(images_a[:2])[None], scene.depth(a)[None], scene.depth(b)[None], args[2].float(),
                   args[3].float(), args[4].double(), args[5].double())
    valid = rp.valid[0, 0] > 0
    assert 0.3 < fraction < 0.999 and fraction == pytest.approx(float(valid.float().mean()))
    for k in range(2):
        expected = (rp.features[0, 3 * k:3 * k + 3] - images_b[k]).abs().mean(0)[valid].mean()
        assert errors[k] == pytest.approx(float(expected), rel=1e-5)
    assert errors[2] is None


def test_enhance_path_writes_video_flicker_and_resumes(toy_path, enhancer, tmp_path):
    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    out = tmp_path / "out"
    calls = []
    result = enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="ray", quality=23,
                          progress=lambda d, t: calls.append((d, t)))
    T = len(cp)
    assert result.frames == result.enhanced_now == T
    # One progress step per frame and pass (the defaults blend both ways): the bar reaches its end
    # only when the second pass has written the last of frames/, never earlier.
    assert enhancer.options.temporal.both_ways and calls == [(d, 2 * T) for d in range(1, 2 * T + 1)]
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"{t:05d}.png" for t in range(T)]
    info = read_video_info(result.video)
    assert (info["frames"], info["width"], info["height"], info["codec"]) == (T, W, H, "h264")
    side = read_video_info(result.side_by_side)
    assert (side["frames"], side["width"], side["height"]) == (T, 2 * W, H)
    report = json.loads((out / FLICKER_FILE).read_text())
    assert report["frames"] == T and report["flicker"]["pairs"] == T - 1
    # Frames per second of the frames made now: not the checks before, nor the videos after.
    assert report["enhanced_now"] == T and report["frames_per_second"] == pytest.approx(result.frames_per_second)
    assert result.frames_per_second > T / result.seconds and result.enhance_seconds < result.seconds
    for pair in report["per_pair"]:
        assert pair["valid_fraction"] > 0.3 and pair["render"] > 0 and pair["enhanced"] > 0
    # Frames 0, STEPS, 2 * STEPS sit on scene views 1..3: they have photos and a PSNR gain figure.
    with_photos = [f["frame"] for f in report["per_frame"] if "gain_db" in f]
    assert with_photos == [0, STEPS, 2 * STEPS]
    assert [report["per_frame"][t]["view"] for t in with_photos] == [scene.frames[i].name for i in (1, 2, 3)]
    assert report["psnr"]["frames_with_photos"] == 3 and math.isfinite(report["psnr"]["mean_gain_db"])
    assert report["flicker"]["ratio"] == pytest.approx(report["flicker"]["enhanced"] / report["flicker"]["render"])
    # Beside it, the renders sharpened alike as much as the enhanced frames (their detail ratio, per frame).
    assert all(f["detail_ratio"] > 0 for f in report["per_frame"])
    assert all(p["sharpened"] > 0 for p in report["per_pair"])
    assert report["flicker"]["ratio_sharpened"] == pytest.approx(report["flicker"]["enhanced"]
                                                                 / report["flicker"]["sharpened"])
    # The path's training photos were encoded once, for the whole path.
    assert 0 < result.cached_views <= len(scene.indices("train"))

    # Interrupted: two frames lost, then a cancel after the first of them (the second pass, from the
    # last frame back, makes 5 before 2); a re-run finishes the rest.
    first = (out / "frames" / "00002.png").read_bytes()
    (out / "frames" / "00002.png").unlink()
    (out / "frames" / "00005.png").unlink()
    asked = iter([False] * T + [False, False, True])  # the first pass's frames, then 6, 5 and 4
    with pytest.raises(PathCancelled):
        enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="ray", quality=23,
                     should_stop=lambda: next(asked))
    assert (out / "frames" / "00005.png").is_file() and not (out / "frames" / "00002.png").exists()
    again = enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="ray", quality=23, video=False)
    assert again.enhanced_now == 1 and (out / "frames" / "00002.png").read_bytes() == first
    assert again.flicker["enhanced_now"] == 1 and again.frames_per_second == pytest.approx(1 / again.enhance_seconds)
    assert again.flicker["flicker"] == pytest.approx(report["flicker"])
    # Another setting into the same folder is refused instead of mixing frames.
    with pytest.raises(InputError, match="another path"):
        enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="ray", background="max", video=False)
    # So is another colour matching (a changed default after an upgrade, say) or pose refinement.
    from roguenerf.enhance.colour import ColourConfig

    for other in (SceneEnhancer(scene, enhancer.model, colour=ColourConfig(local_sigma=8.0)),
                  SceneEnhancer(scene, enhancer.model, align=False)):
        with pytest.raises(InputError, match="another path"):
            enhance_path(scene, other, cp, root / "frames", out, depth_type="ray", video=False)


def test_a_frame_write_that_fails_stops_the_path_in_order_and_the_rerun_makes_the_same_frames(
        toy_path, enhancer, tmp_path, monkeypatch):
    """Frames are written by a background thread: its error reaches the caller, no frame after
    the failed one is written, and the rerun resumes into the frames of a run that never failed."""
    import roguenerf.imageio

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    clean = tmp_path / "clean"
    enhance_path(scene, enhancer, cp, root / "frames", clean, depth_type="ray", video=False)
    real = roguenerf.imageio.write_png

    def full_disk(path, image, **kw):
        if path is not None and path.name == "00004.png":
            raise OSError(28, "No space left on device")
        return real(path, image, **kw)

    monkeypatch.setattr(roguenerf.imageio, "write_png", full_disk)
    out = tmp_path / "out"
    with pytest.raises(OSError, match="No space left"):
        enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="ray", video=False)
    # the first pass (TemporalConfig.both_ways) failed at its frame 4: nothing of the second written
    assert sorted(p.name for p in (out / "forward").iterdir()) == [f"{t:05d}.png" for t in range(4)]
    assert not any((out / "frames").iterdir())
    monkeypatch.setattr(roguenerf.imageio, "write_png", real)
    again = enhance_path(scene, enhancer, cp, root / "frames", out, depth_type="ray", video=False)
    assert again.enhanced_now == len(cp)  # every frame written into frames/ now
    for t in range(len(cp)):
        for sub in ("forward", "frames"):
            assert (out / sub / f"{t:05d}.png").read_bytes() == (clean / sub / f"{t:05d}.png").read_bytes()


def test_the_temporal_filter_lowers_flicker_and_leaves_the_first_frame(toy_path, enhancer, tmp_path):
    """Along the path each frame's change is blended with the last frame's, reprojected
    (roguenerf.enhance.temporal): the enhanced video flickers less than with every frame on its
    own, the first frame of the first pass is the same, and the setting is part of the resume
    fingerprint."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.temporal import TemporalConfig

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    alone = SceneEnhancer(scene, enhancer.model, options=EnhanceOptions(temporal=None))
    assert enhancer.options.temporal == TemporalConfig()
    on = enhance_path(scene, enhancer, cp, root / "frames", tmp_path / "on", depth_type="ray", video=False)
    off = enhance_path(scene, alone, cp, root / "frames", tmp_path / "off", depth_type="ray", video=False)
    frame = lambda folder, t, sub="frames": (tmp_path / folder / sub / f"{t:05d}.png").read_bytes()  # noqa: E731
    assert frame("on", 0, "forward") == frame("off", 0) and frame("on", 1, "forward") != frame("off", 1)
    assert on.flicker["flicker"]["enhanced"] < off.flicker["flicker"]["enhanced"]
    # keep_within: each frame names its neighbours; one still among the nearest stays to the next frame
    keep = 4
    sticky = SceneEnhancer(scene, enhancer.model, options=EnhanceOptions(temporal=TemporalConfig(keep_within=keep)))
    kept = enhance_path(scene, sticky, cp, root / "frames", tmp_path / "sticky", depth_type="ray", video=False)
    used = [f["neighbours"] for f in kept.flicker["per_frame"]]
    assert all(len(u) >= 2 for u in used)
    rule = [[enhancer.train_names[p] for p in enhancer.candidates(pose, 2, exclude=view)]  # the 2 nearest here
            for pose, view in zip(cp.world_from_cam, [f["view"] for f in on.flicker["per_frame"]], strict=True)]
    for run in (on, off):  # every frame names the neighbours the model took, filtered or not
        assert [f["neighbours"] for f in run.flicker["per_frame"]] == rule
    views = [f["view"] for f in kept.flicker["per_frame"]]  # a frame on a training view never takes it
    nearest = [[enhancer.train_names[p] for p in enhancer.candidates(pose, keep, exclude=view)]
               for pose, view in zip(cp.world_from_cam, views, strict=True)]
    for t in range(1, len(used)):
        stay = [n for n in used[t - 1] if n in nearest[t]][:len(used[t])]
        assert used[t][:len(stay)] == stay
    with pytest.raises(InputError, match="another path"):
        enhance_path(scene, alone, cp, root / "frames", tmp_path / "on", depth_type="ray", video=False)


def test_a_neighbour_change_is_blended_more_for_change_frames_and_resumes_the_same(toy_path, enhancer, tmp_path,
                                                                                    monkeypatch):
    """A frame whose neighbour set differs from the frame before's, and the change_frames - 1
    frames after it, take change_weight instead of weight (the jump a new photo brings is spread
    over more frames); the frames before the first change are those of change_weight = weight,
    and a path resumed after a change weighs and makes its frames as the first run did."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.temporal import TemporalConfig, TemporalFilter

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    T = len(cp)
    took = []
    real = TemporalFilter.__call__
    monkeypatch.setattr(TemporalFilter, "__call__", lambda self, *a, changed=False, **k: took.append(
        self.config.change_weight if changed else self.config.weight) or real(self, *a, changed=changed, **k))

    def run(out, change_weight=0.9):
        config = TemporalConfig(weight=0.5, change_weight=change_weight, change_frames=2, both_ways=False)
        mover = SceneEnhancer(scene, enhancer.model, options=EnhanceOptions(temporal=config))
        return enhance_path(scene, mover, cp, root / "frames", out, depth_type="ray", video=False)

    result = run(tmp_path / "change")
    sets = [set(f["neighbours"]) for f in result.flicker["per_frame"]]
    changes = [t for t in range(1, T) if sets[t] != sets[t - 1]]
    assert changes and changes[0] + 1 < T  # the toy orbit's path changes its neighbours on the way
    assert result.flicker["flicker"]["neighbour_changes"] == len(changes)
    first = changes[0]
    assert took[:first] == [0.5] * first and took[first:first + 2] == [0.9, 0.9]
    assert took == [0.9 if any(t - 2 < c <= t for c in changes) else 0.5 for t in range(T)]
    frame = lambda folder, t: (tmp_path / folder / "frames" / f"{t:05d}.png").read_bytes()  # noqa: E731
    run(tmp_path / "plain", change_weight=0.5)
    assert all(frame("change", t) == frame("plain", t) for t in range(first))
    assert frame("change", first) != frame("plain", first)
    made = {t: frame("change", t) for t in range(T)}
    for t in range(first + 1, T):
        (tmp_path / "change" / "frames" / f"{t:05d}.png").unlink()
    took.clear()
    again = run(tmp_path / "change")
    assert again.enhanced_now == T - first - 1 and took == [0.9 if any(t - 2 < c <= t for c in changes) else 0.5
                                                            for t in range(first + 1, T)]
    assert all(frame("change", t) == made[t] for t in range(T))


def test_frames_between_the_models_are_carried_and_resume_the_same(toy_path, enhancer, tmp_path, monkeypatch):
    """model_every=2: the model runs on the even frames only; an odd frame is the last one
    carried into it (marked in the report); a resumed path makes the same frames."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.temporal import TemporalConfig

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    every = SceneEnhancer(scene, enhancer.model,
                          options=EnhanceOptions(temporal=TemporalConfig(model_every=2, min_seen=0.0,
                                                                         carry_agreement=0.0, both_ways=False)))
    ran = []
    real = every.enhance
    monkeypatch.setattr(every, "enhance", lambda *a, **k: ran.append(1) or real(*a, **k))
    out = tmp_path / "every2"
    result = enhance_path(scene, every, cp, root / "frames", out, depth_type="ray", video=False)
    T = len(cp)
    assert [f["carried"] for f in result.flicker["per_frame"]] == [t % 2 == 1 for t in range(T)]
    assert len(ran) == (T + 1) // 2 and result.enhanced_now == T
    once = SceneEnhancer(scene, enhancer.model, options=EnhanceOptions(temporal=TemporalConfig(both_ways=False)))
    shipped = enhance_path(scene, once, cp, root / "frames", tmp_path / "shipped", depth_type="ray", video=False)
    assert "carried" not in shipped.flicker["per_frame"][0]
    frame = lambda folder, t: (tmp_path / folder / "frames" / f"{t:05d}.png").read_bytes()  # noqa: E731
    assert frame("every2", 0) == frame("shipped", 0) and frame("every2", 1) != frame("shipped", 1)
    made = {t: frame("every2", t) for t in range(T)}
    for t in (1, 2, 5):
        (out / "frames" / f"{t:05d}.png").unlink()
    ran.clear()
    again = enhance_path(scene, every, cp, root / "frames", out, depth_type="ray", video=False)
    assert again.enhanced_now == 3 and len(ran) == 1  # frame 2 by the model; 1 and 5 carried
    assert all(frame("every2", t) == made[t] for t in range(T))



def test_frames_are_carried_from_the_model_frame_only_where_its_render_predicts_theirs(toy_path, enhancer,
                                                                                     tmp_path):
    """model_every=3, carried from the last model frame, with the render-agreement gate set
    between the agreements a path without it measures: a frame due to be carried is
    carried exactly where its agreement reaches the gate (the report keeps it), and a resumed
    path (a carried frame and a model frame deleted) makes the same frames."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.temporal import TemporalConfig

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)

    def run(gate: float, out):
        config = TemporalConfig(model_every=3, min_seen=0.0, carry_from="model", carry_agreement=gate,
                                carry_between=False)
        gated = SceneEnhancer(scene, enhancer.model, options=EnhanceOptions(temporal=config))
        return enhance_path(scene, gated, cp, root / "frames", out, depth_type="ray", video=False).flicker["per_frame"]

    free = run(1e-6, tmp_path / "free")
    measured = [f["carry_agreement_db"] for f in free if "carry_agreement_db" in f]
    assert len(measured) >= 2 and all(f["carried"] for f in free if "carry_agreement_db" in f)
    gate = (min(measured) + max(measured)) / 2  # between them: no frame sits on it
    rows = run(gate, tmp_path / "gated")
    tried = [f for f in rows if "carry_agreement_db" in f]
    assert tried and all(f["carried"] == (f["carry_agreement_db"] >= gate) for f in tried)
    assert any(not f["carried"] for f in tried) and any(f["carried"] for f in tried)
    assert not any(f["carried"] for f in rows if "carry_agreement_db" not in f)
    frame = lambda t: (tmp_path / "gated" / "frames" / f"{t:05d}.png").read_bytes()  # noqa: E731
    made = {t: frame(t) for t in range(len(rows))}
    deleted = [next(f["frame"] for f in rows if f["carried"]), next(f["frame"] for f in tried if not f["carried"])]
    for t in deleted:
        (tmp_path / "gated" / "frames" / f"{t:05d}.png").unlink()
    again = run(gate, tmp_path / "gated")
    assert [f["carried"] for f in again] == [f["carried"] for f in rows]
    assert all(frame(t) == made[t] for t in range(len(rows)))

def _recording(scene, model, config, cp, made: list, monkeypatch):
    """A SceneEnhancer with ``config`` as its temporal setting that appends to ``made`` the path
    frame (its index in ``cp``) of every view the model runs on."""
    from roguenerf.enhance import EnhanceOptions

    recording = SceneEnhancer(scene, model, options=EnhanceOptions(temporal=config))
    real = recording.enhance
    monkeypatch.setattr(recording, "enhance", lambda render, *a, **k: made.append(
        next(t for t in range(len(cp)) if torch.equal(a[2], cp.world_from_cam[t]))) or real(render, *a, **k))
    return recording


def test_frames_between_two_model_frames_are_carried_from_both_and_resume_the_same(toy_path, enhancer, tmp_path,
                                                                                     monkeypatch):
    """carry_between with model_every=3 on the 7-frame path: the model runs on frames 0, 3 and 6
    only, and in that order for each stretch (3 before 1 and 2); each frame between is a mix of
    the two moved into it, not what carrying from the one before gives; the frames are written
    and reported in order, and a resumed path (a frame between and the model frame after it
    deleted, then stopped between them) makes the same frames."""
    from roguenerf.enhance.temporal import TemporalConfig

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    T = len(cp)
    made_by_model = []

    def run(out, between=True, **kw):
        config = TemporalConfig(model_every=3, min_seen=0.0, carry_agreement=0.0, carry_between=between,
                                both_ways=False)
        mixer = _recording(scene, enhancer.model, config, cp, made_by_model, monkeypatch)
        return enhance_path(scene, mixer, cp, root / "frames", out, depth_type="ray", video=False, **kw)

    from roguenerf.enhance.temporal import TemporalFilter

    apart = []
    blend = TemporalFilter.__call__
    monkeypatch.setattr(TemporalFilter, "__call__", lambda self, *a, frames_apart=1, **k: apart.append(
        frames_apart) or blend(self, *a, frames_apart=frames_apart, **k))
    result = run(tmp_path / "between")
    assert made_by_model == [0, 3, 6] and result.enhanced_now == T
    assert apart == [1, 3, 3]  # each model frame is blended with the one 3 frames before it
    rows = result.flicker["per_frame"]
    assert [f["frame"] for f in rows] == list(range(T))
    assert [f["carried"] for f in rows] == [t % 3 > 0 for t in range(T)]
    assert [p["to"] for p in result.flicker["per_pair"]] == list(range(1, T))
    frame = lambda folder, t: (tmp_path / folder / "frames" / f"{t:05d}.png").read_bytes()  # noqa: E731
    run(tmp_path / "after", between=False)
    assert frame("between", 0) == frame("after", 0) and frame("between", 1) != frame("after", 1)
    made = {t: frame("between", t) for t in range(T)}
    for t in (4, 5, 6):
        (tmp_path / "between" / "frames" / f"{t:05d}.png").unlink()
    asked = iter([False] * 5 + [True])  # stops before frame 5: 4 written, 6 made but not yet
    with pytest.raises(PathCancelled):
        run(tmp_path / "between", should_stop=lambda: next(asked))
    assert (tmp_path / "between" / "frames" / "00004.png").is_file()
    assert not (tmp_path / "between" / "frames" / "00006.png").exists()
    made_by_model.clear()
    again = run(tmp_path / "between")
    assert again.enhanced_now == 2 and made_by_model == [6]
    assert all(frame("between", t) == made[t] for t in range(T))
    assert [f["carried"] for f in again.flicker["per_frame"]] == [f["carried"] for f in rows]


@pytest.mark.parametrize("every", [1, 3])
def test_the_fade_along_the_path_resumes_to_the_same_frames(toy_path, enhancer, tmp_path, every):
    """fade_along, both ways (and with model_every=3, frames carried between the model's): frames
    deleted from both passes are made again as they were, though what a read-back frame carries
    from before is not on disk (worked out again from the renders, depths and cameras); the
    fade along the path makes other frames than the plain fade."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.temporal import TemporalConfig

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    T = len(cp)

    def run(out, along=True, **kw):
        # a fade of 0.5 degrees: the toy path's frames are 2-4 degrees apart
        config = TemporalConfig(fade_deg=0.5, fade_along=along, model_every=every, min_seen=0.0,
                                carry_agreement=0.0)
        faded = SceneEnhancer(scene, enhancer.model, options=EnhanceOptions(temporal=config))
        return enhance_path(scene, faded, cp, root / "frames", out, depth_type="ray", video=False, **kw)

    run(tmp_path / "along")
    run(tmp_path / "plain", along=False)
    frame = lambda folder, sub, t: (tmp_path / folder / sub / f"{t:05d}.png").read_bytes()  # noqa: E731
    made = {(sub, t): frame("along", sub, t) for sub in ("forward", "frames") for t in range(T)}
    assert any(made["frames", t] != frame("plain", "frames", t) for t in range(T))
    assert frame("plain", "forward", 0) == made["forward", 0]  # nothing carried into the first frame
    for sub, t in (("forward", 4), ("forward", 5), ("frames", 1), ("frames", 2)):
        (tmp_path / "along" / sub / f"{t:05d}.png").unlink()
    again = run(tmp_path / "along")
    assert again.enhanced_now == 2
    assert all(frame("along", sub, t) == made[sub, t] for sub in ("forward", "frames") for t in range(T))


def test_enhance_path_cli(toy_path, tmp_path):
    root = toy_path["root"]
    runner = CliRunner()
    args = ["enhance-path", str(root / "scene"), "--frames", str(root / "frames"), "--cameras",
            str(root / "camera_path.json"), "--output", str(tmp_path / "cli"), "--depth-type", "ray", "--no-video"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "flicker" in result.output and "frames have photos" in result.output
    assert " left]" in result.output  # the bar's estimate is PathClock's, not tqdm's own
    report = json.loads((tmp_path / "cli" / FLICKER_FILE).read_text())
    assert report["frames"] == 2 * STEPS + 1
    changes = report["flicker"]["neighbour_changes"]  # the toy path's set changes, and the CLI says where
    assert changes > 0 and f"the neighbour set changed across {changes} of {2 * STEPS} frame pairs" in result.output
    assert (tmp_path / "cli" / "forward").is_dir()  # both ways: the first pass's frames kept
    into = lambda name: [str(tmp_path / name) if a == str(tmp_path / "cli") else a for a in args]  # noqa: E731
    once = runner.invoke(app, [*into("once"), "--one-way"])
    assert once.exit_code == 0, once.output
    assert not (tmp_path / "once" / "forward").exists()
    assert (tmp_path / "once" / "frames" / "00000.png").read_bytes() == (
        tmp_path / "cli" / "forward" / "00000.png").read_bytes()
    clash = runner.invoke(app, [*into("clash"), "--one-way", "--no-temporal"])
    assert clash.exit_code == 2 and "--one-way" in clash.output and "Traceback" not in clash.output
    bad = runner.invoke(app, args[:-1] + ["--quality", "99"])
    assert bad.exit_code == 2 and "--quality" in bad.output and "Traceback" not in bad.output
    (tmp_path / "empty").mkdir()
    wrong = runner.invoke(app, [*args[:3], str(tmp_path / "empty"), *args[4:]])
    assert wrong.exit_code == 2 and "no frames found" in wrong.output
    every = args[:7] + [str(tmp_path / "every"), *args[8:], "--model-every", "2", "--carry-agreement", "0",
                        "--between-agreement", "0"]
    result = runner.invoke(app, every)
    assert result.exit_code == 0, result.output
    carried = [f["carried"] for f in json.loads((tmp_path / "every" / FLICKER_FILE).read_text())["per_frame"]]
    assert not carried[0] and any(carried) and not any(carried[t] for t in range(0, len(carried), 2))
    # --carry-after: from the last model frame only (another setting: another folder); frame 1 differs
    after = args[:7] + [str(tmp_path / "after"), *args[8:], "--model-every", "2", "--carry-after",
                        "--carry-agreement", "0"]
    assert runner.invoke(app, after).exit_code == 0
    frame = lambda folder: (tmp_path / folder / "frames" / "00001.png").read_bytes()  # noqa: E731
    assert frame("after") != frame("every")
    # --fast: TemporalConfig.fast(), one way; a flag beside it wins (here the model on every second frame)
    fast = args[:7] + [str(tmp_path / "fast"), *args[8:], "--fast", "--model-every", "2"]
    result = runner.invoke(app, fast)
    assert result.exit_code == 0, result.output
    assert not (tmp_path / "fast" / "forward").exists()
    rows = json.loads((tmp_path / "fast" / FLICKER_FILE).read_text())["per_frame"]
    assert not any(rows[t]["carried"] for t in range(0, len(rows), 2))
    assert all("carry_nearer" in rows[t] for t in range(1, len(rows) - 1, 2))  # judged by the photos' distance
    assert all(rows[t]["carried"] == (rows[t]["carry_nearer"] <= 1) for t in range(1, len(rows) - 1, 2))
    # --schedule gate: where no carry would pass, every frame is a model frame and none is even tried
    gate = args[:7] + [str(tmp_path / "gate"), *args[8:], "--fast", "--schedule", "gate", "--carry-nearer", "0.0001"]
    result = runner.invoke(app, gate)
    assert result.exit_code == 0, result.output
    rows = json.loads((tmp_path / "gate" / FLICKER_FILE).read_text())["per_frame"]
    assert not any(f["carried"] or "carry_nearer" in f for f in rows)
    for flags, message in ((["--model-every", "0"], "model_every"), (["--no-temporal", "--model-every", "2"],
                                                                     "drop --no-temporal"),
                           (["--no-temporal", "--fast"], "drop --no-temporal"),
                           (["--carry-agreement", "40"], "only with --model-every"),
                           (["--carry-after"], "only with --model-every"),
                           (["--model-every", "2", "--carry-after", "--between-agreement", "40"],
                            "without --carry-after"),
                           (["--model-every", "2", "--between-agreement", "-1"], "between_agreement"),
                           (["--model-every", "2", "--carry-agreement", "-1"], "carry_agreement"),
                           (["--carry-share", "0.1"], "only with --model-every"),
                           (["--carry-nearer", "1"], "only with --model-every"),
                           (["--model-every", "2", "--carry-nearer", "-1"], "carry_nearer"),
                           (["--model-every", "2", "--carry-share", "-1"], "carry_share"),
                           (["--schedule", "gate"], "only with --model-every"),
                           (["--model-every", "2", "--carry-after", "--schedule", "gate"], "drop --carry-after"),
                           (["--model-every", "2", "--schedule", "sometimes"], "schedule")):
        bad = runner.invoke(app, args[:7] + [str(tmp_path / "bad"), *args[8:], *flags])
        assert bad.exit_code == 2 and message in bad.output and "Traceback" not in bad.output


def test_frames_are_carried_only_where_the_renders_miss_is_a_small_share_of_the_change(toy_path, enhancer,
                                                                                        tmp_path):
    """carry_share (carrying between, no absolute gate): a share too large to refuse anything
    carries every frame due and reports both PSNRs; with a share between the ratios so measured,
    a frame is carried exactly where its renders' miss (mean square) is at most that share of the
    model frames' change, as the report's two figures say."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.temporal import TemporalConfig

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)

    def run(share: float, out):
        config = TemporalConfig(model_every=3, min_seen=0.0, carry_agreement=0.0, carry_share=share)
        gated = SceneEnhancer(scene, enhancer.model, options=EnhanceOptions(temporal=config))
        return enhance_path(scene, gated, cp, root / "frames", out, depth_type="ray", video=False).flicker["per_frame"]

    ratio = lambda f: 10 ** ((f["carry_change_db"] - f["carry_agreement_db"]) / 10)  # noqa: E731
    free = run(1e9, tmp_path / "free")
    tried = [f for f in free if "carry_change_db" in f]
    assert len(tried) >= 2 and all(f["carried"] and "carry_agreement_db" in f for f in tried)
    ratios = sorted(ratio(f) for f in tried)
    assert ratios[0] < ratios[-1] * 0.9
    share = math.sqrt(ratios[0] * ratios[-1])  # between them, not on either (the rows are rounded)
    rows = [f for f in run(share, tmp_path / "gated") if "carry_change_db" in f]
    assert rows and all(f["carried"] == (ratio(f) <= share) for f in rows)
    assert any(f["carried"] for f in rows) and not all(f["carried"] for f in rows)


def test_frames_nearer_a_photo_than_their_model_frames_are_given_to_the_model(toy_path, enhancer, tmp_path):
    """carry_nearer (carrying between): each frame due is judged by how far its two model frames
    are (mixed by position) over its nearest training photo, which the report keeps, worked out
    here from the cameras; with a ratio between those so measured, a frame is carried exactly
    where it is at most that."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.temporal import TemporalConfig
    from roguenerf.trajectory.enhancing import _match_views

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    matches = _match_views(scene, cp)

    def run(limit: float, out):
        config = TemporalConfig(model_every=3, min_seen=0.0, carry_nearer=limit, both_ways=False)
        gated = SceneEnhancer(scene, enhancer.model, options=EnhanceOptions(temporal=config))
        return enhance_path(scene, gated, cp, root / "frames", out, depth_type="ray", video=False).flicker["per_frame"]

    free = run(1e9, tmp_path / "free")
    tried = [f for f in free if "carry_nearer" in f]
    assert len(tried) >= 2 and all(f["carried"] for f in tried)
    centre = cp.world_from_cam[:, :3, 3]
    train = list(scene.indices("train"))
    for f in tried:
        t = f["frame"]
        a = t - t % 3
        b = min(a + 3, len(cp) - 1)
        far = ((b - t) * (centre[t] - centre[a]).norm() + (t - a) * (centre[t] - centre[b]).norm()) / (b - a)
        photo = min(float((centre[t] - scene.frames[i].world_from_cam[:3, 3]).norm()) for i in train
                    if i != matches[t])
        assert f["carry_nearer"] == pytest.approx(float(far) / photo, abs=1e-3)
    ratios = sorted(f["carry_nearer"] for f in tried)
    assert ratios[0] < ratios[-1] * 0.9
    limit = math.sqrt(ratios[0] * ratios[-1])
    rows = [f for f in run(limit, tmp_path / "gated") if "carry_nearer" in f]
    assert rows and all(f["carried"] == (f["carry_nearer"] <= limit) for f in rows)
    assert any(f["carried"] for f in rows) and not all(f["carried"] for f in rows)


def test_bad_camera_paths_are_named(tmp_path):
    bad = tmp_path / "p.json"
    bad.write_text(json.dumps({"render_height": 4, "render_width": 4, "camera_path": [{"fov": 50}]}))
    with pytest.raises(InputError, match="camera_to_world"):
        read_camera_path(bad)
    bad.write_text("{")
    with pytest.raises(InputError, match="cannot read"):
        read_camera_path(bad)
    ours = tmp_path / "t.json"
    pose = np.eye(4).tolist()
    ours.write_text(json.dumps({"fl_x": 10, "cx": 2, "cy": 2, "w": 4, "h": 4,
                                "frames": [{"transform_matrix": pose}, {"transform_matrix": pose}]}))
    cp = read_camera_path(ours)
    assert len(cp) == 2 and cp.source == "transforms" and (cp.width, cp.height) == (4, 4)


def test_paths_and_exports_import_no_service_stack_no_fitter_no_av():
    import subprocess
    import sys

    code = ("import sys, roguenerf.trajectory, roguenerf.data.exports, roguenerf.video; "
            "print(sorted(m for m in ('fastapi', 'huey', 'uvicorn', 'roguefit', 'av', 'service', 'workers') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


# --- issue 38: a path in another space is refused, naming the camera and the likely cause ------------


def _transforms_path(file, poses_gl, K, names=None):
    frames = [{"transform_matrix": p.tolist(), **({"file_path": names[t]} if names else {})}
              for t, p in enumerate(poses_gl)]
    file.write_text(json.dumps({"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]),
                                "cy": float(K[1, 2]), "w": W, "h": H, "fps": 12, "frames": frames}))
    return read_camera_path(file)


def test_the_right_path_fits_the_scene(toy_path, enhancer):
    from roguenerf.geometry import ray_to_z_depth
    from roguenerf.imageio import read_depth
    from roguenerf.trajectory import check_camera_path, find_path_frames

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    pairs = find_path_frames(root / "frames", len(cp))

    def depth_of(t):
        return ray_to_z_depth(read_depth(pairs[t][1]).double(), cp.K[t]).float()

    check = check_camera_path(scene, cp, depth_of)
    assert check.problem is None and check.warning is None and check.lost == [] and check.far == []
    assert min(check.seen.values()) > 0.3 and check.checked == list(range(len(cp)))


def test_a_model_world_path_without_dataparser_transforms_is_refused(toy_path, enhancer, tmp_path):
    # What the user hit: nerfstudio's camera_path.json (model world: rotated, scaled by 0.5 and
    # translated) read without dataparser_transforms.json. It used to exit 0 and write the MP4.
    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json")  # no dataparser
    with pytest.raises(InputError) as err:
        enhance_path(scene, enhancer, cp, root / "frames", tmp_path / "out", depth_type="ray", video=False)
    message = str(err.value)
    assert "does not fit the scene" in message and "dataparser_transforms.json" in message
    assert "OpenGL vs OpenCV" in message and message.endswith("To enhance it anyway: force=True")
    assert re.search(r"worst: camera \d+ \(camera_path\[\d+\]\)", message)
    assert not (tmp_path / "out").exists()  # refused before anything was written
    # --force goes on, with the problem as a warning.
    result = enhance_path(scene, enhancer, cp, root / "frames", tmp_path / "out", depth_type="ray", video=False,
                          force=True)
    assert result.frames == len(cp) and len(result.warnings) == 1 and "dataparser" in result.warnings[0]


def test_a_path_with_opencv_axes_read_as_opengl_is_refused_and_names_the_axes(toy_path, enhancer, tmp_path):
    root, scene = toy_path["root"], toy_path["scene"]
    K = scene.frames[0].K
    names = [f"frame_{t}.png" for t in range(len(toy_path["poses"]))]
    right = _transforms_path(tmp_path / "right.json", opencv_to_opengl(toy_path["poses"]), K, names)
    result = enhance_path(scene, enhancer, right, root / "frames", tmp_path / "ok", depth_type="ray", video=False)
    assert result.warnings == []
    wrong = _transforms_path(tmp_path / "wrong.json", toy_path["poses"], K, names)  # OpenCV written as-is
    with pytest.raises(InputError, match=r"worst: camera \d+ \(frames\[\d+\] \(frame_\d+\.png\)\)") as err:
        enhance_path(scene, enhancer, wrong, root / "frames", tmp_path / "bad", depth_type="ray", video=False)
    # The flipped hypothesis fits, so the axes come first among the causes.
    assert "Likely causes: OpenGL vs OpenCV axes: with the y and z axes flipped" in str(err.value)


def test_enhance_path_cli_refuses_a_wrong_space_path_and_force_goes_on(toy_path, tmp_path):
    root = toy_path["root"]
    K = toy_path["scene"].frames[0].K
    _transforms_path(tmp_path / "wrong.json", toy_path["poses"], K)
    args = ["enhance-path", str(root / "scene"), "--frames", str(root / "frames"), "--cameras",
            str(tmp_path / "wrong.json"), "--output", str(tmp_path / "cli"), "--depth-type", "ray", "--no-video"]
    refused = CliRunner().invoke(app, args)
    assert refused.exit_code == 2 and "does not fit the scene" in refused.output
    assert "Traceback" not in refused.output
    assert refused.output.strip().endswith("To enhance it anyway: --force") and "force=True" not in refused.output
    forced = CliRunner().invoke(app, [*args, "--force"])
    assert forced.exit_code == 0, forced.output
    assert "warning: " in forced.output and "OpenGL vs OpenCV" in forced.output


# --- issue 38: one pose validation (smooth_path, camera paths) ------------------------------------


def _key_poses():
    keys = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    keys[:, 0, 3] = torch.tensor([0.0, 1.0, 2.0])
    return keys


@pytest.mark.parametrize("breakage, message", [
    ("nan", r"key_poses\[1\]: expected a finite"),
    ("inf", r"key_poses\[1\]: expected a finite"),
    ("reflected", r"key_poses\[1\]: expected a proper rotation \(det \+1\), got det -1"),
    ("scaled", r"key_poses\[1\]: expected an orthonormal rotation .*scaled"),
    ("bottom", r"key_poses\[1\]: expected bottom row"),
])
def test_smooth_path_refuses_bad_key_poses(breakage, message):
    keys = _key_poses()
    if breakage == "nan":
        keys[1, 0, 0] = float("nan")
    elif breakage == "inf":
        keys[1, 2, 3] = float("inf")
    elif breakage == "reflected":
        keys[1, :3, 2] *= -1
    elif breakage == "scaled":
        keys[1, :3, :3] *= 2.0
    else:
        keys[1, 3, 0] = 0.5
    with pytest.raises(InputError, match=message):
        smooth_path(keys, 4)


def test_smooth_path_takes_3x4_keys_like_4x4():
    keys = _key_poses()
    torch.testing.assert_close(smooth_path(keys[:, :3], 4), smooth_path(keys, 4), rtol=0, atol=0)
    out = smooth_path(keys[:, :3].float(), 2)
    assert out.shape == (5, 4, 4) and out.dtype == torch.float64
    torch.testing.assert_close(out[2, :3, 3], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    with pytest.raises(InputError, match="steps"):
        smooth_path(keys, 0)


def test_camera_path_errors_name_the_camera(tmp_path):
    good = np.eye(4)
    bad = np.eye(4)
    bad[:3, 0] *= -1  # a reflection
    file = tmp_path / "t.json"
    file.write_text(json.dumps({"fl_x": 10, "cx": 2, "cy": 2, "w": 4, "h": 4, "frames": [
        {"file_path": "a.png", "transform_matrix": good.tolist()},
        {"file_path": "b.png", "transform_matrix": bad.tolist()}]}))
    with pytest.raises(InputError, match=r"frames\[1\] \(b\.png\): expected a proper rotation"):
        read_camera_path(file)
    nan = np.eye(4)
    nan[0, 3] = np.nan
    ns = tmp_path / "c.json"
    cams = [{"camera_to_world": good.flatten().tolist(), "fov": 50},
            {"camera_to_world": good.flatten().tolist(), "fov": 50},
            {"camera_to_world": [x if x == x else "NaN" for x in nan.flatten().tolist()], "fov": 50}]
    ns.write_text(json.dumps({"render_height": 4, "render_width": 4, "camera_path": cams}))
    with pytest.raises(InputError, match=r"camera_path\[2\]"):
        read_camera_path(ns)
    cams[2] = {"camera_to_world": good.flatten().tolist(), "fov": 200}
    ns.write_text(json.dumps({"render_height": 4, "render_width": 4, "camera_path": cams}))
    with pytest.raises(InputError, match=r"camera_path\[2\]\.fov"):
        read_camera_path(ns)
    # 3x4 (12 numbers) is a camera too.
    cams[2] = {"camera_to_world": good[:3].flatten().tolist(), "fov": 50}
    ns.write_text(json.dumps({"render_height": 4, "render_width": 4, "camera_path": cams}))
    assert len(read_camera_path(ns)) == 3


def test_side_by_side_halves_are_labelled():
    from roguenerf.video import label_image, side_by_side

    render = torch.full((3, 40, 80), 0.5)
    enhanced = torch.full((3, 40, 80), 0.25)
    labelled = label_image(render, "render")
    box = (labelled - render).abs().amax(0) > 0
    assert bool(box[:12, :40].any()) and not bool(box[20:].any()) and not bool(box[:, 60:].any())
    # white text on a dark box: both extremes appear where the label is
    assert float(labelled[:, :12, :40].max()) > 0.9 and float(labelled[:, :12, :40].min()) == 0.0
    both = side_by_side(render, enhanced)
    assert both.shape == (3, 40, 160)
    torch.testing.assert_close(both[:, :, :80], labelled)
    torch.testing.assert_close(both[:, :, 80:], label_image(enhanced, "enhanced"))
    assert not torch.equal(label_image(enhanced, "enhanced")[:, :12, :40], label_image(enhanced, "render")[:, :12, :40])


@pytest.mark.parametrize("frame, message", [
    (torch.full((3, 8, 8), float("nan")), "non-finite"),
    (torch.zeros(3, 8, 8, dtype=torch.uint8), r"dtype torch.uint8.*x.float\(\) / 255"),
    (torch.zeros(3, 8, 8, dtype=torch.bool), r"dtype torch.bool"),
    (torch.zeros(3, 8, 8, dtype=torch.int16), r"dtype torch.int16"),
    (torch.zeros(8, 8), r"expected shape \(3, H, W\)"),
    (np.zeros((8, 8, 3), np.uint8), "NumPy array"),
])
def test_the_video_writer_follows_the_image_dtype_rule(tmp_path, frame, message):
    from roguenerf.video import Mp4Writer

    path = tmp_path / "v.mp4"
    with pytest.raises(InputError, match=message):
        with Mp4Writer(path, fps=4) as video:
            video.write(torch.rand(3, 8, 8))
            video.write(frame)
    assert not path.exists() and not list(tmp_path.iterdir())  # atomic: nothing left behind


@pytest.mark.parametrize("given, stored, frames", [("z", "ray", "frames"), ("ray", "z", "zframes")])
def test_a_path_depth_type_that_disagrees_with_the_scene_is_refused(toy_path, enhancer, tmp_path, given, stored,
                                                                    frames):
    """The frames' depth against the scene's own z-depth, reprojected: the wrong type is found."""
    root, scene = toy_path["root"], toy_path["scene"]
    if frames == "zframes":  # the same frames with z-depth stored
        (tmp_path / "zframes" / "depth").mkdir(parents=True)
        for t, pose in enumerate(toy_path["poses"]):
            _, z = render_toy_view(make_toy_world(SEED), pose, scene.frames[0].K, H, W)
            write_depth_like(tmp_path / "zframes" / "depth" / f"frame_{t}.npy", z[0].numpy(), kind="npy")
        import shutil

        shutil.copytree(root / "frames" / "rgb", tmp_path / "zframes" / "rgb")
        folder = tmp_path / "zframes"
    else:
        folder = root / "frames"
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    with pytest.raises(InputError, match=rf"look like .* not --depth-type {given}.*Likely fix: --depth-type {stored}"):
        enhance_path(scene, enhancer, cp, folder, tmp_path / "out", depth_type=given, video=False)
    assert not (tmp_path / "out").exists()
    ok = enhance_path(scene, enhancer, cp, folder, tmp_path / "ok", depth_type=stored, video=False)
    assert ok.warnings == [] and ok.frames == len(cp)


@pytest.mark.parametrize("scale, shift", [(0.3, (0.5, -0.2, 0.1)), (0.8, (0.0, 0.0, 0.0)), (0.5, (1.0, 0.0, 0.0))])
def test_a_scaled_and_shifted_path_is_refused(toy_path, enhancer, tmp_path, scale, shift):
    """nerfstudio's usual dataparser transform (no rotation: scale + translation) applied to the
    path's cameras, the frames rendered where the scene's cameras are: refused, every time."""
    root, scene = toy_path["root"], toy_path["scene"]
    parser = DataparserTransform(transform=torch.tensor(
        [[1.0, 0.0, 0.0, shift[0]], [0.0, 1.0, 0.0, shift[1]], [0.0, 0.0, 1.0, shift[2]]], dtype=torch.float64),
        scale=scale)
    K = scene.frames[0].K
    fov = math.degrees(2 * math.atan(H / 2 / float(K[1, 1])))
    cams = [{"camera_to_world": parser.to_model(opencv_to_opengl(p)).flatten().tolist(), "fov": fov}
            for p in toy_path["poses"]]
    (tmp_path / "cp.json").write_text(json.dumps({"render_height": H, "render_width": W, "camera_path": cams}))
    with pytest.raises(InputError, match="does not fit the scene.*dataparser_transforms.json"):
        enhance_path(scene, enhancer, read_camera_path(tmp_path / "cp.json"), root / "frames", tmp_path / "out",
                     depth_type="ray", video=False)
    # With the transform, the same file is the right path.
    right = read_camera_path(tmp_path / "cp.json", dataparser=parser)
    torch.testing.assert_close(right.world_from_cam, toy_path["poses"], rtol=0, atol=1e-9)
    ok = enhance_path(scene, enhancer, right, root / "frames", tmp_path / "ok", depth_type="ray", video=False)
    assert ok.warnings == []


def test_a_far_path_without_depth_to_tell_is_refused_naming_the_camera(toy_path):
    from roguenerf.trajectory import FAR_FACTOR, check_camera_path

    scene = toy_path["scene"]
    poses = toy_path["poses"].clone()
    poses[4:, :3, 3] += torch.tensor([100.0, 0.0, 0.0], dtype=torch.float64)  # the last three cameras
    cp = read_camera_path(toy_path["root"] / "camera_path.json", dataparser=PARSER)
    cp.world_from_cam = poses
    empty = torch.zeros(1, H, W)  # no known depth: only the distance can tell
    check = check_camera_path(scene, cp, lambda t: empty)
    assert check.far == [4, 5, 6] and check.worst == 6 and check.lost == []
    assert all(check.distance[t] > FAR_FACTOR for t in check.far)
    assert check.problem.startswith("the camera path does not fit the scene: 3 of 7 checked cameras are far")
    assert "worst: camera 6 (camera_path[6]) lies" in check.problem


def test_a_field_whose_own_novel_views_fail_the_check_is_named_as_the_likely_cause(tmp_path):
    """A field with floaters: its depth is off on every novel view, its renders of the scene's
    held-out views included. A path through them is refused as before, but the first likely cause
    named is the field's geometry, not the path's coordinate space; with the held-out views' depth
    right, that cause is not named."""
    from roguenerf.data.readers import load_scene
    from roguenerf.imageio import atomic_write, encode_npy
    from roguenerf.trajectory import CameraPath, check_camera_path

    root = tmp_path / "scene"
    scene = make_toy_scene(root, seed=SEED, n_train=6, n_test=3, height=H, width=W, kind="orbit")
    test = scene.indices("test")
    poses, K = scene.poses(test), scene.intrinsics()[test].to(torch.float64)
    path = CameraPath(world_from_cam=poses, K=K, width=W, height=H)
    halved = {t: scene.depth(i) * 0.5 for t, i in enumerate(test)}  # floaters halfway to the camera
    check = check_camera_path(scene, path, lambda t: halved[t])
    assert check.problem is not None and "the field's own geometry" not in check.problem
    for i in test:  # the field's own renders of its held-out views: the same floaters
        atomic_write(scene.frames[i].depth_path, encode_npy((scene.depth(i)[0] * 0.5).numpy()))
    check = check_camera_path(load_scene(root), path, lambda t: halved[t])
    assert check.problem.startswith("the camera path does not fit the scene: 3 of 3 checked cameras see almost none")
    assert "Likely causes: the field's own geometry: its renders of the scene's held-out views fail" in check.problem
    assert "with --force (force=True) it goes on" in check.problem


def test_check_camera_names_the_likely_cause_for_one_view(toy_path):
    """check_camera, the test /enhance runs on one view's camera (issue 49): an OpenCV pose read
    as OpenGL, a pose in other units (depth too, or not) and one in another world are refused
    with the likeliest cause first; force returns the problem instead."""
    from roguenerf.errors import CameraMismatchError
    from roguenerf.geometry import opengl_to_opencv
    from roguenerf.trajectory import check_camera

    scene = toy_path["scene"]
    i = scene.indices("test")[0]
    pose, K, depth = scene.frames[i].world_from_cam.to(torch.float64), scene.frames[i].K, scene.depth(i).float()
    assert check_camera(scene, depth, K, pose) is None
    scaled = pose.clone()
    scaled[:3, 3] *= 10
    shifted = pose.clone()
    shifted[:3, 3] += torch.tensor([30.0, -20.0, 25.0], dtype=torch.float64)
    cases = [(opengl_to_opencv(pose), depth, "convention", "Likely causes: OpenGL vs OpenCV axes: with the y and z "
                                                            "axes flipped this camera sees"),
             (scaled, depth, "scale", "Likely causes: another unit: with its position scaled by 0.1 this camera sees"),
             (scaled, depth * 10, "scale", "Likely causes: another unit: with its position and depth scaled by"),
             (shifted, depth, "world", "Likely causes: OpenGL vs OpenCV axes (the pose's convention); another "
                                       "coordinate space")]
    for wrong, d, cause, needle in cases:
        with pytest.raises(CameraMismatchError) as err:
            check_camera(scene, d, K, wrong)
        assert err.value.cause == cause and needle in str(err.value), str(err.value)
        assert str(err.value).startswith("the camera does not fit the scene: the camera ")
        assert str(err.value).endswith(". To enhance it anyway: --force (force=True)")
        assert check_camera(scene, d, K, wrong, force=True) == err.value.problem


def test_enhance_path_refuses_an_output_folder_it_did_not_write_and_a_bad_pose_before_loading(toy_path, tmp_path):
    """Issue 49: a folder of the user's as --output is refused (its frames/ would be taken for enhanced
    frames, its files written over); a camera path with a bad rotation is refused before the scene loads."""
    root = toy_path["root"]
    K = toy_path["scene"].frames[0].K
    good = tmp_path / "good.json"
    _transforms_path(good, opencv_to_opengl(toy_path["poses"]), K)
    mine = tmp_path / "mine"
    (mine / "frames").mkdir(parents=True)
    (mine / "frames" / "00000.png").write_bytes(b"my picture")
    args = ["enhance-path", str(root / "scene"), "--frames", str(root / "frames"), "--depth-type", "ray", "--no-video"]
    refused = CliRunner().invoke(app, [*args, "--cameras", str(good), "--output", str(mine)])
    assert refused.exit_code == 2 and refused.output.strip().splitlines() == [
        f"error: output: {mine} exists and is not empty: it holds other files, not an earlier enhance-path "
        "output (which would be resumed); choose a new folder"]
    assert sorted(p.name for p in mine.rglob("*")) == ["00000.png", "frames"]
    assert (mine / "frames" / "00000.png").read_bytes() == b"my picture"
    with pytest.raises(InputError, match="not an earlier enhance-path output"):
        enhance_path(toy_path["scene"], None, read_camera_path(good), root / "frames", mine)
    doc = json.loads(good.read_text())
    doc["frames"][1]["transform_matrix"][0][0] *= 1.5  # not a rotation
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    missing = tmp_path / "no_scene"  # the scene is not even there: the path is read first
    result = CliRunner().invoke(app, ["enhance-path", str(missing), "--frames", str(root / "frames"), "--cameras",
                                      str(bad), "--output", str(tmp_path / "out"), "--no-video"])
    assert result.exit_code == 2 and "frames[1]" in result.output and "does not exist" not in result.output


def test_a_transposed_inria_cameras_json_is_refused_in_its_own_convention(toy_path, enhancer, tmp_path):
    """Issue 49: Inria's cameras.json is OpenCV camera-to-world; the refusal used to say that camera
    paths "are read as OpenGL"."""
    root, scene = toy_path["root"], toy_path["scene"]
    K = scene.frames[0].K
    cams = [{"id": t, "img_name": f"frame_{t}", "width": W, "height": H, "position": pose[:3, 3].tolist(),
             "rotation": pose[:3, :3].T.tolist(),  # world-to-camera: the transposed rotation
             "fx": float(K[0, 0]), "fy": float(K[1, 1])} for t, pose in enumerate(toy_path["poses"])]
    (tmp_path / "cameras.json").write_text(json.dumps(cams))
    cp = read_camera_path(tmp_path / "cameras.json")
    assert cp.source == "inria"
    with pytest.raises(InputError) as err:
        enhance_path(scene, enhancer, cp, root / "frames", tmp_path / "out", depth_type="ray", video=False)
    message = str(err.value)
    assert "a rotation written world-to-camera (transposed) or with OpenGL axes (Inria's cameras.json is read as " \
           "OpenCV camera-to-world (rotation and position, as 3DGS's train.py writes them))" in message
    assert "read as OpenGL" not in message


def test_both_ways_blends_each_first_pass_frame_with_the_frame_after_it(toy_path, enhancer, tmp_path):
    """TemporalConfig.both_ways (the default): forward/ holds what the first pass alone writes
    (both_ways=False), and frames/ is that, blended from the last frame back with the frame after
    it as written, by the same filter; the last frame has none after it. Flicker and gains are
    measured on frames/."""
    from roguenerf.enhance import EnhanceOptions
    from roguenerf.enhance.temporal import TemporalConfig, TemporalFilter
    from roguenerf.geometry.cameras import ray_to_z_depth
    from roguenerf.imageio import read_depth, read_image
    from roguenerf.metrics import psnr
    from roguenerf.trajectory import find_path_frames

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    T = len(cp)
    both = enhance_path(scene, enhancer, cp, root / "frames", tmp_path / "both", depth_type="ray", video=False)
    once = SceneEnhancer(scene, enhancer.model, options=EnhanceOptions(temporal=TemporalConfig(both_ways=False)))
    calls = []
    enhance_path(scene, once, cp, root / "frames", tmp_path / "once", depth_type="ray", video=False,
                 progress=lambda d, t: calls.append((d, t)))
    assert calls == [(d, T) for d in range(1, T + 1)]  # one pass: one step per frame
    png = lambda folder, sub, t: tmp_path / folder / sub / f"{t:05d}.png"  # noqa: E731
    assert all(png("both", "forward", t).read_bytes() == png("once", "frames", t).read_bytes() for t in range(T))
    assert not (tmp_path / "once" / "forward").exists()
    back = TemporalFilter(TemporalConfig())
    files = find_path_frames(root / "frames", T)
    seen = {}
    for t in reversed(range(T)):
        render = read_image(files[t][0])
        depth = ray_to_z_depth(read_depth(files[t][1]).double(), cp.K[t]).float()
        expected = back(render, read_image(png("both", "forward", t)), depth, cp.K[t], cp.world_from_cam[t])
        written = read_image(png("both", "frames", t))
        assert (written - expected).abs().max() <= 0.5 / 255 + 1e-6, t
        back.remember(render, written, depth, cp.K[t], cp.world_from_cam[t], parallax=back.last_parallax)
        seen[t] = ([render, written], depth, cp.K[t], cp.world_from_cam[t])
    assert png("both", "frames", T - 1).read_bytes() == png("both", "forward", T - 1).read_bytes()
    assert png("both", "frames", 0).read_bytes() != png("both", "forward", 0).read_bytes()
    report = json.loads((tmp_path / "both" / FLICKER_FILE).read_text())
    assert [p["from"] for p in report["per_pair"]] == list(range(T - 1))
    # each pair measured the way the second pass blends: frame t + 1 moved into t (its own move reused)
    for p in report["per_pair"]:
        (images, depth, K, pose), (images1, depth1, K1, pose1) = seen[p["from"]], seen[p["to"]]
        errors, fraction = pair_flicker(images1, images, depth1, depth, K1, K, pose1, pose)
        forward, _ = pair_flicker(images, images1, depth, depth1, K, K1, pose, pose1)
        assert [p["render"], p["enhanced"]] == pytest.approx(errors, rel=1e-4) != forward
        assert p["valid_fraction"] == pytest.approx(fraction)
    gains = {f["frame"]: f["gain_db"] for f in report["per_frame"] if "gain_db" in f}
    photo = scene.photo(scene.index(report["per_frame"][0]["view"]))
    first = read_image(png("both", "frames", 0))
    render0 = read_image(files[0][0])
    assert gains[0] == pytest.approx(float(psnr(first[None], photo[None])[0] - psnr(render0[None], photo[None])[0]),
                                     abs=1e-4)
    assert both.enhanced_now == T


def test_the_path_clock_times_each_pass_on_its_own():
    """PathClock: while the first of two passes runs, the seconds left are its own steps at its
    rate plus the second pass's at SECOND_PASS_SHARE of that; the second pass is then timed on its
    own steps; frames read back at the start of a resumed path leave the window; one pass without
    both_ways; None before anything is timed."""
    from roguenerf.enhance.temporal import TemporalConfig
    from roguenerf.trajectory.enhancing import SECOND_PASS_SHARE, SECOND_PASS_SHARE_CARRIED, PathClock

    now = [0.0]
    clock = PathClock(TemporalConfig(), clock=lambda: now[0])
    frames, left = 10, []
    for done in range(1, 2 * frames + 1):  # the first pass 2 s a step, the second 0.5 s (not the share's 0.4)
        now[0] += 2.0 if done <= frames else 0.5
        left.append(clock(done, 2 * frames))
    assert left[0] == pytest.approx(9 * 2.0 + frames * 2.0 * SECOND_PASS_SHARE)
    assert left[frames - 1] == pytest.approx(frames * 2.0 * SECOND_PASS_SHARE)  # the first pass done
    assert left[frames:] == pytest.approx([0.5 * (frames - k) for k in range(1, frames + 1)])  # its own rate
    cumulative = (2 * frames - 1) / (1 / 2.0)  # what the rate of all steps so far said after the first step
    assert left[0] < 0.7 * cumulative

    now[0] = 0.0
    resumed = PathClock(None, clock=lambda: now[0])  # frame by frame: one pass
    estimates = []
    for done in range(1, 41):  # 20 frames read back (0.01 s), then 1 s a frame
        now[0] += 0.01 if done <= 20 else 1.0
        estimates.append(resumed(done, 40))
    assert estimates[20] < 5  # just after the read-back frames the window still holds them
    assert estimates[-8] == pytest.approx(7.0)  # 13 steps later it holds only enhanced frames
    assert PathClock(TemporalConfig(model_every=4)).second_share == SECOND_PASS_SHARE_CARRIED
    assert PathClock(TemporalConfig(both_ways=False)).passes == 1
    start = [5.0]
    first = PathClock(TemporalConfig(), clock=lambda: start[0])
    assert first(0, 20) is None  # nothing done yet
    start[0] = 7.0
    assert first(1, 20) == pytest.approx(9 * 2.0 + 10 * 2.0 * SECOND_PASS_SHARE)  # timed from the clock's start


def test_the_gated_schedule_runs_the_model_where_it_says_and_resumes_the_same(toy_path, enhancer, tmp_path,
                                                                             monkeypatch):
    """schedule "gate" on the 7-frame path, with a carry_nearer under which it differs from every
    3rd frame: the model runs on exactly the scheduled frames (each model frame after a stretch
    before the frames of the stretch), every other frame is carried, and a path stopped and
    resumed makes the same frames."""
    from roguenerf.enhance.temporal import TemporalConfig, gated_schedule
    from roguenerf.trajectory.enhancing import _match_views

    root, scene = toy_path["root"], toy_path["scene"]
    cp = read_camera_path(root / "camera_path.json", dataparser=PARSER)
    T = len(cp)
    matches = _match_views(scene, cp)
    train = list(scene.indices("train"))
    photos = [min(float((cp.world_from_cam[t, :3, 3] - scene.frames[i].world_from_cam[:3, 3]).norm())
                  for i in train if i != matches[t]) for t in range(T)]
    centres = cp.world_from_cam[:, :3, 3].double()
    limits = [x for x in (2.0, 1.0, 0.5, 0.25, 0.1) if gated_schedule(centres, photos, 3, x) not in
              ([0, 3, 6], list(range(T)))]
    assert limits, "no carry_nearer makes this path's schedule differ from every 3rd frame"
    schedule = gated_schedule(centres, photos, 3, limits[0])
    made_by_model = []

    def run(out, **kw):
        config = TemporalConfig(model_every=3, min_seen=0.0, carry_nearer=limits[0], schedule="gate",
                                both_ways=False)
        gated = _recording(scene, enhancer.model, config, cp, made_by_model, monkeypatch)
        return enhance_path(scene, gated, cp, root / "frames", out, depth_type="ray", video=False, **kw)

    result = run(tmp_path / "gate")
    assert sorted(made_by_model) == schedule and len(made_by_model) == len(schedule)
    assert [f["carried"] for f in result.flicker["per_frame"]] == [t not in schedule for t in range(T)]
    frame = lambda t: (tmp_path / "gate" / "frames" / f"{t:05d}.png").read_bytes()  # noqa: E731
    made = {t: frame(t) for t in range(T)}
    for t in range(2, T):
        (tmp_path / "gate" / "frames" / f"{t:05d}.png").unlink()
    asked = iter([False] * 4 + [True])
    with pytest.raises(PathCancelled):
        run(tmp_path / "gate", should_stop=lambda: next(asked))
    again = run(tmp_path / "gate")
    assert all(frame(t) == made[t] for t in range(T))
    assert [f["carried"] for f in again.flicker["per_frame"]] == [t not in schedule for t in range(T)]
