"""``roguenerf import-3dgs``: a trained 3DGS ``.ply`` + its dataset -> our scene folder (and a
camera path's frames for ``enhance-path``), on a tiny synthetic splat scene with known answers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from roguecli import app
from roguenerf.data.colmap import write_colmap
from roguenerf.data.readers import load_scene
from roguenerf.data.toy import look_at
from roguenerf.geometry.cameras import opencv_to_opengl
from roguenerf.imageio import read_image, write_png
from roguenerf.splats import Gaussians, logit, render, write_ply
from roguenerf.trajectory import find_path_frames

runner = CliRunner()
H, W, VIEWS = 36, 48, 9


def splat_scene(n: int = 400, seed: int = 0) -> Gaussians:
    """A few hundred Gaussians on a textured wall and a box in front of it (degree-1 SH)."""
    g = torch.Generator().manual_seed(seed)
    wall = torch.rand(n // 2, 3, generator=g) * torch.tensor([3.0, 0.05, 2.2]) + torch.tensor([-1.5, 1.5, -1.1])
    box = torch.rand(n - n // 2, 3, generator=g) * torch.tensor([0.8, 0.8, 0.8]) + torch.tensor([-0.4, 0.0, -0.4])
    means = torch.cat([wall, box])
    sh = torch.randn(n, 4, 3, generator=g) * 0.15
    sh[:, 0] = (torch.rand(n, 3, generator=g) - 0.5) * 2.5
    return Gaussians(means=means, sh=sh, opacity=logit(torch.rand(n, generator=g) * 0.3 + 0.69),
                     log_scales=torch.log(torch.rand(n, 3, generator=g) * 0.12 + 0.08),
                     quats=torch.randn(n, 4, generator=g))


def cameras(count: int) -> tuple[torch.Tensor, torch.Tensor]:
    poses = []
    for i in range(count):
        a = math.radians(-25 + 50 * i / max(count - 1, 1))
        eye = torch.tensor([3.0 * math.sin(a), -3.0 * math.cos(a), 0.4], dtype=torch.float64)
        poses.append(look_at(eye, torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64)))
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]], dtype=torch.float64)
    return torch.stack(poses), K


def _camera_path(path, poses: torch.Tensor, *, opengl: bool = True):
    """``poses`` (OpenCV) as a nerfstudio transforms.json camera path at the dataset's size, focal
    40 px; ``opengl=False`` writes them without the axis change (the user's mix-up)."""
    frames = [{"transform_matrix": (opencv_to_opengl(p) if opengl else p).tolist()} for p in poses]
    path.write_text(json.dumps({"fl_x": 40.0, "fl_y": 40.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H,
                                "frames": frames}))
    return path


@pytest.fixture(scope="module")
def splat_data(tmp_path_factory):
    """A transforms.json dataset whose photos are the splats' renders plus a little noise, and the .ply."""
    root = tmp_path_factory.mktemp("splat")
    g = splat_scene()
    write_ply(root / "point_cloud.ply", g)
    poses, K = cameras(VIEWS)
    frames = []
    noise = torch.Generator().manual_seed(1)
    for i in range(VIEWS):
        rgb, _, _ = render(g, poses[i], K, H, W)
        photo = (rgb + 0.03 * torch.randn(rgb.shape, generator=noise)).clamp(0, 1)
        (root / "data" / "images").mkdir(parents=True, exist_ok=True)
        write_png(root / "data" / "images" / f"view_{i:02d}.png", photo)
        frames.append({"file_path": f"images/view_{i:02d}.png", "transform_matrix": opencv_to_opengl(poses[i]).tolist(),
                       "split": "test" if i in (2, 6) else "train"})
    doc = {"fl_x": 40.0, "fl_y": 40.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H, "frames": frames}
    (root / "data" / "transforms.json").write_text(json.dumps(doc))
    return root, g, poses, K


def test_import_3dgs_renders_every_view_and_evaluate_loads_it(splat_data, tmp_path):
    root, g, poses, K = splat_data
    out = tmp_path / "scene"
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--ply", str(root / "point_cloud.ply"),
                                 "--output", str(out), "--backend", "cpu"])
    assert result.exit_code == 0, result.output
    scene = load_scene(out)
    assert [f.split for f in scene.frames].count("test") == 2 and len(scene.frames) == VIEWS
    assert not list(tmp_path.glob(".scene.*"))  # the temporary folder was renamed into place
    for i, frame in enumerate(scene.frames):
        rgb, depth, acc = render(g, poses[i], K, H, W)
        assert torch.allclose(frame.world_from_cam, poses[i], atol=1e-12)
        assert (scene.render(i) - rgb).abs().max() <= 0.5 / 255 + 1e-6
        got = scene.depth(i)
        known = acc >= 0.5
        assert known.float().mean() > 0.3 and (~known).any()
        assert torch.equal(got > 0, known)  # no splat (or too little of one): unknown depth
        assert (got - depth).abs().max() < 1e-5
        assert torch.equal(read_image(frame.image_path), read_image(root / "data" / "images" / f"view_{i:02d}.png"))
    assert (out / "acc" / "view_00.png").is_file()
    meta = json.loads((out / "transforms.json").read_text())["source"]
    assert meta["gaussians"] == 400 and meta["sh_degree"] == 1 and meta["backend"] == "cpu"

    evaluated = runner.invoke(app, ["evaluate", str(out), "--json"])
    assert evaluated.exit_code == 0, evaluated.output
    report = json.loads(evaluated.stdout.strip().splitlines()[-1])
    assert len(report["views"]) == 2 and math.isfinite(report["render"]["psnr"])


