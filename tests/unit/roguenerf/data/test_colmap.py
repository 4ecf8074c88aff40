"""COLMAP sparse models: our reader and writer against known answers and against pycolmap."""

from __future__ import annotations

import math
import shutil
import struct

import numpy as np
import pytest
import torch

from roguenerf.data.colmap import (
    ColmapCamera,
    ColmapImage,
    ColmapModel,
    find_sparse_dir,
    qvec_to_rotmat,
    read_colmap,
    read_colmap_model,
    rotmat_to_qvec,
    write_colmap,
    write_colmap_model,
)
from roguenerf.data.toy import make_toy_scene
from roguenerf.errors import InputError, SceneFormatError
from roguenerf.imageio import write_png


@pytest.fixture(scope="module")
def toy_scene(tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp("toy") / "scene", seed=3, n_train=7, n_test=3, height=24, width=32)


def _colmap_dataset(toy_scene, root, *, binary, names=None, K=None):
    """The toy scene's photos and poses as a COLMAP dataset at ``root`` (model order scrambled)."""
    frames = toy_scene.frames
    names = names or [f"{f.name}.png" for f in frames]
    (root / "images").mkdir(parents=True)
    for f, name in zip(frames, names, strict=True):
        shutil.copyfile(f.image_path, root / "images" / name)
    Ks = torch.stack([f.K for f in frames]) if K is None else K
    order = [3, 0, 7, 1, 9, 2, 5, 4, 8, 6]  # the model's own image order is not the name order
    write_colmap(
        root / "sparse" / "0",
        names=[names[i] for i in order],
        K=Ks[order],
        world_from_cam=torch.stack([frames[i].world_from_cam for i in order]),
        widths=32,
        heights=24,
        binary=binary,
    )
    return names


@pytest.mark.parametrize("binary", [True, False])
def test_toy_scene_round_trip(toy_scene, tmp_path, binary):
    # Per-view focal lengths and principal points, so each view needs its own camera.
    K = torch.stack([f.K for f in toy_scene.frames]).clone()
    K[:, 0, 0] += torch.arange(10, dtype=torch.float64) * 0.37
    K[:, 1, 2] += 0.25
    names = _colmap_dataset(toy_scene, tmp_path, binary=binary, K=K)
    ext = "bin" if binary else "txt"
    assert (tmp_path / "sparse" / "0" / f"images.{ext}").is_file()
    data = read_colmap(tmp_path)
    assert data.format == ext
    assert data.names == sorted(names)
    assert data.stems == [n[:-4] for n in sorted(names)]
    assert data.image_paths == [tmp_path / "images" / n for n in sorted(names)]
    by_name = {f"{f.name}.png": (f, K[i]) for i, f in enumerate(toy_scene.frames)}
    for i, name in enumerate(data.names):
        frame, k = by_name[name]
        assert data.world_from_cam.dtype == torch.float64 and data.K.dtype == torch.float64
        assert (data.world_from_cam[i] - frame.world_from_cam).abs().max() < 1e-9, name
        assert (data.K[i] - k).abs().max() < 1e-9, name
    assert data.widths == [32] * 10 and data.heights == [24] * 10
    assert len(set(data.camera_ids)) == 10


