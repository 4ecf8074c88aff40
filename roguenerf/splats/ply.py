"""Read and write Inria 3DGS ``point_cloud.ply`` files (binary little-endian).

One ``vertex`` element per Gaussian with float properties ``x y z``, optional ``nx ny nz``,
``f_dc_0..2``, ``f_rest_0..M-1`` (M = 3 (K - 1) for K = 1, 4, 9, 16 coefficients per channel,
stored channel-major: all of red's higher coefficients, then green's, then blue's), ``opacity``
(a logit), ``scale_0..2`` (logarithms) and ``rot_0..3`` (a quaternion, w first). Other vertex
properties (any numeric type) are read past; other elements before ``vertex`` must have no list
properties. Everything wrong with a file raises :class:`~roguenerf.errors.InputError` naming it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from roguenerf.errors import InputError
from roguenerf.splats.gaussians import Gaussians, sh_degree_of

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
MAX_HEADER_BYTES = 1 << 20
REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3")


def _fail(path: Path, message: str) -> InputError:
    return InputError(f"{path}: {message}")


def _read_header(path: Path, f) -> tuple[list[tuple[str, int, list[tuple[str, str]], bool]], int]:
    head = f.read(4)
    if head != b"ply\n":
        raise _fail(path, "not a PLY file (it does not start with 'ply')")
    lines, size = [], 4
    while True:
        line = f.readline(4096)
        size += len(line)
        if not line.endswith(b"\n") or size > MAX_HEADER_BYTES:
            raise _fail(path, "PLY header has no end_header line")
        text = line.decode("ascii", errors="replace").strip()
        if text == "end_header":
            break
        lines.append(text)
    elements: list[tuple[str, int, list[tuple[str, str]], bool]] = []
    fmt = None
    for text in lines:
        parts = text.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = parts[1] if len(parts) > 1 else ""
        elif parts[0] == "element" and len(parts) == 3 and parts[2].isdigit():
            elements.append((parts[1], int(parts[2]), [], False))
        elif parts[0] == "property" and elements:
            name, count, props, has_list = elements[-1]
            if len(parts) >= 2 and parts[1] == "list":
                elements[-1] = (name, count, props, True)
            elif len(parts) == 3 and parts[1] in _TYPES:
                props.append((parts[2], "<" + _TYPES[parts[1]]))
            else:
                raise _fail(path, f"PLY header: cannot read {text!r}")
        else:
            raise _fail(path, f"PLY header: cannot read {text!r}")
    if fmt != "binary_little_endian":
        raise _fail(path, f"expected a binary_little_endian PLY (as 3DGS writes), got format {fmt!r}")
    return elements, size


def read_ply(path: str | os.PathLike) -> Gaussians:
    """Read a 3DGS ``point_cloud.ply`` into float32 :class:`Gaussians` (CPU)."""
    path = Path(path)
    try:
        f = open(path, "rb")
    except FileNotFoundError:
        raise _fail(path, "file not found") from None
    except OSError as exc:
        raise _fail(path, f"cannot open ({exc.strerror})") from None
    with f:
        elements, offset = _read_header(path, f)
        skip = 0
        for name, count, props, has_list in elements:
            if name == "vertex":
                break
            if has_list:
                raise _fail(path, f"element {name!r} before 'vertex' has list properties: not a 3DGS file")
            skip += count * np.dtype(props).itemsize
        else:
            raise _fail(path, "no 'vertex' element: not a 3DGS point cloud")
        _, count, props, has_list = next(e for e in elements if e[0] == "vertex")
        if has_list:
            raise _fail(path, "vertex element has list properties: not a 3DGS point cloud")
        names = [p[0] for p in props]
        if len(set(names)) != len(names):
            raise _fail(path, "vertex properties repeat a name")
        missing = [p for p in REQUIRED if p not in names]
        if missing:
            raise _fail(path, f"not a 3DGS point cloud: vertex properties {', '.join(missing)} are missing "
                              f"(found {', '.join(names[:12])}{' ...' if len(names) > 12 else ''})")
        rest = sorted(int(m.group(1)) for n in names if (m := re.fullmatch(r"f_rest_(\d+)", n)))
        if rest != list(range(len(rest))):
            raise _fail(path, f"f_rest_* properties are not numbered 0..{len(rest) - 1}")
        if len(rest) % 3:
            raise _fail(path, f"{len(rest)} f_rest_* properties: expected 0, 9, 24 or 45 (3 channels)")
        try:
            degree = sh_degree_of(1 + len(rest) // 3)
        except InputError:
            raise _fail(path, f"{len(rest)} f_rest_* properties: expected 0, 9, 24 or 45 (SH degree 0..3)") from None
        dtype = np.dtype(props)
        if count == 0:
            raise _fail(path, "the point cloud holds no Gaussians")
        need = count * dtype.itemsize
        held = max(0, os.fstat(f.fileno()).st_size - offset - skip)
        if need > held:  # before reading: a corrupt count would ask for more memory than there is
            raise _fail(path, f"file is truncated: the header claims {count} vertices of {dtype.itemsize} bytes "
                              f"({need} bytes), the file holds {held} after the header"
                              f"{' and the elements before vertex' if skip else ''}")
        f.seek(offset + skip)
        data = f.read(need)
    v = np.frombuffer(data, dtype=dtype, count=count)

    def cols(keys):
        return torch.from_numpy(np.stack([v[k].astype(np.float32) for k in keys], axis=-1))

    k = (degree + 1) ** 2
    sh = torch.zeros(count, k, 3)
    sh[:, 0] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    if k > 1:
        f_rest = cols([f"f_rest_{i}" for i in range(3 * (k - 1))])  # channel-major: (N, 3, K-1)
        sh[:, 1:] = f_rest.reshape(count, 3, k - 1).transpose(1, 2)
    g = Gaussians(means=cols(["x", "y", "z"]), sh=sh, opacity=cols(["opacity"])[:, 0],
                  log_scales=cols(["scale_0", "scale_1", "scale_2"]), quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]))
    g.check_finite(str(path))
    if (g.quats.norm(dim=-1) < 1e-12).any():
        raise _fail(path, "a rotation quaternion (rot_0..3) is zero")
    return g


def write_ply(path: str | os.PathLike, gaussians: Gaussians, *, normals: bool = True) -> Path:
    """Write ``gaussians`` as Inria's ``point_cloud.ply`` (float32, with zero ``nx ny nz`` as
    Inria writes them unless ``normals=False``); atomic (temporary file, fsync, rename)."""
    from roguenerf.imageio import atomic_write

    g = gaussians.detach().to("cpu", torch.float32)
    n, k = len(g), int(g.sh.shape[1])
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + ["f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    columns = [g.means] + ([torch.zeros(n, 3)] if normals else []) + [g.sh[:, 0]]
    if k > 1:
        columns.append(g.sh[:, 1:].transpose(1, 2).reshape(n, 3 * (k - 1)))
    columns += [g.opacity[:, None], g.log_scales, g.quats]
    table = torch.cat(columns, dim=1).numpy().astype("<f4")
    header = "ply\nformat binary_little_endian 1.0\n" f"element vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    return atomic_write(Path(path), header.encode("ascii") + table.tobytes(), make_parents=True)