def test_a_camera_path_goes_to_an_enhanced_mp4_in_two_commands(splat_data, tmp_path):
    root, g, poses, K = splat_data
    path_poses, _ = cameras(5)
    path_poses[:, 2, 3] += 0.2  # novel views: above the dataset's
    path = _camera_path(tmp_path / "path.json", path_poses)
    out = tmp_path / "scene"
    first = runner.invoke(app, ["import-3dgs", str(root / "data"), "--ply", str(root / "point_cloud.ply"),
                                "--output", str(out), "--path", str(path), "--backend", "cpu"])
    assert first.exit_code == 0, first.output
    frames = out / "path"
    pairs = find_path_frames(frames, 5)
    rgb, depth, _ = render(g, path_poses[3], K, H, W)
    assert (read_image(pairs[3][0]) - rgb).abs().max() <= 0.5 / 255 + 1e-6
    assert np.abs(np.load(pairs[3][1]) - depth[0].numpy()).max() < 1e-5
    pytest.importorskip("av")
    second = runner.invoke(app, ["enhance-path", str(out), "--frames", str(frames), "--cameras",
                                 str(frames / "transforms.json"), "--output", str(tmp_path / "enhanced")])
    assert second.exit_code == 0, second.output
    assert (tmp_path / "enhanced" / "enhanced.mp4").stat().st_size > 0


def test_import_3dgs_reads_a_colmap_dataset_with_the_trainers_split(splat_data, tmp_path):
    root, g, poses, K = splat_data
    data = tmp_path / "colmap"
    (data / "images").mkdir(parents=True)
    names = [f"view_{i:02d}.png" for i in range(VIEWS)]
    for name in names:
        (data / "images" / name).write_bytes((root / "data" / "images" / name).read_bytes())
    write_colmap(data / "sparse" / "0", names=names, K=K, world_from_cam=poses, widths=W, heights=H)
    out = tmp_path / "scene"
    result = runner.invoke(app, ["import-3dgs", str(data), "--ply", str(root / "point_cloud.ply"),
                                 "--output", str(out), "--backend", "cpu", "--hold", "4"])
    assert result.exit_code == 0, result.output
    scene = load_scene(out)
    assert [f.name for f in scene.frames if f.split == "test"] == ["view_00", "view_04", "view_08"]
    rgb, _, _ = render(g, poses[5], K, H, W)
    assert (scene.render("view_05") - rgb).abs().max() <= 0.5 / 255 + 1e-6


