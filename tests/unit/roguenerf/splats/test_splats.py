"""3D Gaussian splats: the Inria ``.ply``, spherical harmonics and the CPU rasterizer, against
answers worked out independently (a brute-force per-pixel renderer written plainly below)."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
import torch

from roguenerf.errors import InputError
from roguenerf.splats import Gaussians, eval_sh, logit, read_ply, render, sh_basis, write_ply
from roguenerf.splats.sh import C0


def random_gaussians(n: int, degree: int = 3, seed: int = 0, dtype=torch.float32) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    means = torch.rand(n, 3, generator=g) * torch.tensor([3.0, 2.4, 3.0]) - torch.tensor([1.5, 1.2, -0.5])
    means[: n // 20, 2] = torch.rand(n // 20, generator=g) * 0.5 - 0.45  # some behind or at the near plane
    return Gaussians(
        means=means.to(dtype),
        sh=(torch.randn(n, k, 3, generator=g) * 0.4).to(dtype),
        opacity=logit(torch.rand(n, generator=g) * 0.93 + 0.02).to(dtype),
        log_scales=torch.log(torch.rand(n, 3, generator=g) * 0.12 + 0.005).to(dtype),
        quats=torch.randn(n, 4, generator=g).to(dtype),
    )


def camera(width=56, height=40):
    K = torch.tensor([[48.0, 0, width / 2 + 1.3], [0, 47.0, height / 2 - 0.7], [0, 0, 1]], dtype=torch.float64)
    angle = math.radians(8)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0],
                                 [-math.sin(angle), 0, math.cos(angle)]], dtype=torch.float64)
    pose[:3, 3] = torch.tensor([0.1, -0.05, -0.2], dtype=torch.float64)
    return pose, K


def brute_force(g: Gaussians, pose, K, height, width, background=(0.0, 0.0, 0.0), near=0.01):
    """Every pixel, every Gaussian, in the order of camera z: the 3DGS image formation, plainly."""
    R_cw = pose[:3, :3].T.double()
    t_cw = -R_cw @ pose[:3, 3].double()
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    splats = []
    for i in range(len(g)):
        p = R_cw @ g.means[i].double() + t_cw
        x, y, z = (float(v) for v in p)
        if z <= near:
            continue
        w_, a, b, c = (float(v) for v in g.quats[i].double() / g.quats[i].double().norm())
        rot = torch.tensor([[1 - 2 * (b * b + c * c), 2 * (a * b - w_ * c), 2 * (a * c + w_ * b)],
                            [2 * (a * b + w_ * c), 1 - 2 * (a * a + c * c), 2 * (b * c - w_ * a)],
                            [2 * (a * c - w_ * b), 2 * (b * c + w_ * a), 1 - 2 * (a * a + b * b)]], dtype=torch.float64)
        s = torch.exp(g.log_scales[i].double())
        cov3 = rot @ torch.diag(s * s) @ rot.T
        tan_fovx, tan_fovy = width / (2 * fx), height / (2 * fy)  # gsplat's clamp: 0.3 tan(fov/2) past the edges
        limx_pos, limx_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
        limy_pos, limy_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
        tx = z * min(max(x / z, -limx_neg), limx_pos)
        ty = z * min(max(y / z, -limy_neg), limy_pos)
        J = torch.tensor([[fx / z, 0, -fx * tx / z ** 2], [0, fy / z, -fy * ty / z ** 2]], dtype=torch.float64)
        cov2 = J @ R_cw @ cov3 @ R_cw.T @ J.T + 0.3 * torch.eye(2, dtype=torch.float64)
        conic = torch.linalg.inv(cov2)
        direction = g.means[i].double() - pose[:3, 3].double()
        colour = eval_sh(g.sh[i:i + 1].double(), direction[None])[0]
        opacity = 1 / (1 + math.exp(-float(g.opacity[i])))
        splats.append((z, fx * x / z + cx, fy * y / z + cy, float(conic[0, 0]), float(conic[0, 1]),
                       float(conic[1, 1]), opacity, [float(v) for v in colour]))
    splats.sort(key=lambda s: s[0])
    rgb = np.zeros((3, height, width))
    depth = np.zeros((1, height, width))
    acc = np.zeros((1, height, width))
    for v in range(height):
        for u in range(width):
            px, py = u + 0.5, v + 0.5
            T, col, wz, ws = 1.0, [0.0, 0.0, 0.0], 0.0, 0.0
            for z, mu, mv, ca, cb, cc, o, colour in splats:
                dx, dy = px - mu, py - mv
                maha = ca * dx * dx + 2 * cb * dx * dy + cc * dy * dy
                if maha > 9:
                    continue
                alpha = min(0.99, o * math.exp(-0.5 * maha))
                if alpha < 1 / 255:
                    continue
                if T * (1 - alpha) < 1e-4:
                    break
                for ch in range(3):
                    col[ch] += alpha * T * colour[ch]
                wz += alpha * T * z
                ws += alpha * T
                T *= 1 - alpha
            for ch in range(3):
                rgb[ch, v, u] = col[ch] + T * background[ch]
            acc[0, v, u] = ws
            depth[0, v, u] = wz / ws if ws >= 0.5 else 0.0
    return torch.from_numpy(rgb), torch.from_numpy(depth), torch.from_numpy(acc)


def test_one_opaque_gaussian_renders_its_sh_colour_and_depth():
    sh = torch.tensor([[[0.9, -0.3, 0.2], [0.4, 0.1, -0.2], [0.0, 0.5, 0.1], [0.3, 0.3, -0.6]]])
    g = Gaussians(means=torch.tensor([[0.2, -0.1, 3.0]]), sh=sh, opacity=torch.tensor([logit(0.9999)]),
                  log_scales=torch.log(torch.tensor([[0.4, 0.3, 0.02]])), quats=torch.tensor([[1.0, 0, 0, 0]]))
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 3] = torch.tensor([0.2, -0.1, 0.0], dtype=torch.float64)  # the centre pixel looks at it
    K = torch.tensor([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]], dtype=torch.float64)
    rgb, depth, opacity = render(g, pose, K, 48, 64)
    # Seen straight on (direction +z): Y00 = C0, Y1,-1 = -C1 y = 0, Y10 = C1 z = C1, Y11 = -C1 x = 0.
    expected = (sh[0, 0] * C0 + sh[0, 2] * 0.4886025119029199 + 0.5).clamp_min(0) * 0.99
    centre = rgb[:, 23:25, 31:33].mean((1, 2))
    assert torch.allclose(centre, expected, atol=2e-3), (centre, expected)
    assert abs(float(depth[0, 24, 32]) - 3.0) < 0.03
    assert abs(float(opacity[0, 24, 32]) - 0.99) < 1e-4
    assert float(opacity[0, 0, 0]) == 0.0 and float(depth[0, 0, 0]) == 0.0  # nothing there: unknown depth


@pytest.mark.parametrize("degree", [0, 3])
def test_random_gaussians_match_a_brute_force_renderer(degree):
    g = random_gaussians(300, degree=degree, seed=degree)
    pose, K = camera()
    background = (0.2, 0.5, 0.9)
    rgb, depth, acc = render(g, pose, K, 40, 56, background=background)
    ref_rgb, ref_depth, ref_acc = brute_force(g, pose, K, 40, 56, background=background)
    assert float(ref_acc.max()) > 0.95 and float((ref_acc < 0.5).float().mean()) > 0.02  # a real test
    assert (rgb.double() - ref_rgb).abs().max() < 1e-4
    assert (acc.double() - ref_acc).abs().max() < 1e-4
    assert ((depth.double() == 0) == (ref_depth == 0)).all()
    assert (depth.double() - ref_depth).abs().max() < 1e-4 * float(ref_depth.max())
    # Tile size, slices and chunks change how the work is cut, never the answer.
    small = render(g, pose, K, 40, 56, background=background, tile=8, chunk=50, group=3)
    for a, b in zip(small, (rgb, depth, acc), strict=True):
        assert (a - b).abs().max() < 2e-6


def test_many_gaussians_saturate_and_stop_early_as_the_reference_does():
    g = random_gaussians(250, degree=1, seed=5)
    g.opacity = logit(torch.full((250,), 0.95))  # opaque: transmittance falls below 1e-4 often
    g.log_scales = g.log_scales + 1.0
    pose, K = camera(24, 20)
    rgb, depth, acc = render(g, pose, K, 20, 24, group=4)  # small groups: whole tiles saturate and stop early
    ref_rgb, ref_depth, ref_acc = brute_force(g, pose, K, 20, 24)
    assert float(ref_acc.min()) > 0.99  # saturated everywhere: the early stop decides each pixel
    assert (rgb.double() - ref_rgb).abs().max() < 1e-4
    assert (depth.double() - ref_depth).abs().max() < 1e-4 * float(ref_depth.max())


def test_the_render_is_differentiable():
    g = random_gaussians(6, degree=1, seed=2, dtype=torch.float64)
    g.means = g.means * 0.3 + torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)
    g.log_scales = g.log_scales + 1.5
    pose, K = camera(12, 10)
    params = [g.means, g.sh, g.opacity, g.log_scales, g.quats]
    for p in params:
        p.requires_grad_(True)

    def f(means, sh, opacity, log_scales, quats):
        rgb, depth, acc = render(Gaussians(means, sh, opacity, log_scales, quats), pose, K, 10, 12,
                                 depth_threshold=0.0)
        return rgb.sum() + 0.1 * (depth * acc).sum()

    assert torch.autograd.gradcheck(f, params, eps=1e-6, atol=1e-4, rtol=1e-3)
    rgb, _, _, info = render(Gaussians(*params), pose, K, 10, 12, return_info=True)
    rgb.sum().backward()
    assert info["means2d"].grad is not None and info["means2d"].grad[info["visible"]].abs().sum() > 0


def legendre(l_: int, m: int, x: float) -> float:
    """Associated Legendre P_l^m(x) with the Condon-Shortley phase (recurrence in l)."""
    pmm = (-1) ** m * math.prod(range(1, 2 * m, 2)) * (1 - x * x) ** (m / 2)
    if l_ == m:
        return pmm
    pm1 = x * (2 * m + 1) * pmm
    for ll in range(m + 2, l_ + 1):
        pmm, pm1 = pm1, ((2 * ll - 1) * x * pm1 - (ll + m - 1) * pmm) / (ll - m)
    return pm1


def real_sh(l_: int, m: int, theta: float, phi: float) -> float:
    k = math.sqrt((2 * l_ + 1) / (4 * math.pi) * math.factorial(l_ - abs(m)) / math.factorial(l_ + abs(m)))
    p = legendre(l_, abs(m), math.cos(theta))
    if m > 0:
        return math.sqrt(2) * k * math.cos(m * phi) * p
    if m < 0:
        return math.sqrt(2) * k * math.sin(-m * phi) * p
    return k * p


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_matches_a_direct_evaluation(degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(40, 3, generator=g, dtype=torch.float64)
    coeffs = torch.randn(40, (degree + 1) ** 2, 3, generator=g, dtype=torch.float64)
    colour = eval_sh(coeffs, dirs * 3.7)  # not unit: normalised inside
    basis = sh_basis(degree, dirs / dirs.norm(dim=-1, keepdim=True))
    for n in range(40):
        x, y, z = (float(v) for v in dirs[n] / dirs[n].norm())
        theta, phi = math.acos(z), math.atan2(y, x)
        direct = [real_sh(l_, m, theta, phi) for l_ in range(degree + 1) for m in range(-l_, l_ + 1)]
        assert np.allclose(basis[n].numpy(), direct, atol=1e-12)
        want = (torch.tensor(direct, dtype=torch.float64)[:, None] * coeffs[n]).sum(0) + 0.5
        assert torch.allclose(colour[n], want.clamp_min(0), atol=1e-12)
    # A lower degree uses the first coefficients only.
    if degree == 3:
        low = eval_sh(coeffs, dirs, degree=1)
        assert torch.allclose(low, eval_sh(coeffs[:, :4], dirs))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_round_trip(tmp_path, degree):
    g = random_gaussians(37, degree=degree, seed=1)
    path = write_ply(tmp_path / "point_cloud.ply", g, normals=degree % 2 == 0)
    back = read_ply(path)
    assert back.sh_degree == degree and len(back) == 37
    for name in ("means", "sh", "opacity", "log_scales", "quats"):
        assert torch.equal(getattr(back, name), getattr(g, name)), name


def write_raw_ply(path, names, rows, *, fmt="binary_little_endian", extra_header=""):
    header = f"ply\nformat {fmt} 1.0\n{extra_header}element vertex {len(rows)}\n"
    header += "".join(f"property float {n}\n" for n in names) + "end_header\n"
    body = b"".join(struct.pack("<" + "f" * len(names), *row) for row in rows)
    path.write_bytes(header.encode() + body)
    return path


def test_ply_reads_inria_channel_major_layout(tmp_path):
    """f_rest_0..8 are red's three degree-1 coefficients, then green's, then blue's."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(9)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    row = [1, 2, 3, 0, 0, 0, 10, 20, 30] + [11, 12, 13, 21, 22, 23, 31, 32, 33] + [0.5, -1, -2, -3, 1, 0, 0, 0]
    g = read_ply(write_raw_ply(tmp_path / "a.ply", names, [row]))
    assert g.sh[0].tolist() == [[10, 20, 30], [11, 21, 31], [12, 22, 32], [13, 23, 33]]
    assert g.means[0].tolist() == [1, 2, 3] and g.opacity.tolist() == [0.5]
    assert g.log_scales[0].tolist() == [-1, -2, -3] and g.quats[0].tolist() == [1, 0, 0, 0]


