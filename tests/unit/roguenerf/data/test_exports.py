"""nerfstudio and gsplat exports, in their exact file formats, load to the z-depth of our folder."""

from __future__ import annotations

import gzip
import io
import json
import math
import re
import shutil

import numpy as np
import pytest
import torch

from roguenerf.data.exports import DataparserTransform, import_renders, write_depth_like
from roguenerf.data.readers import load_scene
from roguenerf.data.toy import make_toy_scene
from roguenerf.errors import InputError, SceneFormatError
from roguenerf.geometry import opencv_to_opengl
from roguenerf.imageio import ImageTooLargeError, read_depth
from roguenerf.reprojection import reproject

H, W = 24, 32
SCALE = 0.37


def _rotation(axis, angle):
    axis = torch.tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    x, y, z = axis.tolist()
    Kx = torch.tensor([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx


PARSER = DataparserTransform(
    transform=torch.cat([_rotation((0.3, -1.0, 0.5), 0.7),
                         torch.tensor([[0.4], [-1.2], [2.0]], dtype=torch.float64)], 1),
    scale=SCALE)


def _ray_norm(K):
    u = torch.arange(W, dtype=torch.float64) + 0.5
    v = torch.arange(H, dtype=torch.float64) + 0.5
    x = (u[None, :] - K[0, 2]) / K[0, 0]
    y = (v[:, None] - K[1, 2]) / K[1, 1]
    return torch.sqrt(x * x + y * y + 1)


@pytest.fixture(scope="module")
def ours(tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp("ours") / "scene", seed=5, n_train=4, n_test=1,
                          height=H, width=W, kind="orbit")


def _nerfstudio_dataset(root, scene):
    """A nerfstudio dataset (transforms.json, images/) of the toy scene's photos and poses."""
    (root / "images").mkdir(parents=True)
    frames = []
    for f in scene.frames:
        shutil.copyfile(f.image_path, root / "images" / f"{f.name}.png")
        frames.append({"file_path": f"images/{f.name}.png",
                       "transform_matrix": opencv_to_opengl(f.world_from_cam).tolist()})
    K = scene.frames[0].K
    doc = {"camera_model": "OPENCV", "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]),
           "cy": float(K[1, 2]), "w": W, "h": H, "frames": frames,
           "train_filenames": [f"images/{f.name}.png" for f in scene.frames if f.split == "train"],
           "test_filenames": [f"images/{f.name}.png" for f in scene.frames if f.split == "test"]}
    (root / "transforms.json").write_text(json.dumps(doc))
    (root / "dataparser_transforms.json").write_text(json.dumps(
        {"transform": PARSER.transform.tolist(), "scale": SCALE}))


def _ns_render(out, scene, *, depth_type="ray", layout="nerfstudio", kind="npy.gz", background=None):
    """What `ns-render dataset --rendered-output-names rgb raw-depth` (or a gsplat script) writes."""
    for f in scene.frames:
        split = f.split if layout == "nerfstudio" else None
        base = out / split if split else out
        rgb_dir = base / "rgb"
        depth_dir = base / ("raw-depth" if layout == "nerfstudio" else "depth")
        rgb_dir.mkdir(parents=True, exist_ok=True)
        depth_dir.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f.render_path, rgb_dir / f"{f.name}.png")
        z = scene.depth(f.name)[0].double()
        depth = z * _ray_norm(f.K) if depth_type == "ray" else z
        # Rendered in the model's world (times the scale, float32), divided back by ns-render.
        depth = ((depth * SCALE).float() / SCALE).numpy()
        if background is not None:
            depth = depth.copy()
            depth[:3, :5] = background
        suffix = {"npy.gz": ".npy.gz", "npy": ".npy", "npz": ".npz", "png16": ".png", "tiff": ".tiff"}[kind]
        write_depth_like(depth_dir / f"{f.name}{suffix}", depth, kind=kind, scale=1e-3)


def test_nerfstudio_export_gives_the_folder_z_depth(ours, tmp_path):
    _nerfstudio_dataset(tmp_path / "ds", ours)
    _ns_render(tmp_path / "renders", ours)
    raw = read_depth(tmp_path / "renders" / "train" / "raw-depth" / f"{ours.frames[0].name}.npy.gz")
    assert raw.shape == (1, H, W)
    with gzip.open(tmp_path / "renders" / "train" / "raw-depth" / f"{ours.frames[0].name}.npy.gz") as fh:
        assert np.load(fh).shape == (H, W, 1)  # the exact nerfstudio layout
    scene = import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "out",
                           dataparser_transforms=tmp_path / "ds" / "dataparser_transforms.json")
    assert [f.name for f in scene.frames] == [f.name for f in ours.frames]
    assert [f.split for f in scene.frames] == [f.split for f in ours.frames]
    for f in ours.frames:
        torch.testing.assert_close(scene.depth(f.name), ours.depth(f.name), rtol=2e-6, atol=1e-6)
        torch.testing.assert_close(scene.poses([scene.index(f.name)])[0], f.world_from_cam, rtol=0, atol=1e-12)
        torch.testing.assert_close(scene.photo(f.name), ours.photo(f.name))
        torch.testing.assert_close(scene.render(f.name), ours.render(f.name))
    kept = DataparserTransform.read(tmp_path / "out" / "dataparser_transforms.json")
    assert kept.scale == SCALE and torch.equal(kept.transform, PARSER.transform)
    # Verified by reprojection: photo 0 seen from view 1 through the imported depth matches photo 1.
    a, b = 0, 1
    rp = reproject(scene.photo(a)[None], scene.depth(a)[None], scene.depth(b)[None], scene.frames[a].K,
                   scene.frames[b].K, scene.frames[a].world_from_cam, scene.frames[b].world_from_cam)
    valid = rp.valid[0, 0] > 0
    assert valid.float().mean() > 0.3
    err = (rp.features[0] - scene.photo(b)).abs().mean(0)[valid].mean()
    assert err < 0.05


