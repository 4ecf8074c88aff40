"""``roguenerf import-3dgs``: a trained 3DGS ``.ply`` + its dataset -> our scene folder (and a
camera path's frames for ``enhance-path``), on a tiny synthetic splat scene with known answers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from roguenerf.cli import app
from roguenerf.data.colmap import write_colmap
from roguenerf.data.readers import load_scene
from roguenerf.data.toy import look_at
from roguenerf.geometry.cameras import opencv_to_opengl
from roguenerf.imageio import read_image, write_png
from roguenerf.paths import find_path_frames
from roguenerf.splats import Gaussians, logit, render, write_ply

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
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"fl_x": 40.0, "fl_y": 40.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H,
                                "frames": [{"transform_matrix": opencv_to_opengl(p).tolist()} for p in path_poses]}))
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
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"fl_x": 40.0, "fl_y": 40.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H,
                                "frames": [{"transform_matrix": opencv_to_opengl(p).tolist()} for p in path_poses]}))
    out = tmp_path / "scene"
    args = ["import-3dgs", str(root / "data"), "--ply", str(root / "point_cloud.ply"), "--output", str(out),
            "--path", str(path), "--backend", "cpu"]
    assert runner.invoke(app, args).exit_code == 0
    assert json.loads((out / "path" / "transforms.json").read_text())["source"]["tool"] == "3dgs"
    (out / "renders" / "view_00.png").write_bytes(b"stale")
    again = runner.invoke(app, args)  # an earlier output of import-3dgs: replaced whole
    assert again.exit_code == 0, again.output
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
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"fl_x": 40.0, "fl_y": 40.0, "cx": W / 2, "cy": H / 2, "w": W, "h": H,
                                "frames": [{"transform_matrix": opencv_to_opengl(p).tolist()} for p in path_poses]}))
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