BASE = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3"]


@pytest.mark.parametrize("case, message", [
    ("missing", "opacity"),
    ("ascii", "binary_little_endian"),
    ("not_ply", "not a PLY file"),
    ("truncated", "truncated"),
    ("rest7", "f_rest"),
    ("nan", "NaN"),
    ("no_end", "end_header"),
    ("zero_quat", "zero"),
    ("absent", "not found"),
    ("empty", "no Gaussians"),
])
def test_malformed_ply_is_refused(tmp_path, case, message):
    path = tmp_path / "bad.ply"
    row = [0, 0, 1, 0.1, 0.2, 0.3, 0.0, -2, -2, -2, 1, 0, 0, 0]
    if case == "missing":
        write_raw_ply(path, [n for n in BASE if n != "opacity"], [row[:6] + row[7:]])
    elif case == "ascii":
        write_raw_ply(path, BASE, [row], fmt="ascii")
    elif case == "not_ply":
        path.write_bytes(b"\x89PNG\r\n")
    elif case == "truncated":
        write_raw_ply(path, BASE, [row, row])
        path.write_bytes(path.read_bytes()[:-5])
    elif case == "rest7":
        write_raw_ply(path, BASE + [f"f_rest_{i}" for i in range(7)], [row + [0] * 7])
    elif case == "nan":
        write_raw_ply(path, BASE, [row[:6] + [float("nan")] + row[7:]])
    elif case == "no_end":
        path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n")
    elif case == "zero_quat":
        write_raw_ply(path, BASE, [row[:10] + [0, 0, 0, 0]])
    elif case == "empty":
        write_raw_ply(path, BASE, [])
    with pytest.raises(InputError, match=message):
        read_ply(path)