def test_model_units_depth_and_wrong_inputs(ours, tmp_path):
    _nerfstudio_dataset(tmp_path / "ds", ours)
    _ns_render(tmp_path / "renders", ours)
    # Depth left in the model's world (older exports): times the scale; depth_units="model" undoes it.
    for path in (tmp_path / "renders").rglob("*.npy.gz"):
        depth = read_depth(path)[0].numpy() * SCALE
        write_depth_like(path, depth, kind="npy.gz")
    scene = import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "out", depth_units="model",
                           dataparser_transforms=tmp_path / "ds" / "dataparser_transforms.json")
    torch.testing.assert_close(scene.depth(0), ours.depth(0), rtol=1e-5, atol=1e-6)
    with pytest.raises(InputError, match="dataparser"):
        import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "o2", depth_units="model")
    with pytest.raises(InputError, match="render folder"):
        import_renders(tmp_path / "ds", tmp_path / "ds", tmp_path / "o3")


@pytest.mark.parametrize("kind,tol,depth_type", [
    (kind, 1e-5, depth_type) for kind in ("npy", "npz", "tiff", "npy.gz") for depth_type in ("z", "ray")
] + [("png16", 6e-4, "z")])  # one 16-bit PNG case (millimetre quantisation) is enough
def test_gsplat_export_formats_give_the_folder_z_depth(ours, tmp_path, kind, tol, depth_type):
    _nerfstudio_dataset(tmp_path / "ds", ours)
    no_splat = 65535 * 1e-3 if kind == "png16" else 1e4  # the map's maximum where no splat is
    _ns_render(tmp_path / "renders", ours, depth_type=depth_type, layout="flat", kind=kind, background=no_splat)
    scene = import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "out", tool="gsplat",
                           depth_type=depth_type, depth_scale=1e-3 if kind == "png16" else 1.0)
    for f in ours.frames:
        got, want = scene.depth(f.name), ours.depth(f.name)
        assert (got[0, :3, :5] == 0).all(), "no-splat pixels must be unknown"
        keep = torch.ones_like(want, dtype=torch.bool)
        keep[0, :3, :5] = False
        torch.testing.assert_close(got[keep], want[keep], rtol=tol, atol=tol)
    assert [f.split for f in scene.frames] == [f.split for f in ours.frames]