def test_import_3dgs_refuses_bad_input(splat_data, tmp_path):
    root, _, _, _ = splat_data
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--ply", str(bad), "--output",
                                 str(tmp_path / "out"), "--backend", "cpu"])
    assert result.exit_code == 2 and "binary_little_endian" in result.output
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.*"))
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "mine.txt").write_text("keep me")
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--ply", str(root / "point_cloud.ply"),
                                 "--output", str(busy), "--backend", "cpu"])
    assert result.exit_code == 2 and "other files" in result.output
    assert (busy / "mine.txt").read_text() == "keep me"
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--ply", str(root / "point_cloud.ply"),
                                 "--output", str(tmp_path / "o2"), "--backend", "warp"])
    assert result.exit_code == 2 and "backend" in result.output


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def test_a_splatfacto_export_in_the_model_world_renders_the_dataset_views(splat_data, tmp_path):
    """nerfstudio's model world: x' = s (R_T x + t_T). The same splats moved there, with the
    dataparser file, give the dataset-world renders and depths in the dataset's units."""
    root, g, poses, K = splat_data
    g0 = Gaussians(g.means, g.sh[:, :1].clone(), g.opacity, g.log_scales, g.quats)  # degree 0: no SH rotation
    theta, s = 0.7, 0.37
    R_T = torch.tensor([[math.cos(theta), -math.sin(theta), 0], [math.sin(theta), math.cos(theta), 0], [0, 0, 1]])
    t_T = torch.tensor([0.3, -1.2, 0.5])
    q_T = torch.tensor([math.cos(theta / 2), 0, 0, math.sin(theta / 2)])
    moved = Gaussians(means=s * (g0.means @ R_T.T + t_T), sh=g0.sh, opacity=g0.opacity,
                      log_scales=g0.log_scales + math.log(s), quats=quat_mul(q_T.expand_as(g0.quats), g0.quats))
    write_ply(tmp_path / "splat.ply", moved)
    parser = tmp_path / "dataparser_transforms.json"
    parser.write_text(json.dumps({"transform": torch.cat([R_T, t_T[:, None]], 1).tolist(), "scale": s}))
    out = tmp_path / "scene"
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--ply", str(tmp_path / "splat.ply"),
                                 "--output", str(out), "--backend", "cpu", "--dataparser-transforms", str(parser)])
    assert result.exit_code == 0, result.output
    scene = load_scene(out)
    assert (out / "dataparser_transforms.json").is_file()
    for i in (0, 4):
        rgb, depth, _ = render(g0, poses[i], K, H, W)
        assert (scene.render(i) - rgb).abs().max() <= 0.5 / 255 + 2e-4
        got = scene.depth(i)
        assert torch.equal(got > 0, depth > 0)
        assert ((got - depth).abs() / depth.clamp_min(1e-6)).max() < 1e-4


def normalised(g: Gaussians, centre: torch.Tensor, scale: float) -> Gaussians:
    """The splats as gsplat's trainer saves them with its default normalize_world_space (recentred
    on the cameras, scaled down): another world than the dataset's."""
    return Gaussians(means=(g.means - centre) * scale, sh=g.sh, opacity=g.opacity,
                     log_scales=g.log_scales + math.log(scale), quats=g.quats)


def test_a_ply_in_another_world_is_refused_before_rendering(splat_data, tmp_path):
    root, g, poses, K = splat_data
    ply = tmp_path / "normalised.ply"
    write_ply(ply, normalised(g, poses[:, :3, 3].mean(0).float(), 1 / 20))
    out = tmp_path / "scene"
    args = ["import-3dgs", str(root / "data"), "--ply", str(ply), "--output", str(out), "--backend", "cpu"]
    result = runner.invoke(app, args)
    assert result.exit_code == 2, result.output
    assert "--ply: the splats do not lie in the dataset's world" in result.output
    assert "--no-normalize-world-space" in result.output and "--dataparser-transforms" in result.output
    assert "--force" in result.output and "Traceback" not in result.output
    assert not out.exists() and not list(tmp_path.glob(".scene.*"))
    forced = runner.invoke(app, args + ["--force"])
    assert forced.exit_code == 0, forced.output
    assert "warning: --ply: the splats do not lie in the dataset's world" in forced.output
    assert len(load_scene(out).frames) == VIEWS