def test_gaussians_refuse_bad_shapes():
    g = random_gaussians(4, degree=1)
    with pytest.raises(InputError, match="sh"):
        Gaussians(g.means, g.sh[:, :3], g.opacity, g.log_scales, g.quats)
    with pytest.raises(InputError, match="quats"):
        Gaussians(g.means, g.sh, g.opacity, g.log_scales, g.quats[:, :3])


def test_ply_count_beyond_the_file_is_refused_before_reading(tmp_path):
    """A header claiming ten billion vertices: an InputError naming the counts, not MemoryError."""
    row = [0, 0, 1, 0.1, 0.2, 0.3, 0.0, -2, -2, -2, 1, 0, 0, 0]
    path = write_raw_ply(tmp_path / "big.ply", BASE, [row, row])
    path.write_bytes(path.read_bytes().replace(b"element vertex 2\n", b"element vertex 10000000000\n"))
    with pytest.raises(InputError) as err:
        read_ply(path)
    assert str(err.value) == (f"{path}: file is truncated: the header claims 10000000000 vertices of 56 bytes "
                              "(560000000000 bytes), the file holds 112 after the header")
    # The CLI: one line, exit status 2.
    from typer.testing import CliRunner

    from roguecli import app
    from roguenerf.data.colmap import write_colmap
    from roguenerf.imageio import write_png

    data = tmp_path / "data"
    (data / "images").mkdir(parents=True)
    write_png(data / "images" / "a.png", torch.zeros(3, 24, 32))
    pose, K = camera(32, 24)
    write_colmap(data / "sparse" / "0", names=["a.png"], K=K, world_from_cam=pose[None], widths=32, heights=24)
    result = CliRunner().invoke(app, ["import-3dgs", str(data), "--ply", str(path), "--output", str(tmp_path / "o"),
                                      "--backend", "cpu"])
    assert result.exit_code == 2, result.output
    assert "10000000000 vertices" in result.output and "MemoryError" not in result.output
    # Two vertices the header claims and the file holds are read.
    path.write_bytes(path.read_bytes().replace(b"element vertex 10000000000\n", b"element vertex 2\n"))
    assert len(read_ply(path)) == 2