def test_dataparser_transform_round_trip(ours):
    poses = ours.poses()
    model = PARSER.to_model(poses)
    assert not torch.allclose(model, poses)
    torch.testing.assert_close(PARSER.to_dataset(model), poses, rtol=0, atol=1e-12)
    # Distances scale by the dataparser's scale, rotations stay rotations.
    d0 = (poses[0, :3, 3] - poses[1, :3, 3]).norm()
    d1 = (model[0, :3, 3] - model[1, :3, 3]).norm()
    assert abs(d1 / d0 - SCALE) < 1e-12


def test_read_depth_formats_and_refusals(tmp_path):
    depth = np.random.default_rng(0).uniform(1, 5, (H, W)).astype(np.float32)
    for kind, suffix in (("npy.gz", ".npy.gz"), ("npz", ".npz"), ("tiff", ".tif")):
        path = write_depth_like(tmp_path / f"d{suffix}", depth, kind=kind)
        np.testing.assert_array_equal(read_depth(path)[0].numpy(), depth)
    # A gzip bomb: a tiny file that would inflate past the size limit is refused early.
    buf = io.BytesIO()
    np.save(buf, np.zeros((1000, 1000), np.float64))
    bomb = gzip.compress(buf.getvalue())
    with pytest.raises(ImageTooLargeError):
        read_depth(bomb, max_pixels=10_000)
    with pytest.raises(InputError, match="OpenEXR"):
        read_depth(b"\x76\x2f\x31\x01" + b"\x00" * 20)
    with pytest.raises(InputError, match="corrupt gzip|truncated gzip"):
        read_depth(gzip.compress(buf.getvalue())[:100])
    with pytest.raises(SceneFormatError, match="rotation"):
        bad = tmp_path / "dp.json"
        bad.write_text(json.dumps({"transform": [[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0]], "scale": 1}))
        DataparserTransform.read(bad)


def test_import_cli(ours, tmp_path):
    from typer.testing import CliRunner

    from roguecli import app

    _nerfstudio_dataset(tmp_path / "ds", ours)
    _ns_render(tmp_path / "renders", ours)
    runner = CliRunner()
    r = runner.invoke(app, ["import-nerfstudio", str(tmp_path / "ds"), "--renders", str(tmp_path / "renders"),
                            "--output", str(tmp_path / "out"), "--dataparser-transforms",
                            str(tmp_path / "ds" / "dataparser_transforms.json")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "out" / "dataparser_transforms.json").is_file()
    bad = runner.invoke(app, ["import-gsplat", str(tmp_path / "nope"), "--renders", str(tmp_path / "renders"),
                              "--output", str(tmp_path / "o2")])
    assert bad.exit_code == 2 and "does not exist" in bad.output and "Traceback" not in bad.output
    bad = runner.invoke(app, ["import-nerfstudio", str(tmp_path / "ds"), "--renders", str(tmp_path / "renders"),
                              "--output", str(tmp_path / "o3"), "--depth-type", "zz"])
    assert bad.exit_code == 2 and "--depth-type" in bad.output


# --- issue 38: missing files, atomic imports, the depth type checked by multi-view consistency --------


def test_a_missing_depth_file_is_refused_with_its_name(ours, tmp_path):
    from typer.testing import CliRunner

    from roguecli import app

    _nerfstudio_dataset(tmp_path / "ds", ours)
    _ns_render(tmp_path / "renders", ours)
    gone = ours.frames[2]
    missing = tmp_path / "renders" / gone.split / "raw-depth" / f"{gone.name}.npy.gz"
    missing.unlink()
    expected = rf"1 of 5 views .*lack a file: missing {gone.name}: {re.escape(str(missing))}"
    with pytest.raises(InputError, match=expected + r"\. Render them, or pass skip_missing=True to import"):
        import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "out")
    assert not (tmp_path / "out").exists()
    args = ["import-nerfstudio", str(tmp_path / "ds"), "--renders", str(tmp_path / "renders"),
            "--output", str(tmp_path / "cli")]
    refused = CliRunner().invoke(app, args)
    assert refused.exit_code == 2 and f"{gone.name}.npy.gz" in refused.output
    assert "Render them, or pass --skip-missing to import" in refused.output  # the flag, not the keyword
    assert "skip_missing=True" not in refused.output
    assert not (tmp_path / "cli").exists()
    # --skip-missing imports the others and says which it skipped.
    done = CliRunner().invoke(app, [*args, "--skip-missing"])
    assert done.exit_code == 0, done.output
    assert f"warning: skipped 1 views without a render or depth: {gone.name}" in done.output
    scene = load_scene(tmp_path / "cli")
    assert [f.name for f in scene.frames] == [f.name for f in ours.frames if f.name != gone.name]
    assert json.loads((tmp_path / "cli" / "transforms.json").read_text())["source"]["skipped"] == [gone.name]