def test_handwritten_text_model_known_answer(tmp_path):
    """A model written by hand: 90 degrees about z (w first), a SIMPLE_PINHOLE camera."""
    sparse = tmp_path / "sparse"  # sparse/ without 0/, as some tools write it
    sparse.mkdir()
    (sparse / "cameras.txt").write_text("# comment\n1 SIMPLE_PINHOLE 64 48 50 32.5 24\n")
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    (sparse / "images.txt").write_text(
        "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        f"7 {c!r} 0 0 {s!r} 1 2 3 1 b.jpg\n"
        "10.5 20.5 -1 3 4 12\n"
        f"2 1 0 0 0 0 0 0 1 a.jpg\n"
        "\n"
    )
    data = read_colmap(tmp_path, check_files=False)
    assert data.names == ["a.jpg", "b.jpg"] and data.image_ids == [2, 7]
    want = torch.tensor(
        [[0.0, 1, 0, -2], [-1, 0, 0, 1], [0, 0, 1, -3], [0, 0, 0, 1]], dtype=torch.float64
    )
    assert (data.world_from_cam[1] - want).abs().max() < 1e-12
    assert torch.equal(data.world_from_cam[0], torch.eye(4, dtype=torch.float64))
    assert torch.equal(
        data.K[0], torch.tensor([[50.0, 0, 32.5], [0, 50, 24], [0, 0, 1]], dtype=torch.float64)
    )
    model = read_colmap_model(tmp_path, keypoints=True)
    assert model.images[7].xys.tolist() == [[10.5, 20.5], [3.0, 4.0]]
    assert model.images[7].point3D_ids.tolist() == [-1, 12]
    # Written by hand without the keypoint lines: every image is still read.
    (sparse / "images.txt").write_text(
        f"7 {c!r} 0 0 {s!r} 1 2 3 1 b.jpg\n2 1 0 0 0 0 0 0 1 a.jpg\n3 1 0 0 0 0 0 1 1 c.jpg\n"
    )
    assert read_colmap(tmp_path, check_files=False).names == ["a.jpg", "b.jpg", "c.jpg"]
    (sparse / "images.txt").write_text("2 1 0 0 0 0 0 0 1 a.jpg\n\n2 1 0 0 0 0 0 0 1 b.jpg\n\n")
    with pytest.raises(SceneFormatError, match="image id 2 appears twice"):
        read_colmap(tmp_path, check_files=False)


def test_quaternion_of_every_branch():
    rng = np.random.default_rng(0)
    for angle_axis in [
        (math.pi, (1, 0, 0)),
        (math.pi, (0, 1, 0)),
        (math.pi, (0, 0, 1)),
        (0.3, (1, 2, 3)),
    ]:
        angle, axis = angle_axis
        axis = np.asarray(axis, float) / np.linalg.norm(axis)
        q = np.array([math.cos(angle / 2), *(math.sin(angle / 2) * axis)])
        R = qvec_to_rotmat(q)
        assert np.allclose(rotmat_to_qvec(R), q if q[0] >= 0 else -q, atol=1e-12)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        back = rotmat_to_qvec(qvec_to_rotmat(q))
        assert np.allclose(back, q if q[0] >= 0 else -q, atol=1e-12)


def test_locates_the_model(toy_scene, tmp_path):
    _colmap_dataset(toy_scene, tmp_path, binary=True)
    model_dir = tmp_path / "sparse" / "0"
    assert find_sparse_dir(tmp_path) == model_dir
    assert find_sparse_dir(model_dir) == model_dir
    assert find_sparse_dir(model_dir / "images.bin") == model_dir
    # Given the model folder, the dataset is the folder above sparse/.
    assert read_colmap(model_dir).root == tmp_path
    with pytest.raises(SceneFormatError, match="no COLMAP model"):
        find_sparse_dir(tmp_path / "images")


def test_distortion_refused_and_zero_distortion_accepted(tmp_path):
    for k1, ok in ((0.0, True), (0.05, False)):
        folder = tmp_path / f"k{k1}" / "sparse" / "0"
        cams = {1: ColmapCamera(1, "OPENCV", 64, 48, (50.0, 51.0, 32.0, 24.0, k1, 0.0, 0.0, 0.0))}
        ims = {1: ColmapImage(1, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, "x.png")}
        write_colmap_model(folder, ColmapModel(cams, ims), binary=True)
        if ok:
            data = read_colmap(folder.parent.parent, check_files=False)
            assert data.K[0].tolist() == [[50.0, 0, 32.0], [0, 51.0, 24.0], [0, 0, 1]]
        else:
            with pytest.raises(SceneFormatError, match="image_undistorter") as err:
                read_colmap(folder.parent.parent, check_files=False)
            assert "OPENCV" in str(err.value) and "camera 1" in str(err.value)