def one_gaussian(mean, log_scales, quat=(1.0, 0.0, 0.0, 0.0), opacity=0.8, dc=(0.6, -0.2, 0.1)):
    return Gaussians(means=torch.tensor([mean]), sh=torch.tensor([[dc]]), opacity=torch.tensor([logit(opacity)]),
                     log_scales=torch.tensor([log_scales]), quats=torch.tensor([quat]))


def test_off_screen_centres_are_clamped_to_1_3_times_the_field_of_view():
    """3DGS: ``limx = 1.3 tan_fovx`` (centred ``cx``); gsplat: ``(W - cx)/fx + 0.3 tan_fovx``;
    ``tan_fovx = W/(2 fx)``."""
    from roguenerf.splats import project

    W, H, f, z, s = 64, 48, 50.0, 4.0, 0.5
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=torch.float64)
    pose = torch.eye(4, dtype=torch.float64)
    # Far to the right (x/z = 2 > 1.3 W/(2f) = 0.832): J is taken at x/z = 0.832.
    g = one_gaussian([2.0 * z, 0.0, z], [math.log(s)] * 3, opacity=0.99)
    proj = project(g, pose, K, H, W)
    lim = 1.3 * W / (2 * f)
    assert lim == pytest.approx(0.832)
    cxx = (f / z) ** 2 * s * s * (1 + lim * lim) + 0.3  # J = [[f/z, 0, -f lim/z], [0, f/z, 0]], Σ = s² I
    cyy = (f / z) ** 2 * s * s + 0.3
    assert proj.cov2d[0].tolist() == pytest.approx([cxx, 0.0, cyy], rel=1e-6, abs=1e-6)
    # Its footprint reaches the image's right edge: the edge pixels' α is that of this conic.
    g = one_gaussian([0.95 * z, 0.0, z], [math.log(1.2)] * 3, opacity=0.9, dc=(0.5 / C0, 0.0, 0.0))
    rgb, _, acc = render(g, pose, K, H, W)
    u0 = f * 0.95 + W / 2  # the centre, off the image (u = 79.5)
    lim_y = 1.3 * H / (2 * f)
    assert lim < 0.95 and lim_y > 0
    a = (f / z) ** 2 * 1.44 * (1 + lim * lim) + 0.3
    c = (f / z) ** 2 * 1.44 + 0.3
    for v in (0, 20, 24, 47):
        dx, dy = W - 0.5 - u0, v + 0.5 - H / 2
        maha = dx * dx / a + dy * dy / c
        alpha = min(0.99, 0.9 * math.exp(-0.5 * maha))
        assert maha <= 9 and alpha >= 1 / 255
        assert float(acc[0, v, W - 1]) == pytest.approx(alpha, rel=1e-5), v
        assert float(rgb[0, v, W - 1]) == pytest.approx(alpha * 1.0, rel=1e-5), v