def test_the_world_check_passes_the_right_ply_cheaply(splat_data):
    from roguenerf.splats.importer import check_world, read_dataset_views

    root, g, poses, K = splat_data
    views, _ = read_dataset_views(root / "data")
    check = check_world(g, views)
    assert check.problem is None and min(check.coverage) > 0.2
    moved = check_world(normalised(g, poses[:, :3, 3].mean(0).float(), 1 / 20), views)
    assert moved.problem is not None and max(moved.coverage) < 0.05


def test_a_path_that_sees_nothing_is_refused_before_rendering(splat_data, tmp_path):
    root, g, poses, K = splat_data
    path_poses, _ = cameras(5)
    # OpenCV poses written as OpenGL: every camera looks away.
    path = _camera_path(tmp_path / "path.json", path_poses, opengl=False)
    out = tmp_path / "scene"
    args = ["import-3dgs", str(root / "data"), "--ply", str(root / "point_cloud.ply"), "--output", str(out),
            "--path", str(path), "--backend", "cpu"]
    result = runner.invoke(app, args)
    assert result.exit_code == 2, result.output
    assert "--path: the camera path does not fit the scene" in result.output
    assert "none of the 5 checked cameras sees a splat" in result.output and "--force" in result.output
    assert not out.exists() and not list(tmp_path.glob(".scene.*"))
    forced = runner.invoke(app, args + ["--force"])
    assert forced.exit_code == 0, forced.output
    assert "warning: --path: the camera path does not fit the scene" in forced.output
    assert len(find_path_frames(out / "path", 5)) == 5


def inria_cameras(poses, names, width, height, focal, hold=8) -> list[dict]:
    """Inria's cameras.json: test cameras (every hold-th in name order) first, then the rest."""
    order = [i for i in range(len(names)) if i % hold == 0] + [i for i in range(len(names)) if i % hold]
    out = []
    for j, i in enumerate(order):
        p = poses[i]
        out.append({"id": j, "img_name": names[i], "width": width, "height": height, "position": p[:3, 3].tolist(),
                    "rotation": p[:3, :3].tolist(), "fx": focal, "fy": focal})
    return out


def half_size_colmap(root, poses, K, folder):
    """A COLMAP dataset at twice the photos' size whose images_2/ holds them (gsplat/Inria -r 2)."""
    names = [f"view_{i:02d}.png" for i in range(VIEWS)]
    (folder / "images_2").mkdir(parents=True)
    for name in names:
        (folder / "images_2" / name).write_bytes((root / "data" / "images" / name).read_bytes())
    K2 = K.clone()
    K2[:2] *= 2
    write_colmap(folder / "sparse" / "0", names=names, K=K2, world_from_cam=poses, widths=2 * W, heights=2 * H)
    return [n[:-4] for n in names]


def test_an_inria_cameras_json_path_follows_the_dataset_order_and_image_size(splat_data, tmp_path):
    root, g, poses, K = splat_data
    data = tmp_path / "colmap"
    names = half_size_colmap(root, poses, K, data)
    cams = tmp_path / "cameras.json"
    cams.write_text(json.dumps(inria_cameras(poses, names, 2 * W, 2 * H, 80.0)))
    out = tmp_path / "scene"
    result = runner.invoke(app, ["import-3dgs", str(data), "--images", "images_2", "--ply",
                                 str(root / "point_cloud.ply"), "--output", str(out), "--path", str(cams),
                                 "--backend", "cpu"])
    assert result.exit_code == 0, result.output
    scene = load_scene(out)
    doc = json.loads((out / "path" / "transforms.json").read_text())
    assert len(doc["frames"]) == VIEWS
    for t, frame in enumerate(doc["frames"]):  # frame t is view t: same pose, intrinsics and size
        assert (frame["w"], frame["h"]) == (W, H)
        assert (frame["fl_x"], frame["cx"]) == (40.0, W / 2)
        pose = torch.tensor(frame["transform_matrix"], dtype=torch.float64)
        assert (pose - opencv_to_opengl(scene.frames[t].world_from_cam)).abs().max() < 1e-9
    pairs = find_path_frames(out / "path", VIEWS)
    assert torch.equal(read_image(pairs[8][0]), scene.render(8))
    video = tmp_path / "video"
    enhanced = runner.invoke(app, ["enhance-path", str(out), "--frames", str(out / "path"), "--cameras",
                                   str(out / "path" / "transforms.json"), "--output", str(video), "--no-video"])
    assert enhanced.exit_code == 0, enhanced.output
    flicker = json.loads((video / "flicker.json").read_text())
    assert flicker["psnr"]["frames_with_photos"] == VIEWS  # every frame is its view: a PSNR each