def test_malformed_files_are_named(toy_scene, tmp_path):
    _colmap_dataset(toy_scene, tmp_path, binary=True)
    images_bin = tmp_path / "sparse" / "0" / "images.bin"
    images_bin.write_bytes(images_bin.read_bytes()[:-5])
    with pytest.raises(SceneFormatError, match="truncated") as err:
        read_colmap(tmp_path)
    assert str(images_bin) in str(err.value)
    (tmp_path / "sparse" / "0" / "images.bin").unlink()
    (tmp_path / "sparse" / "0" / "cameras.bin").unlink()
    (tmp_path / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 32 24 abc 1 2 3\n")
    (tmp_path / "sparse" / "0" / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(SceneFormatError, match="line 1"):
        read_colmap(tmp_path, check_files=False)


def test_missing_image_and_downscaled_folder(toy_scene, tmp_path):
    _colmap_dataset(toy_scene, tmp_path, binary=True)
    # A half-size copy as images_2/ (gsplat's --data-factor 2): K follows the files.
    (tmp_path / "images_2").mkdir()
    for path in (tmp_path / "images").iterdir():
        write_png(tmp_path / "images_2" / path.name, torch.zeros(3, 12, 16))
    full = read_colmap(tmp_path)
    half = read_colmap(tmp_path, images="images_2")
    assert half.widths == [16] * 10 and half.heights == [12] * 10
    assert torch.allclose(half.K[:, :2], full.K[:, :2] / 2, atol=1e-12)
    (tmp_path / "images" / full.names[4]).unlink()
    with pytest.raises(SceneFormatError, match="missing image"):
        read_colmap(tmp_path)


@pytest.mark.parametrize("binary", [True, False])
def test_agrees_with_pycolmap(toy_scene, tmp_path, binary):
    """pycolmap (COLMAP's own code) reads what we write, and we read what it writes."""
    import pycolmap  # in the dev extra (optional at run time: our reader needs no dependency)

    _colmap_dataset(toy_scene, tmp_path, binary=binary)
    model_dir = tmp_path / "sparse" / "0"
    ours = read_colmap(tmp_path)
    rec = pycolmap.Reconstruction(str(model_dir))
    assert sorted(im.name for im in rec.images.values()) == ours.names
    for image in rec.images.values():
        i = ours.names.index(image.name)
        cam_from_world = image.cam_from_world()
        cam_from_world = np.asarray(cam_from_world.matrix())
        world_from_cam = np.linalg.inv(np.vstack([cam_from_world, [0, 0, 0, 1]]))
        assert np.abs(world_from_cam - ours.world_from_cam[i].numpy()).max() < 1e-9
        assert (
            np.abs(np.asarray(image.camera.calibration_matrix()) - ours.K[i].numpy()).max() < 1e-9
        )
    # ... and the other way: pycolmap writes, we read (both encodings).
    out = tmp_path / "written_by_pycolmap"
    out.mkdir()
    (rec.write_binary if binary else rec.write_text)(str(out))
    theirs = read_colmap(out, images=tmp_path / "images")
    assert theirs.names == ours.names
    assert (theirs.world_from_cam - ours.world_from_cam).abs().max() < 1e-9
    assert (theirs.K - ours.K).abs().max() < 1e-9


# -- import-gsplat with a COLMAP dataset -------------------------------------------------------


def _run(*args):
    from typer.testing import CliRunner

    from roguecli import app

    return CliRunner().invoke(app, [str(a) for a in args])


def _named_renders(toy_scene, out):
    """rgb/NAME.png + depth/NAME.npy (z), as a gsplat script writes them."""
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    for f in toy_scene.frames:
        shutil.copyfile(f.render_path, out / "rgb" / f"{f.name}.png")
        np.save(out / "depth" / f"{f.name}.npy", toy_scene.depth(f.name)[0].numpy())


def test_import_gsplat_reads_a_colmap_dataset(toy_scene, tmp_path):
    _colmap_dataset(toy_scene, tmp_path / "data", binary=True)
    _named_renders(toy_scene, tmp_path / "renders")
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "renders", "--output",
             tmp_path / "out", "--eval")
    assert r.exit_code == 0, r.output
    from roguenerf.data.readers import load_scene

    scene = load_scene(tmp_path / "out")
    names = sorted(f.name for f in toy_scene.frames)
    assert [f.name for f in scene.frames] == names
    # --eval: names sorted, positions 0 and 8 held out (Inria's llffhold, gsplat's test_every).
    assert [f.name for f in scene.frames if f.split == "test"] == [names[0], names[8]]
    for f in scene.frames:
        want = toy_scene.frames[toy_scene.index(f.name)]
        assert (f.world_from_cam - want.world_from_cam).abs().max() < 1e-9
        assert (f.K - want.K).abs().max() < 1e-9
        assert torch.equal(scene.depth(f.name), toy_scene.depth(f.name))
    # Issue 49: without a flag, the same split (import-3dgs's default too); --hold 0: every view
    # trains; --hold N / --test-every N and --split-file override.
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "renders", "--output",
             tmp_path / "default")
    assert r.exit_code == 0, r.output
    assert [f.name for f in load_scene(tmp_path / "default").frames if f.split == "test"] == [names[0], names[8]]
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "renders", "--output",
             tmp_path / "all", "--hold", "0")
    assert r.exit_code == 0, r.output
    assert {f.split for f in load_scene(tmp_path / "all").frames} == {"train"}
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "renders", "--output",
             tmp_path / "h3", "--hold", "3")
    assert r.exit_code == 0, r.output
    assert [f.name for f in load_scene(tmp_path / "h3").frames if f.split == "test"] == names[::3]
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "renders", "--output",
             tmp_path / "neg", "--hold", "-1")
    assert r.exit_code == 2 and r.output.strip() == "error: --hold: expected >= 0 (0: no test views), got -1"
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "renders", "--output",
             tmp_path / "t3", "--test-every", "3")
    assert r.exit_code == 0, r.output
    got = [f.name for f in load_scene(tmp_path / "t3").frames if f.split == "test"]
    assert got == [names[0], names[3], names[6], names[9]]
    (tmp_path / "test.txt").write_text(f"{names[2]}.png\n{names[5]}\n")
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "renders", "--output",
             tmp_path / "sf", "--eval", "--split-file", tmp_path / "test.txt")
    assert r.exit_code == 0, r.output
    got = [f.name for f in load_scene(tmp_path / "sf").frames if f.split == "test"]
    assert got == [names[2], names[5]]
    (tmp_path / "bad.txt").write_text("nope.png\n")
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "renders", "--output",
             tmp_path / "bad", "--split-file", tmp_path / "bad.txt")
    assert r.exit_code == 2 and "nope.png" in r.output and "Traceback" not in r.output