def test_render_refuses_what_it_would_draw_wrongly():
    g = random_gaussians(20, degree=1, seed=4)
    pose, K = camera(16, 12)
    mirrored = pose.clone()
    mirrored[:3, 0] *= -1
    scaled = pose.clone()
    scaled[:3, :3] *= 2.0
    bad_sh = Gaussians(g.means, g.sh.clone(), g.opacity, g.log_scales, g.quats)
    bad_sh.sh[3, 1, 2] = float("inf")
    cases = [
        (dict(world_from_cam=mirrored), "world_from_cam: expected a proper rotation (det +1), got det -1"),
        (dict(world_from_cam=scaled), "world_from_cam: expected an orthonormal rotation"),
        (dict(gaussians=bad_sh), "gaussians: sh holds NaN or infinite values"),
        (dict(near=float("nan")), "near: expected a finite distance >= 0 (centres at camera z <= near are culled), "
                                  "got nan"),
        (dict(near=-1.0), "near: expected a finite distance >= 0 (centres at camera z <= near are culled), got -1.0"),
        (dict(background=(float("nan"), 0.0, 0.0)), "background: expected 3 finite values (RGB), got [nan, 0.0, 0.0]"),
        (dict(background=(0.0, 1.0)), "background: expected 3 finite values (RGB), got [0.0, 1.0]"),
    ]
    for change, message in cases:
        args = dict(gaussians=g, world_from_cam=pose, K=K, height=12, width=16)
        args.update(change)
        with pytest.raises(InputError) as err:
            render(**args)
        assert str(err.value).startswith(message), (change, str(err.value))
    rgb, _, _ = render(g, pose, K, 12, 16, near=0.0, background=(0.1, 0.2, 0.3))
    assert torch.isfinite(rgb).all()


