"""H.264 MP4 writing through PyAV (the ``video`` extra: ``pip install 'roguenerf[video]'``).

PyAV's wheels carry their own FFmpeg with libx264, so nothing else is installed. Frames are
encoded as they arrive (bounded memory for any path length); odd sizes are padded by one
edge pixel, since 4:2:0 chroma needs even sides.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from roguenerf.errors import InputError

DEFAULT_CRF = 20
"""x264 constant rate factor: 0 is lossless, 18-23 visually good, 51 worst."""


def require_av():
    try:
        import av
    except ImportError:
        raise InputError("writing MP4 needs PyAV: pip install 'roguenerf[video]' (or pass --no-video)") from None
    return av


def check_quality(crf: int) -> int:
    if isinstance(crf, bool) or not isinstance(crf, int) or not 0 <= crf <= 51:
        raise InputError(f"quality (x264 CRF): expected an integer 0..51 (lower is better), got {crf!r}")
    return crf


def _as_uint8(frame, name: str = "frame") -> np.ndarray:
    """``(3, H, W)`` float tensor in [0, 1] -> ``(H, W, 3)`` uint8 (even sides, edge-padded).

    The image-dtype rule (:func:`roguenerf.images.check_float_image`): integer and bool frames
    are refused naming the conversion, never rescaled; NaN / inf pixels are refused, never
    encoded as black; finite values outside [0, 1] are clamped.
    """
    from roguenerf.images import check_float_image

    if isinstance(frame, np.ndarray):
        raise InputError(f"{name}: expected a (3, H, W) float torch.Tensor in [0, 1], got a NumPy array "
                         f"{frame.dtype} {frame.shape}; e.g. torch.from_numpy(x).permute(2, 0, 1).float() / 255 "
                         "for an (H, W, 3) uint8 array")
    check_float_image(frame, name)
    if frame.ndim != 3 or frame.shape[0] != 3 or frame.shape[1] < 1 or frame.shape[2] < 1:
        raise InputError(f"{name}: expected shape (3, H, W) (RGB, channels first), got {tuple(frame.shape)}")
    finite = torch.isfinite(frame)
    if not bool(finite.all()):
        bad = int((~finite).sum())
        raise InputError(f"{name}: {bad} non-finite (NaN or inf) values; a video frame must be finite "
                         "(they are never encoded as black)")
    frame = (frame.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    h, w = frame.shape[:2]
    if h % 2 or w % 2:
        frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    return np.ascontiguousarray(frame)


def label_image(image: Tensor, text: str) -> Tensor:
    """``image`` ``(3, H, W)`` float in [0, 1] with ``text`` drawn in its top-left corner (white on
    a dark box, PIL's default font); the side-by-side video's "render" | "enhanced" labels."""
    from PIL import Image, ImageDraw

    from roguenerf.images import check_float_image

    check_float_image(image, "image")
    array = (image.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    picture = Image.fromarray(np.ascontiguousarray(array))
    draw = ImageDraw.Draw(picture)
    left, top, right, bottom = draw.textbbox((3, 2), text)
    draw.rectangle((0, 0, right + 3, bottom + 2), fill=(0, 0, 0))
    draw.text((3, 2), text, fill=(255, 255, 255))
    labelled = torch.from_numpy(np.asarray(picture).copy()).permute(2, 0, 1).float() / 255
    # Only the label's box changes: the pixels outside keep their values (no 8-bit rounding).
    out = image.detach().to(torch.float32).clone()
    h, w = min(bottom + 3, out.shape[1]), min(right + 4, out.shape[2])
    out[:, :h, :w] = labelled[:, :h, :w]
    return out


def side_by_side(render: Tensor, enhanced: Tensor, labels: tuple[str, str] = ("render", "enhanced")) -> Tensor:
    """``render | enhanced`` side by side, each half labelled (``(3, H, 2W)``)."""
    return torch.cat([label_image(render, labels[0]), label_image(enhanced, labels[1])], dim=2)


class Mp4Writer:
    """``with Mp4Writer(path, fps=24, crf=20) as video: video.write(frame)``; atomic: the file
    appears under its name only when closed without an error."""

    def __init__(self, path: str | os.PathLike, *, fps: float = 24.0, crf: int = DEFAULT_CRF):
        self.av = require_av()
        if not (isinstance(fps, (int, float)) and 0 < fps <= 240):
            raise InputError(f"fps: expected a number in (0, 240], got {fps!r}")
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.partial.mp4")
        self.fps = fps
        self.crf = check_quality(crf)
        self.container = None
        self.stream = None
        self.frames = 0

    def __enter__(self) -> Mp4Writer:
        return self

    def write(self, frame: Tensor) -> None:
        """Encode ``frame`` ``(3, H, W)`` float in [0, 1] (see :func:`_as_uint8` for what is refused)."""
        from fractions import Fraction

        image = _as_uint8(frame, f"video frame {self.frames}")
        if self.container is None:
            self.container = self.av.open(str(self.tmp), mode="w", format="mp4")
            rate = Fraction(self.fps).limit_denominator(1001)
            self.stream = self.container.add_stream("libx264", rate=rate)
            self.stream.width, self.stream.height = image.shape[1], image.shape[0]
            self.stream.pix_fmt = "yuv420p"
            self.stream.options = {"crf": str(self.crf), "preset": "medium"}
        elif (image.shape[1], image.shape[0]) != (self.stream.width, self.stream.height):
            raise InputError(f"video frame {self.frames}: size {image.shape[1]}x{image.shape[0]} differs "
                             f"from the first frame's {self.stream.width}x{self.stream.height}")
        video_frame = self.av.VideoFrame.from_ndarray(image, format="rgb24")
        for packet in self.stream.encode(video_frame):
            self.container.mux(packet)
        self.frames += 1

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.container is None:
            return
        try:
            if exc_type is None:
                for packet in self.stream.encode():
                    self.container.mux(packet)
        finally:
            self.container.close()
        if exc_type is None:
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)


def read_video_info(path: str | os.PathLike) -> dict:
    """Decode a video back: ``{"frames", "width", "height", "codec"}`` (tests, benches)."""
    av = require_av()
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = 0
        for frame in container.decode(stream):
            frames += 1
            width, height = frame.width, frame.height
        return {"frames": frames, "width": width if frames else 0, "height": height if frames else 0,
                "codec": stream.codec_context.name}