def _inria_render(toy_scene, model_dir, *, test_every, depth):
    """What Inria's render.py writes: MODEL/<split>/ours_30000/renders/00000.png (+ gt/), the
    i-th camera of the split in name order; ``depth``: also a depth/ folder (as forks add)."""
    names = sorted(f.name for f in toy_scene.frames)
    for split in ("train", "test") if test_every else ("train",):  # 0: trained without --eval
        views = [n for i, n in enumerate(names) if (bool(test_every) and i % test_every == 0) == (split == "test")]
        base = model_dir / split / "ours_30000"
        (base / "renders").mkdir(parents=True)
        (base / "gt").mkdir()
        if depth:
            (base / "depth").mkdir()
        for i, name in enumerate(views):
            frame = toy_scene.frames[toy_scene.index(name)]
            shutil.copyfile(frame.render_path, base / "renders" / f"{i:05d}.png")
            shutil.copyfile(frame.image_path, base / "gt" / f"{i:05d}.png")
            if depth:
                np.save(base / "depth" / f"{i:05d}.npy", toy_scene.depth(name)[0].numpy())
    # An older iteration that must not be used.
    (model_dir / ("test" if test_every else "train") / "ours_7000" / "renders").mkdir(parents=True)


def _import_inria_renders(toy_scene, tmp_path, *, binary: bool, depth: bool):
    """``import-gsplat`` of the toy scene as a COLMAP dataset (tmp_path/data) with Inria's renders of a
    model trained with --eval (tmp_path/model, every 8th view held out) into tmp_path/out."""
    _colmap_dataset(toy_scene, tmp_path / "data", binary=binary)
    _inria_render(toy_scene, tmp_path / "model", test_every=8, depth=depth)
    return _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "model", "--output", tmp_path / "out")