def test_huge_scales_cover_the_view_as_the_closed_form_says():
    W, H, f, z = 32, 24, 40.0, 3.0
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=torch.float64)
    pose = torch.eye(4, dtype=torch.float64)
    background = (0.1, 0.2, 0.3)
    colour = [max(v * C0 + 0.5, 0.0) for v in (0.6, -0.2, 0.1)]
    # Isotropic, e^50 wide: the whole view is covered, α = o everywhere.
    for log_scale in (50.0, 200.0):
        rgb, depth, acc = render(one_gaussian([0.0, 0.0, z], [log_scale] * 3), pose, K, H, W, background=background)
        assert (acc - 0.8).abs().max() < 1e-6, log_scale
        assert (depth - z).abs().max() < 1e-5
        for ch in range(3):
            assert (rgb[ch] - (0.8 * colour[ch] + 0.2 * background[ch])).abs().max() < 1e-6
    # A line e^50 long, 0.05 thin, turned 30° in the image plane: a band across the view whose
    # α follows the distance to the line, maha = (n·d)² / ((f/z)² 0.05² + 0.3) (+ (u·d)² / ~e^100).
    theta = math.radians(30)
    quat = (math.cos(theta / 2), 0.0, 0.0, math.sin(theta / 2))
    g = one_gaussian([0.0, 0.0, z], [50.0, math.log(0.05), math.log(0.05)], quat=quat)
    rgb, _, acc = render(g, pose, K, H, W, background=background)
    band = (f / z) ** 2 * 0.05 ** 2 + 0.3
    n = (-math.sin(theta), math.cos(theta))
    want = torch.zeros(H, W, dtype=torch.float64)
    for v in range(H):
        for u in range(W):
            maha = ((u + 0.5 - W / 2) * n[0] + (v + 0.5 - H / 2) * n[1]) ** 2 / band
            alpha = min(0.99, 0.8 * math.exp(-0.5 * maha))
            want[v, u] = alpha if maha <= 9 and alpha >= 1 / 255 else 0.0
    assert float(want.max()) > 0.7 and float((want == 0).float().mean()) > 0.5  # a band, not the whole view
    assert (acc[0].double() - want).abs().max() < 1e-5
    assert (rgb[0].double() - (want * colour[0] + (1 - want) * background[0])).abs().max() < 1e-5