def inria_model(root, poses, names, folder):
    """An Inria model folder: cameras.json, cfg_args and two iterations' point clouds."""
    for it in (7000, 30000):
        (folder / "point_cloud" / f"iteration_{it}").mkdir(parents=True)
    (folder / "point_cloud" / "iteration_7000" / "point_cloud.ply").write_bytes(b"not the latest")
    (folder / "point_cloud" / "iteration_30000" / "point_cloud.ply").write_bytes(
        (root / "point_cloud.ply").read_bytes())
    (folder / "cameras.json").write_text(json.dumps(inria_cameras(poses, names, W, H, 40.0)))
    (folder / "cfg_args").write_text("Namespace(eval=True, images='images', resolution=-1, sh_degree=1)")
    return folder


def test_a_model_folder_goes_to_a_fly_through_in_one_command(splat_data, tmp_path):
    root, g, poses, K = splat_data
    model = inria_model(root, poses, [f"view_{i:02d}" for i in range(VIEWS)], tmp_path / "model")
    out = tmp_path / "scene"
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--model", str(model), "--output", str(out),
                                 "--backend", "cpu", "--frames", "17"])
    assert result.exit_code == 0, result.output
    meta = json.loads((out / "transforms.json").read_text())["source"]
    assert meta["ply"] == str(model / "point_cloud" / "iteration_30000" / "point_cloud.ply")
    scene = load_scene(out)
    doc = json.loads((out / "path" / "transforms.json").read_text())
    assert len(doc["frames"]) == 17 and doc["source"]["format"] == "fly-through"
    for t, i in ((0, 0), (2, 1), (16, 8)):  # every 2nd frame is a view (9 keys, 2 steps each)
        pose = torch.tensor(doc["frames"][t]["transform_matrix"], dtype=torch.float64)
        assert (pose - opencv_to_opengl(poses[i])).abs().max() < 1e-12
    steps = [torch.tensor(f["transform_matrix"])[:3, 3] for f in doc["frames"]]
    gaps = torch.stack([(b - a).norm() for a, b in zip(steps, steps[1:])])
    assert gaps.max() < 1.5 * gaps.min()  # no jumps
    pairs = find_path_frames(out / "path", 17)
    assert torch.equal(read_image(pairs[2][0]), scene.render(1))
    video = tmp_path / "scene_video"
    assert (f"next: roguenerf enhance-path {out} --frames {out / 'path'} --cameras "
            f"{out / 'path' / 'transforms.json'} --output {video}") in result.output