def test_inria_numbered_renders_map_to_views_in_name_order(toy_scene, tmp_path):
    from roguenerf.data.readers import load_scene

    # No --eval given: Inria's test renders say the model was trained with it (every 8th).
    r = _import_inria_renders(toy_scene, tmp_path, binary=False, depth=True)
    assert r.exit_code == 0, r.output
    scene = load_scene(tmp_path / "out")
    assert len(scene.frames) == 10
    for f in scene.frames:
        assert torch.equal(scene.depth(f.name), toy_scene.depth(f.name)), f.name
        assert torch.equal(scene.render(f.name), toy_scene.render(f.name)), f.name
    names = sorted(f.name for f in toy_scene.frames)
    assert [f.name for f in scene.frames if f.split == "test"] == [names[0], names[8]]
    # A split that does not fit the renders is named, not guessed.
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "model", "--output",
             tmp_path / "o2", "--test-every", "3")
    assert r.exit_code == 2 and "renders, but the dataset has" in r.output
    assert "--hold 8" in r.output
    # Renders of a model trained without --eval (no test renders): all train, with no flag.
    _inria_render(toy_scene, tmp_path / "all_train", test_every=0, depth=True)
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "all_train", "--output",
             tmp_path / "o3")
    assert r.exit_code == 0, r.output
    assert {f.split for f in load_scene(tmp_path / "o3").frames} == {"train"}


def test_renders_without_depth_point_to_import_3dgs(toy_scene, tmp_path):
    r = _import_inria_renders(toy_scene, tmp_path, binary=True, depth=False)
    assert r.exit_code == 2, r.output
    assert "depth" in r.output and "import-3dgs" in r.output and "Traceback" not in r.output
    # gsplat simple_trainer's eval canvases (photo | render, no depth).
    (tmp_path / "results" / "renders").mkdir(parents=True)
    write_png(tmp_path / "results" / "renders" / "val_step29999_0000.png", torch.zeros(3, 24, 64))
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "results", "--output",
             tmp_path / "out2")
    assert r.exit_code == 2 and "side by side" in r.output and "import-3dgs" in r.output


def test_distorted_colmap_dataset_refused_by_the_cli(tmp_path):
    folder = tmp_path / "data" / "sparse" / "0"
    cams = {1: ColmapCamera(1, "SIMPLE_RADIAL", 32, 24, (30.0, 16.0, 12.0, -0.08))}
    ims = {1: ColmapImage(1, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1, "a.png")}
    write_colmap_model(folder, ColmapModel(cams, ims), binary=True)
    (tmp_path / "data" / "images").mkdir()
    write_png(tmp_path / "data" / "images" / "a.png", torch.zeros(3, 24, 32))
    (tmp_path / "renders" / "rgb").mkdir(parents=True)
    (tmp_path / "renders" / "depth").mkdir()
    r = _run("import-gsplat", tmp_path / "data", "--renders", tmp_path / "renders", "--output",
             tmp_path / "out")
    assert r.exit_code == 2, r.output
    assert "SIMPLE_RADIAL" in r.output and "colmap image_undistorter" in r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1


def test_load_scene_autodetects_a_colmap_dataset(toy_scene, tmp_path):
    from roguenerf.data.readers import load_scene

    _colmap_dataset(toy_scene, tmp_path, binary=True)
    scene = load_scene(tmp_path)
    assert scene.meta["format"] == "colmap"
    assert [f.name for f in scene.frames] == sorted(f.name for f in toy_scene.frames)
    assert {f.split for f in scene.frames} == {"train"}