def test_a_failed_import_leaves_no_folder_and_keeps_an_earlier_import(ours, tmp_path):
    _nerfstudio_dataset(tmp_path / "ds", ours)
    _ns_render(tmp_path / "renders", ours)
    last = ours.frames[-1]
    bad = tmp_path / "renders" / last.split / "raw-depth" / f"{last.name}.npy.gz"
    good = bad.read_bytes()
    transposed = read_depth(bad)[0].numpy().T.copy()
    write_depth_like(bad, transposed, kind="npy.gz")  # the user's transposed depth, last view
    for check_depth in (True, False):  # refused up front, or half-way through the views
        with pytest.raises(InputError, match=rf"depth is {H}x{W}, its render .* is {W}x{H}"):
            import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "out", check_depth=check_depth)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "renders"]  # no folder, no temp folder
    # An earlier import is replaced only by a finished one.
    bad.write_bytes(good)
    import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "out")
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "out").rglob("*")}
    write_depth_like(bad, transposed, kind="npy.gz")
    with pytest.raises(InputError):
        import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "out", check_depth=False)
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "out").rglob("*")} == before
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "other")
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


def test_an_import_never_replaces_a_dataset_or_deletes_a_file_it_did_not_write(ours, tmp_path):
    """Issue 49: a dataset given as --output (a transforms.json of its own) is refused; an earlier
    import is replaced, but not when it holds a file the import did not write."""
    from typer.testing import CliRunner

    from roguecli import app

    _nerfstudio_dataset(tmp_path / "ds", ours)
    _ns_render(tmp_path / "renders", ours)

    def tree(folder):
        return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}

    args = ["import-nerfstudio", str(tmp_path / "ds"), "--renders", str(tmp_path / "renders"), "--output"]
    before = tree(tmp_path / "ds")
    refused = CliRunner().invoke(app, [*args, str(tmp_path / "ds")])
    assert refused.exit_code == 2 and refused.output.strip().splitlines() == [
        f"error: output: {tmp_path / 'ds'} exists and is not empty: it holds other files, not an earlier output "
        "of this command (which would be replaced); choose a new folder"]
    assert tree(tmp_path / "ds") == before
    out = tmp_path / "out"
    assert CliRunner().invoke(app, [*args, str(out)]).exit_code == 0
    assert CliRunner().invoke(app, [*args, str(out)]).exit_code == 0  # an earlier import: replaced
    (out / "depths" / "mine.npy").write_bytes(b"mine")
    before = tree(out)
    refused = CliRunner().invoke(app, [*args, str(out)])
    assert refused.exit_code == 2 and refused.output.strip().splitlines() == [
        f"error: output: {out} is an earlier output of this command but also holds files it did not write "
        "(depths/mine.npy), which replacing it would delete; move them out or choose a new folder"]
    assert tree(out) == before