def test_a_new_path_for_an_earlier_import_renders_only_the_path(splat_data, tmp_path):
    root, g, poses, K = splat_data
    model = inria_model(root, poses, [f"view_{i:02d}" for i in range(VIEWS)], tmp_path / "model")
    out = tmp_path / "scene"
    base = ["import-3dgs", str(root / "data"), "--model", str(model), "--output", str(out), "--backend", "cpu"]
    assert runner.invoke(app, base + ["--frames", "9"]).exit_code == 0
    before = {p: p.stat().st_mtime_ns for p in (out / "renders").iterdir()}
    marker = out / "renders" / "view_03.png"
    marker.write_bytes(marker.read_bytes())  # a re-render would write it anew (new inode)
    inode = marker.stat().st_ino
    again = runner.invoke(app, base + ["--frames", "5"])
    assert again.exit_code == 0, again.output
    assert "only the path" in again.output
    assert marker.stat().st_ino == inode and len(before) == VIEWS
    assert len(find_path_frames(out / "path", 5)) == 5
    # Another .ply: everything again.
    other = tmp_path / "other.ply"
    other.write_bytes((root / "point_cloud.ply").read_bytes())
    third = runner.invoke(app, ["import-3dgs", str(root / "data"), "--ply", str(other), "--output", str(out),
                                "--backend", "cpu"])
    assert third.exit_code == 0, third.output
    assert "only the path" not in third.output and marker.stat().st_ino != inode
    assert not (out / "path").exists()


def test_a_model_folder_is_checked(splat_data, tmp_path):
    root, g, poses, K = splat_data
    empty = tmp_path / "empty"
    empty.mkdir()
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--model", str(empty), "--output",
                                 str(tmp_path / "o1"), "--backend", "cpu"])
    assert result.exit_code == 2
    assert "--model: " in result.output and "no point_cloud/iteration_*/point_cloud.ply" in result.output
    other = inria_model(root, poses, [f"IMG_{i:04d}" for i in range(VIEWS)], tmp_path / "other")
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--model", str(other), "--output",
                                 str(tmp_path / "o2"), "--backend", "cpu"])
    assert result.exit_code == 2
    assert "cameras.json names none of the dataset's views" in result.output
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--output", str(tmp_path / "o3")])
    assert result.exit_code == 2 and "--ply point_cloud.ply or --model MODEL" in result.output
    assert not [p for p in tmp_path.iterdir() if p.name.startswith((".o", "o1", "o2", "o3"))]


def _tree(folder) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_import_3dgs_never_replaces_a_folder_it_did_not_write(splat_data, tmp_path):
    """Issue 49: a nerfstudio dataset (a transforms.json, photos, notes) given as --output by mistake
    is refused whole, not taken for an earlier output and deleted."""
    root, _, _, _ = splat_data
    ply = str(root / "point_cloud.ply")
    mine = tmp_path / "mydataset"
    (mine / "images").mkdir(parents=True)
    (mine / "images" / "photo.png").write_bytes(b"my photo")
    (mine / "transforms.json").write_text('{"frames": []}')
    (mine / "notes.txt").write_text("notes")
    before = _tree(mine)
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--ply", ply, "--output", str(mine),
                                 "--backend", "cpu"])
    assert result.exit_code == 2, result.output
    assert result.output.strip().splitlines() == [
        f"error: output: {mine} exists and is not empty: it holds other files, not an earlier output of this "
        "command (which would be replaced); choose a new folder"]
    assert _tree(mine) == before and not list(tmp_path.glob(".mydataset.*"))
    # A folder holding only a camera path file is no earlier output either (it used to be taken for one).
    (tmp_path / "cams").mkdir()
    (tmp_path / "cams" / "camera_path.json").write_text("{}")
    result = runner.invoke(app, ["import-3dgs", str(root / "data"), "--ply", ply, "--output",
                                 str(tmp_path / "cams"), "--backend", "cpu"])
    assert result.exit_code == 2 and "choose a new folder" in result.output
    assert (tmp_path / "cams" / "camera_path.json").read_text() == "{}"