@pytest.mark.parametrize("binary", [True, False])
def test_points_round_trip_and_pycolmap_reads_them(tmp_path, binary):
    import pycolmap

    rng = np.random.default_rng(1)
    xyz = rng.normal(size=(7, 3))
    rgb = rng.integers(0, 256, size=(7, 3)).astype(np.uint8)
    pose = torch.eye(4, dtype=torch.float64)
    K = torch.tensor([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]], dtype=torch.float64)
    write_colmap(tmp_path, names=["a.png"], K=K, world_from_cam=pose[None], widths=32, heights=24,
                 binary=binary, points_xyz=xyz, points_rgb=rgb)
    data = read_colmap(tmp_path, points=True, check_files=False)
    assert np.array_equal(data.points_xyz.numpy(), xyz)
    assert np.array_equal(data.points_rgb.numpy(), rgb)
    rec = pycolmap.Reconstruction(str(tmp_path))
    theirs = np.stack([rec.points3D[i].xyz for i in sorted(rec.points3D)])
    assert np.array_equal(theirs, xyz)


def test_colliding_stems_keep_their_folders(tmp_path):
    from roguenerf.data.colmap import view_names

    assert view_names(["b.png", "a.jpg"]) == ["b", "a"]
    assert view_names(["cam0/0001.jpg", "cam1/0001.jpg"]) == ["cam0_0001", "cam1_0001"]


def _camera_bin(*cams) -> bytes:
    """cameras.bin of PINHOLE cameras ``(id, fx)`` (32x24, centre 16, 12)."""
    out = [struct.pack("<Q", len(cams))]
    for cam_id, f in cams:
        out.append(struct.pack("<iiQQdddd", cam_id, 1, 32, 24, f, f, 16.0, 12.0))
    return b"".join(out)


def _images_bin(*images) -> bytes:
    """images.bin of identity poses ``(id, name)`` on camera 1, no keypoints."""
    out = [struct.pack("<Q", len(images))]
    for image_id, name in images:
        out.append(struct.pack("<idddddddi", image_id, 1, 0, 0, 0, 0, 0, 0, 1))
        out.append(name.encode() + b"\x00" + struct.pack("<Q", 0))
    return b"".join(out)


def test_binary_model_refuses_duplicate_ids_as_the_text_one(tmp_path):
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.bin").write_bytes(_camera_bin((1, 30.0)))
    (sparse / "images.bin").write_bytes(_images_bin((2, "a.png"), (3, "b.png")))
    assert read_colmap(tmp_path, check_files=False).names == ["a.png", "b.png"]
    # Two images of id 2: the first view would disappear in silence.
    (sparse / "images.bin").write_bytes(_images_bin((2, "a.png"), (2, "b.png")))
    with pytest.raises(SceneFormatError) as err:
        read_colmap(tmp_path, check_files=False)
    assert str(err.value) == f"{sparse / 'images.bin'}: image 1: image id 2 appears twice"
    # Two cameras of id 1: which focal length is meant?
    (sparse / "images.bin").write_bytes(_images_bin((2, "a.png")))
    (sparse / "cameras.bin").write_bytes(_camera_bin((1, 30.0), (1, 60.0)))
    with pytest.raises(SceneFormatError) as err:
        read_colmap(tmp_path, check_files=False)
    assert str(err.value) == f"{sparse / 'cameras.bin'}: camera 1: camera id 1 appears twice"
    # The text reader says the same of cameras.
    (sparse / "cameras.bin").unlink()
    (sparse / "images.bin").unlink()
    (sparse / "cameras.txt").write_text("1 PINHOLE 32 24 30 30 16 12\n1 PINHOLE 32 24 60 60 16 12\n")
    (sparse / "images.txt").write_text("2 1 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(SceneFormatError) as err:
        read_colmap(tmp_path, check_files=False)
    assert str(err.value) == f"{sparse / 'cameras.txt'}: line 2: camera id 1 appears twice"


def test_points_bin_count_beyond_the_file_is_refused(tmp_path):
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.bin").write_bytes(_camera_bin((1, 30.0)))
    (sparse / "images.bin").write_bytes(_images_bin((2, "a.png")))
    point = struct.pack("<QdddBBBdQ", 1, 0.5, 0.25, 2.0, 1, 2, 3, 0.0, 0)
    (sparse / "points3D.bin").write_bytes(struct.pack("<Q", 1) + point)
    data = read_colmap(tmp_path, points=True, check_files=False)
    assert data.points_xyz.tolist() == [[0.5, 0.25, 2.0]]
    (sparse / "points3D.bin").write_bytes(struct.pack("<Q", 2**62) + point)
    with pytest.raises(SceneFormatError) as err:
        read_colmap(tmp_path, points=True, check_files=False)
    assert str(err.value) == (
        f"{sparse / 'points3D.bin'}: the header claims {2**62} points, but the file's 51 bytes "
        f"after it hold at most 1 (51 bytes each): the file is truncated or not a COLMAP points3D.bin"
    )


def _write_one(folder, **changes):
    args = dict(
        names=["a.png", "b.png"],
        K=torch.tensor([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]], dtype=torch.float64),
        world_from_cam=torch.eye(4, dtype=torch.float64).repeat(2, 1, 1),
        widths=32,
        heights=24,
    )
    args.update(changes)
    return write_colmap(folder, **args)