@pytest.mark.parametrize("stored, given", [("z", "ray"), ("ray", "z")])
def test_a_depth_type_that_disagrees_with_the_scene_is_found_by_multi_view_consistency(ours, tmp_path, stored,
                                                                                        given):
    from typer.testing import CliRunner

    from roguecli import app
    from roguenerf.data.exports import _depth_type_views, _render_inventory, check_depth_type

    _nerfstudio_dataset(tmp_path / "ds", ours)
    _ns_render(tmp_path / "renders", ours, depth_type=stored)
    # Known answers on exact toy depth: the stored type agrees to resampling error, the other
    # is off by the ray-length factor's change between neighbouring views (~1 %).
    found = _render_inventory(tmp_path / "renders")[0]
    source = load_scene(tmp_path / "ds", check_files=False)
    check = check_depth_type(_depth_type_views(source, source.frames, found, 1.0, "zero"))
    assert check.likely == stored and check.pixels > 1000
    assert check.errors[stored] < 1e-3 and check.errors[given] > 5e-3
    assert abs(check.beta - (0.0 if stored == "z" else 1.0)) < 0.25 and check.beta_se < 0.05
    with pytest.raises(InputError, match=rf"not --depth-type {given}.*Likely fix: --depth-type {stored}"):
        import_renders(tmp_path / "ds", tmp_path / "renders", tmp_path / "out", depth_type=given)
    assert not (tmp_path / "out").exists()
    args = ["import-nerfstudio", str(tmp_path / "ds"), "--renders", str(tmp_path / "renders"), "--output",
            str(tmp_path / "cli"), "--depth-type"]
    refused = CliRunner().invoke(app, [*args, given])
    assert refused.exit_code == 2 and f"--depth-type {stored}" in refused.output
    assert refused.output.strip().endswith("to import them as given anyway: --force")
    assert CliRunner().invoke(app, [*args, stored]).exit_code == 0
    scene = load_scene(tmp_path / "cli")
    torch.testing.assert_close(scene.depth(0), ours.depth(0), rtol=2e-6, atol=1e-6)
    forced = CliRunner().invoke(app, [*args, given, "--force"])  # replaces the earlier import, as told
    assert forced.exit_code == 0, forced.output
    assert not torch.allclose(load_scene(tmp_path / "cli").depth(0), ours.depth(0), rtol=1e-3)


def test_the_depth_type_check_on_a_real_fields_depth(lego_dir):
    """lego's grid-field z-depth (2 % noise, 40 deg field of view): stored as ray distance it is
    found (the fit of the ray-distance signature); its true z-depth is left undecided, never
    called ray (undecided never refuses)."""
    from roguenerf.data.exports import check_depth_type
    from roguenerf.geometry import ray_to_z_depth

    scene = load_scene(lego_dir)
    train = scene.indices("train")
    positions = scene.poses(train)[:, :3, 3]

    def pairs(kind):
        out = []
        for p in range(0, 6 * 17, 17):
            d = (positions - positions[p]).norm(dim=-1)
            d[p] = float("inf")
            q = int(d.argmin())
            views = []
            for k in (p, q):
                frame = scene.frames[train[k]]
                z = scene.depth(train[k]).double()
                n = 1 / ray_to_z_depth(torch.ones_like(z), frame.K)  # the ray-length factor
                views.append((z if kind == "z" else z * n, frame.K, frame.world_from_cam))
            out.append(tuple(views))
        return out

    as_ray = check_depth_type(pairs("ray"))
    assert as_ray.likely == "ray" and abs(as_ray.beta - 1) < 0.3, as_ray
    as_z = check_depth_type(pairs("z"))
    assert as_z.likely != "ray", as_z