def test_import_3dgs_replaces_its_own_output_but_never_a_file_it_did_not_write(splat_data, tmp_path):
    root, _, _, K = splat_data
    path_poses, _ = cameras(3)
    path = _camera_path(tmp_path / "path.json", path_poses)
    out = tmp_path / "scene"
    args = ["import-3dgs", str(root / "data"), "--ply", str(root / "point_cloud.ply"), "--output", str(out),
            "--path", str(path), "--backend", "cpu"]
    assert runner.invoke(app, args).exit_code == 0
    assert json.loads((out / "path" / "transforms.json").read_text())["source"]["tool"] == "3dgs"
    (out / "renders" / "view_00.png").write_bytes(b"stale")
    # An earlier output of import-3dgs, with another option (the same ones would render only the
    # path): replaced whole.
    args += ["--depth-threshold", "0.4"]
    again = runner.invoke(app, args)
    assert again.exit_code == 0, again.output
    assert "only the path" not in again.output
    assert (out / "renders" / "view_00.png").read_bytes() != b"stale"
    for extra in ("notes.txt", "images/extra.png", "path/rgb/mine.png"):
        (out / extra).write_text("mine")
        before = _tree(out)
        refused = runner.invoke(app, args)
        assert refused.exit_code == 2, refused.output
        assert refused.output.strip().splitlines() == [
            f"error: output: {out} is an earlier output of this command but also holds files it did not write "
            f"({extra}), which replacing it would delete; move them out or choose a new folder"]
        assert _tree(out) == before
        (out / extra).unlink()


def test_render_camera_path_never_replaces_a_folder_it_did_not_write(splat_data, tmp_path):
    from roguenerf.errors import InputError
    from roguenerf.splats.importer import import_3dgs, render_camera_path

    root, _, _, _ = splat_data
    path_poses, _ = cameras(3)
    path = _camera_path(tmp_path / "path.json", path_poses)
    ply = root / "point_cloud.ply"
    dataset = tmp_path / "dataset"  # a nerfstudio dataset: its transforms.json is not a rendered path
    dataset.mkdir()
    (dataset / "transforms.json").write_text((root / "data" / "transforms.json").read_text())
    (dataset / "photo.png").write_bytes(b"photo")
    before = _tree(dataset)
    with pytest.raises(InputError, match=rf"^path output: {dataset} exists and is not empty: .* choose a new folder$"):
        render_camera_path(ply, path, dataset, backend="cpu")
    assert _tree(dataset) == before
    out = tmp_path / "frames"
    render_camera_path(ply, path, out, backend="cpu")
    render_camera_path(ply, path, out, backend="cpu")  # its own earlier output: replaced
    assert sorted(_tree(out)) == ["depth/00000.npy", "depth/00001.npy", "depth/00002.npy", "rgb/00000.png",
                                  "rgb/00001.png", "rgb/00002.png", "transforms.json"]
    (out / "depth" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match=r"did not write \(depth/notes.txt\)"):
        render_camera_path(ply, path, out, backend="cpu")
    assert (out / "depth" / "notes.txt").read_text() == "mine"
    # A rendered path is no scene folder, and a scene folder no rendered path: each refused as foreign.
    (out / "depth" / "notes.txt").unlink()
    with pytest.raises(InputError, match="not an earlier output of this command"):
        import_3dgs(root / "data", ply, out, backend="cpu")
    scene = tmp_path / "scene"
    import_3dgs(root / "data", ply, scene, backend="cpu")
    with pytest.raises(InputError, match="not an earlier output of this command"):
        render_camera_path(ply, path, scene, backend="cpu")


def test_a_missing_images_folder_is_named_with_the_ones_there(splat_data, tmp_path):
    """Issue 49: --images images_4 where there is no such folder used to say "pass --images"."""
    root, _, poses, K = splat_data
    data = tmp_path / "colmap"
    names = [f"view_{i:02d}.png" for i in range(VIEWS)]
    for folder in ("images", "images_2"):
        (data / folder).mkdir(parents=True)
        for name in names:
            (data / folder / name).write_bytes((root / "data" / "images" / name).read_bytes())
    write_colmap(data / "sparse" / "0", names=names, K=K, world_from_cam=poses, widths=W, heights=H)
    result = runner.invoke(app, ["import-3dgs", str(data), "--ply", str(root / "point_cloud.ply"), "--output",
                                 str(tmp_path / "out"), "--backend", "cpu", "--images", "images_4"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        f"error: {data / 'images_4'}: image folder not found (--images images_4); image folders in {data}: "
        "images, images_2: pass one with --images"]
    assert not (tmp_path / "out").exists()