@pytest.mark.parametrize("binary", [True, False])
def test_write_colmap_refuses_what_it_cannot_represent(tmp_path, binary):
    eye = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    mirrored = eye.clone()
    mirrored[1, 0, 0] = -1.0
    scaled = eye.clone()
    scaled[1, :3, :3] *= 2.0
    bottom = eye.clone()
    bottom[1, 3] = torch.tensor([0.0, 0.0, 0.5, 1.0])
    K = torch.tensor([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]], dtype=torch.float64)
    nan_K = K.clone()
    nan_K[0, 0] = math.nan
    negative_K = K.clone()
    negative_K[1, 1] = -30.0
    cases = [
        (dict(world_from_cam=mirrored), "world_from_cam[1]: expected a proper rotation (det +1), got det -1"),
        (dict(world_from_cam=scaled), "world_from_cam[1]: expected an orthonormal rotation"),
        (dict(world_from_cam=bottom), "world_from_cam[1]: expected bottom row (0, 0, 0, 1), got [0.0, 0.0, 0.5, 1.0]"),
        (dict(K=nan_K), "K: expected finite intrinsics, got non-finite values"),
        (dict(K=negative_K), "K: expected focal lengths fx > 0 and fy > 0, got fx=30, fy=-30 (min)"),
        (dict(widths=[32]), "widths: expected one width for all views or one per view (2), got 1"),
        (dict(heights=[24, 24, 24]), "heights: expected one height for all views or one per view (2), got 3"),
        (dict(widths=[32, 0]), "widths[1]: expected a positive integer size in pixels, got 0"),
        (dict(heights=24.5), "heights: expected a positive integer size in pixels, got 24.5"),
    ]
    for n, (change, message) in enumerate(cases):
        folder = tmp_path / f"case{n}" / "sparse" / "0"
        with pytest.raises(InputError) as err:
            _write_one(folder, binary=binary, **change)
        assert str(err.value).startswith(message), (change, str(err.value))
        assert not (tmp_path / f"case{n}").exists(), change  # nothing written
    # The good model still writes and reads back; the same pose within rounding of a rotation too.
    _write_one(tmp_path / "good", binary=binary, widths=[32, 32], heights=np.int64(24))
    data = read_colmap(tmp_path / "good", check_files=False)
    assert torch.equal(data.world_from_cam, torch.eye(4, dtype=torch.float64).repeat(2, 1, 1))
    assert data.widths == [32, 32] and data.heights == [24, 24]


def test_import_3dgs_and_import_gsplat_state_one_default_split():
    """Issue 49: import-3dgs held out every 8th view by default and import-gsplat none."""
    same = ("COLMAP dataset: every N-th view in name order is a test view, the split of the 3DGS and gsplat "
            "trainers' --eval (Inria's --eval, gsplat's default --test-every 8); 0: none, every view trains.")
    gsplat = " ".join(_run("import-gsplat", "--help").output.split())
    splats = " ".join(_run("import-3dgs", "--help").output.split())
    assert same in gsplat and same in splats
    assert "Default 8;" in gsplat and "[default: 8]" in splats
