"""Enhance every frame of a camera path, write the MP4s, measure flicker.

Legend: T frames, (H, W) render size.

:func:`enhance_path` takes a path's cameras (:class:`~roguenerf.trajectory.CameraPath`) and the
folder of each frame's render and depth, enhances the frames one by one with one
:class:`~roguenerf.inference.SceneEnhancer` (each training photo's features are computed once for
the whole path; with ``EnhanceOptions.temporal`` each neighbour's pose is fitted once too, and
each frame is blended with the previous one: :mod:`roguenerf.enhance.temporal`), writes each
enhanced frame atomically as it is done (an interrupted run resumes after the last written
frame; with ``TemporalConfig.carry_between`` the model frame after a stretch is made before the
frames of the stretch, and still written after them, in order); with ``TemporalConfig.both_ways``
(the default) those are the first pass's frames, written into :data:`FORWARD_FOLDER`, and a
second pass from the last frame back blends each with the frame after it as written into
``frames/`` (resumable the same way, from the end), where the report measures them; then encodes ``enhanced.mp4``
and ``side_by_side.mp4`` (render | enhanced, each half labelled) frame by frame. The flicker
report is :mod:`roguenerf.trajectory.flicker`'s, on two frames held at a time (with
``carry_between``, also the next model frame, made ahead of the stretch before it).

One background thread reads the next frame's render and depth and encodes and writes the last
enhanced frame while the present one is enhanced (the PNG encoder and the decoders release the
interpreter), at most :data:`WRITES_PENDING` frames behind; a write that fails stops the path
with its error, and every frame handed to it is written before :func:`enhance_path` returns or
raises (a cancelled or failed path resumes after the last frame written).
"""

from __future__ import annotations

import bisect
import hashlib
import json
import math
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor

from roguenerf.enhance.temporal import TemporalFilter, gated_schedule, settling, sticky_neighbours
from roguenerf.errors import InputError, PathCancelled
from roguenerf.inference import PoseMemory
from roguenerf.trajectory.checks import check_path
from roguenerf.trajectory.flicker import pair_flicker, sharpening, summarise_flicker
from roguenerf.trajectory.readers import CameraPath, find_path_frames

FRAME_FOLDER = "frames"
FORWARD_FOLDER = "forward"
"""With ``TemporalConfig.both_ways``: the first pass's frames (each blended with the frames before
it), which the second pass, from the last frame back, blends with the frames after it into
:data:`FRAME_FOLDER`; kept, so that a stopped path resumes either pass."""
STATE_FILE = "path_state.json"
FLICKER_FILE = "flicker.json"
VIDEO_FILE = "enhanced.mp4"
SIDE_BY_SIDE_FILE = "side_by_side.mp4"
WRITES_PENDING = 2
"""Enhanced frames handed to the background thread and not yet written, at most (memory: a
1920 x 1080 frame is 25 MB as float32)."""
POSE_MATCH_TOL = 1e-5
"""A path camera "is" a scene view (and has its photo) when rotation and position agree to this
(position relative to the scene's extent)."""


SECOND_PASS_SHARE = 0.2
"""With ``TemporalConfig.both_ways``: a second-pass step's time over a first-pass step's, taken by
:class:`PathClock` until the second pass has timed its own steps. Measured on ``can_clip``'s
49-frame path at 504 px (cProfile, 2026-12-07): 0.17 with the model on every frame (a blend and
the flicker report, about 60 ms, after 350 ms)."""
SECOND_PASS_SHARE_CARRIED = 0.4
""":data:`SECOND_PASS_SHARE` with ``model_every`` > 1: 0.38 there at 4 (the first pass's steps
average the model frames and the cheaper carried ones)."""


class PathClock:
    """Seconds left of an :func:`enhance_path` run, from its ``progress(done, total)`` calls.

    Each pass is timed on its own over its last :attr:`WINDOW` steps (a resumed path's frames,
    read back, go fast; the model frames of ``model_every`` > 1 slow), and while the first of two
    passes runs, the second's steps are taken as ``second_share`` of the first's: the cumulative
    rate of all steps would count the second pass's cheap steps at the first pass's price.

    Args:
        temporal: the run's ``TemporalConfig`` (None: frame by frame, one pass).
        clock: seconds, monotonic (tests pass their own).
    """

    WINDOW = 12

    def __init__(self, temporal=None, *, clock=time.monotonic):
        both = temporal is not None and temporal.both_ways
        self.passes = 2 if both else 1
        carried = temporal is not None and temporal.model_every > 1
        self.second_share = SECOND_PASS_SHARE_CARRIED if carried else SECOND_PASS_SHARE
        self._clock = clock
        self._start = clock()  # the first step is timed from here (the run's loading included)
        self._steps: deque = deque(maxlen=self.WINDOW + 1)
        self._pass = 0
        self._first_rate = None  # the first pass's last rate: the second pass's steps until it has its own

    def __call__(self, done: int, total: int) -> float | None:
        """Record step ``done`` of ``total``; the seconds left (None until a step of the run is timed)."""
        now = self._clock()
        frames = max(1, total // self.passes)
        current = 0 if self.passes == 1 or done <= frames else 1
        if current != self._pass:  # the second pass: timed from the first pass's last step on
            self._pass = current
            self._steps = deque(list(self._steps)[-1:], maxlen=self.WINDOW + 1)
        self._steps.append((done, now))
        (d0, t0), (d1, t1) = self._steps[0], self._steps[-1]
        rate = (d1 - d0) / (t1 - t0) if d1 > d0 and t1 > t0 else None  # steps per second in this pass
        if rate is None and len(self._steps) == 1 and current == 0 and done > 0 and now > self._start:
            rate = done / (now - self._start)  # the run's first step
        if current == 0:
            self._first_rate = rate or self._first_rate
            if rate is None:
                return None
            second = frames * self.second_share / rate if self.passes == 2 else 0.0
            return (frames - done) / rate + second
        if rate is None and self._first_rate is not None:
            rate = self._first_rate / self.second_share
        return None if rate is None else (total - done) / rate


@dataclass
class PathResult:
    output: Path
    frames: int
    enhanced_now: int
    """Frames enhanced by this call: written into ``frames/`` (with ``TemporalConfig.both_ways`` by
    its second pass); the rest were already there (resumed)."""
    seconds: float
    video: Path | None
    side_by_side: Path | None
    flicker: dict = field(default_factory=dict)
    """What :data:`FLICKER_FILE` holds: per-pair and mean flicker, per-frame PSNR where photos exist."""
    cached_views: int = 0
    warnings: list[str] = field(default_factory=list)
    """What went on with ``force=True`` (:func:`~roguenerf.trajectory.check_camera_path`'s message)."""
    enhance_seconds: float = 0.0
    """Seconds spent making the frames enhanced by this call: each such frame's whole turn of
    the loop (reading, enhancing, smoothing, writing, its flicker and PSNR; with
    ``TemporalConfig.both_ways`` its turn in each pass), and the wait for the last writes; not the
    checks before, the frames read back, nor the videos after."""

    @property
    def frames_per_second(self) -> float | None:
        """Frames enhanced per second by this call (None where it enhanced none)."""
        return self.enhanced_now / self.enhance_seconds if self.enhanced_now and self.enhance_seconds > 0 else None


def _fingerprint(camera_path: CameraPath, pairs: list[tuple[Path, Path]], checkpoint_id: str, options: dict) -> str:
    h = hashlib.sha256()
    h.update(camera_path.world_from_cam.numpy().tobytes())
    h.update(camera_path.K.numpy().tobytes())
    for rgb, depth in pairs:
        for p in (rgb, depth):
            st = p.stat()
            h.update(f"{p.name}:{st.st_size}".encode())
    h.update(checkpoint_id.encode())
    h.update(json.dumps(options, sort_keys=True).encode())
    return h.hexdigest()


def check_path_output(output: str | Path) -> None:
    """``enhance_path``'s output may be new, empty, or an earlier run's (its resume state): any
    other folder is refused, since its ``frames/``, videos and flicker report would be written over
    (and frames already there taken for enhanced ones)."""
    output = Path(output)
    if not output.exists():
        return
    if not output.is_dir():
        raise InputError(f"output: {output} exists and is not a folder; choose a new folder")
    if any(output.iterdir()) and not (output / STATE_FILE).is_file():
        raise InputError(f"output: {output} exists and is not empty: it holds other files, not an earlier "
                         "enhance-path output (which would be resumed); choose a new folder")


def enhance_path(
    scene,
    enhancer,
    camera_path: CameraPath,
    frames: str | Path,
    output: str | Path,
    *,
    depth_type: str = "z",
    depth_scale: float = 1.0,
    background: str = "zero",
    video: bool = True,
    quality: int = 20,
    fps: float | None = None,
    checkpoint_id: str = "",
    progress=None,
    should_stop=None,
    force: bool = False,
    force_hint: str = "force=True",
) -> PathResult:
    """Enhance every frame of a camera path; write frames, MP4s and the flicker report.

    Args:
        scene: the registered :class:`~roguenerf.data.scene.Scene` (its training photos are the
            neighbours; a path camera that coincides with one of its views gets that view's photo
            for the PSNR gain and photo flicker, and never uses it as a neighbour).
        enhancer: a :class:`~roguenerf.inference.SceneEnhancer` of ``scene`` (its feature cache
            serves the whole path).
        camera_path: the cameras, in the scene's pose units (:func:`~roguenerf.trajectory.read_camera_path`).
        frames: folder of the frames' renders and depths (:func:`~roguenerf.trajectory.find_path_frames`).
        output: folder for ``frames/NNNNN.png``, the MP4s, :data:`FLICKER_FILE` and the resume
            state. A folder holding another path's frames is refused.
        depth_type, depth_scale, background: how the frames' depth files are stored (see
            :func:`roguenerf.data.exports.import_renders`).
        video: write ``enhanced.mp4`` and ``side_by_side.mp4`` (needs PyAV).
        quality: x264 CRF, 0..51 (lower is better).
        fps: frame rate; default the camera path's.
        checkpoint_id: anything naming the model's weights (part of the resume fingerprint).
        progress: ``callback(done, total)`` per step: one per frame, or with
            :attr:`~roguenerf.enhance.temporal.TemporalConfig.both_ways` one per frame and pass
            (``total`` = 2 x frames; the second pass's steps are the cheaper ones, 8-15 % of a
            frame's time at 504 px).
        should_stop: ``() -> bool`` polled between frames; True raises
            :class:`~roguenerf.errors.PathCancelled` (frames written so far are kept).
        force: go on when :func:`~roguenerf.trajectory.check_camera_path` finds that the path does
            not fit the scene (its message is logged and kept in ``PathResult.warnings``); otherwise
            that is an :class:`~roguenerf.errors.CameraMismatchError`, before any frame is enhanced
            (:func:`~roguenerf.trajectory.check_path`).
        force_hint: how that error tells the caller to force it (the CLI: ``--force``; the service:
            its ``force`` field).
    """
    from roguenerf.data.exports import background_to_unknown
    from roguenerf.geometry.cameras import ray_to_z_depth
    from roguenerf.imageio import atomic_write, finite_for_json, read_depth, read_image
    from roguenerf.metrics import psnr
    from roguenerf.video import Mp4Writer, check_quality, require_av, side_by_side

    start = time.perf_counter()
    check_path_output(output)
    if depth_type not in ("z", "ray"):
        raise InputError(f"depth_type: expected 'z' or 'ray', got {depth_type!r}")
    if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and depth_scale > 0):
        raise InputError(f"depth_scale: expected a finite number > 0, got {depth_scale!r}")
    check_quality(quality)
    if video:
        require_av()
    fps = camera_path.fps if fps is None else fps
    pairs = find_path_frames(frames, len(camera_path))
    matches = _match_views(scene, camera_path)
    total = len(pairs)

    def load_frame(t: int) -> tuple[Tensor, Tensor]:
        rgb_path, depth_path = pairs[t]
        render = read_image(rgb_path)
        if render.shape[1:] != (camera_path.height, camera_path.width):
            raise InputError(f"{rgb_path}: render is {render.shape[2]}x{render.shape[1]}, the camera path says "
                             f"{camera_path.width}x{camera_path.height}")
        depth = read_depth(depth_path, scale=float(depth_scale))
        if depth.shape[1:] != render.shape[1:]:
            raise InputError(f"{depth_path}: depth is {depth.shape[2]}x{depth.shape[1]}, its render "
                             f"{render.shape[2]}x{render.shape[1]}")
        depth = background_to_unknown(depth, background)
        if depth_type == "ray":
            depth = ray_to_z_depth(depth.double(), camera_path.K[t]).float()
        return render, depth

    warnings = check_path(scene, camera_path, frames, depth_type=depth_type, depth_scale=depth_scale,
                          background=background, neighbours=max(1, enhancer.num_neighbours or 1), force=force,
                          override=force_hint)

    output = Path(output)
    frame_dir = output / FRAME_FOLDER
    output.mkdir(parents=True, exist_ok=True)  # frames/ only once the state marks the folder as ours
    # The enhancer's options too (EnhanceOptions.fingerprint, with the count they resolve to for
    # this model): frames made with another neighbour rule, colour reach, trust or pose refinement
    # (a changed default after an upgrade) must not be mixed into this video.
    options = {"depth_type": depth_type, "depth_scale": depth_scale, "background": background,
               "neighbours": enhancer.num_neighbours, "near_extra": enhancer.near_extra,
               "enhance": enhancer.options.fingerprint()}
    fingerprint = _fingerprint(camera_path, pairs, checkpoint_id, options)
    state_path = output / STATE_FILE
    if state_path.is_file():
        try:
            previous = json.loads(state_path.read_text()).get("fingerprint")
        except (OSError, json.JSONDecodeError):
            previous = None
        if previous != fingerprint:
            raise InputError(f"{output} holds the frames of another path, model or setting; "
                             "choose another output folder or delete it")
    else:
        atomic_write(state_path, json.dumps({"fingerprint": fingerprint, "frames": len(pairs)}).encode())
    frame_dir.mkdir(exist_ok=True)
    per_pair, per_frame = [], []
    prev = None
    done_now = 0
    making = 0.0
    temporal = None if enhancer.options.temporal is None else TemporalFilter(enhancer.options.temporal)
    last_neighbours = None
    poses = (PoseMemory(temporal.config.refit_nearer)
             if temporal is not None and temporal.config.reuse_poses and enhancer.align is not None else None)
    # TemporalConfig.carry_between: the model frames 0, k, 2k, ... (and the last) are made before
    # the frames between them, each of which is carried from the two around it; frames are still
    # written, measured and remembered in order.
    every = 1 if temporal is None else temporal.config.model_every
    between = temporal is not None and temporal.config.carry_between and every > 1
    # TemporalConfig.both_ways: the pass above writes into forward/, measured by the second pass,
    # which writes frames/ from the last frame back (a forward-backward moving average)
    both_ways = temporal is not None and temporal.config.both_ways
    first_dir = output / FORWARD_FOLDER if both_ways else frame_dir
    first_dir.mkdir(exist_ok=True)
    steps = total * (2 if both_ways else 1)  # what progress counts

    def measure(t: int, render: Tensor, enhanced: Tensor, depth: Tensor, row: dict) -> tuple:
        """Frame t as written: its PSNR gain where it has a photo and its detail, into ``row``; what
        its pairs' flicker needs."""
        photo = scene.photo(matches[t]) if matches[t] is not None else None
        if photo is not None:
            row["render_psnr"] = float(psnr(render[None], photo[None])[0])
            row["enhanced_psnr"] = float(psnr(enhanced[None], photo[None])[0])
            row["gain_db"] = row["enhanced_psnr"] - row["render_psnr"]
        sharp = sharpening(render, enhanced)
        row["detail_ratio"] = round(sharp.ratio, 4)
        return render, enhanced, photo, depth, camera_path.K[t], camera_path.world_from_cam[t], sharp

    def measure_pair(a: tuple, b: tuple, t: int, moved=None, *, back: bool = False) -> dict:
        """The flicker of frames t (``a``, :func:`measure`'s) and t + 1 (``b``): frame t moved into
        t + 1, or with ``back`` (the second pass of TemporalConfig.both_ways, which blends the other
        way) frame t + 1 into t; ``moved``: the filter's move between them in that direction, where
        it made one (measured alike where it did not: a resumed path)."""
        # the reference: both renders sharpened alike, as much as the two enhanced frames on average
        amount = 0.5 * (a[6].amount + b[6].amount)
        if back:
            a, b = b, a
        errors, fraction = pair_flicker([*a[:3], a[6].image(a[0], amount)], [*b[:3], b[6].image(b[0], amount)],
                                        a[3], b[3], a[4], b[4], a[5], b[5], warp=moved)
        return {"from": t, "to": t + 1, "render": errors[0], "enhanced": errors[1], "photo": errors[2],
                "sharpened": errors[3], "valid_fraction": fraction}
    behind = _Background()
    loading: dict[int, Future] = {}
    made: dict[int, dict] = {}  # frames made (or read back) ahead of their turn: the next model frame
    anchors: dict[int, object] = {}  # between: a model frame's kept state (TemporalFilter.kept)

    def frame(t: int) -> tuple[Tensor, Tensor]:
        """Frame t's render and depth: read ahead by the background thread where it was asked."""
        future = loading.pop(t, None)
        return future.result() if future is not None else load_frame(t)

    def read_ahead(t: int) -> None:
        if t < total and t not in loading and t not in made:
            loading[t] = behind.submit(load_frame, t)

    def excluded(t: int) -> int | None:
        """The scene view frame t sits on where it is a training view: never its own neighbour."""
        match = matches[t]
        return match if match is not None and scene.frames[match].split == "train" else None

    # Along a path the rule's neighbour set changes every few frames, and each change makes the
    # enhanced frame jump (TemporalConfig.change_weight, change_frames): every frame's set is
    # known, read back or not, so a resumed path weighs its frames as the first run did.
    rule: dict[int, list[int]] = {}
    measured = enhancer.options.neighbours.measured

    def chosen(t: int, view: tuple[Tensor, Tensor] | None = None) -> list[int]:
        """The rule's neighbours of frame t (scene indices), chosen once; a measured rule reads
        the frame where it has not been read yet."""
        if t not in rule:
            if view is None and measured:
                view = load_frame(t)
            rule[t] = enhancer.select(camera_path.world_from_cam[t], exclude=excluded(t),
                                      view=None if view is None else (*view, camera_path.K[t]))
        return rule[t]

    changes: list[int] = []  # with keep_within: the frames whose neighbours differ from the frame before's

    def settles(t: int) -> bool:
        """Whether frame t takes TemporalConfig.change_weight (a set change within change_frames)."""
        frames = temporal.config.change_frames
        if temporal.config.keep_within > 0:
            return settling(changes, t, frames)
        return settling([s for s in range(max(1, t - frames + 1), t + 1) if set(chosen(s)) != set(chosen(s - 1))],
                        t, frames)

    def make(t: int, render: Tensor, depth: Tensor, *, neighbours=None, changed=False,
             carry_between=None, apart=1) -> dict:
        """Frame t: carried (where due and allowed), read back (where written before) or enhanced."""
        camera = (camera_path.K[t], camera_path.world_from_cam[t])
        exclude = excluded(t)
        # Along a path with model_every > 1, a frame between the model's is carried into (where
        # the model frames see enough of it); decided the same way on a resume.
        carried = agreement = mutual = change = nearer = None
        # what decided it (TemporalConfig.carry_nearer, carry_agreement, carry_share, between_agreement)
        due = carry_between is not None or (temporal is not None and not between
                                            and not temporal.model_due(t, changed=changed))
        if due:
            carried = temporal.carry(render, depth, *camera, between=carry_between,
                                     photo_distance=None if photos is None else photos[t])
            agreement, mutual, change = temporal.last_agreement, temporal.last_mutual, temporal.last_change
            nearer = temporal.last_nearer
        out_png = first_dir / f"{t:05d}.png"
        entry = {"render": render, "depth": depth, "carried": carried is not None, "agreement": agreement,
                 "mutual": mutual, "change": change, "nearer": nearer, "made": not out_png.is_file(),
                 "neighbours": None}
        if not entry["made"]:
            entry["enhanced"] = read_image(out_png)
            if temporal is not None and carried is None and temporal.config.fade_along:
                entry["blended"] = (settles(t), apart)  # TemporalConfig.fade_along: its map worked out again
            if neighbours is not None and carried is None:  # named as the model took them when it ran
                entry["neighbours"] = [scene.frames[i].name for i in neighbours]
            if poses is not None and carried is None:  # a resumed path fits its neighbours' poses as it did
                used = neighbours if neighbours is not None else chosen(t, (render, depth))
                enhancer.neighbour_poses([enhancer.train.index(i) for i in used], render, depth, *camera,
                                         memory=poses)
        elif carried is not None:
            entry["image"] = carried
        else:
            result = enhancer.enhance(render, depth, *camera, exclude=exclude, neighbours=neighbours,
                                      pose_memory=poses)
            image, entry["neighbours"] = result.image, result.neighbours
            if temporal is not None:
                image = temporal(render, image, depth, *camera, changed=settles(t), frames_apart=apart)
                entry["parallax"] = temporal.last_parallax  # TemporalConfig.fade_along: kept with the frame
            entry["image"] = image
        if entry["made"]:
            entry["enhanced"] = _quantise(entry["image"])
        return entry

    def make_between(t: int, render: Tensor, depth: Tensor) -> dict:
        """Frame t with TemporalConfig.carry_between: a model frame, or one carried from the model
        frames before and after it (the one after made first, right after the one before was remembered)."""
        at = bisect.bisect_right(model_frames, t) - 1
        before = model_frames[at]
        after = model_frames[min(at + 1, len(model_frames) - 1)]
        if t == before or t == after:  # a model frame with nothing to carry between (the last, or frame 0)
            return make(t, render, depth, neighbours=chosen(t, (render, depth)))
        if after not in made:
            kept = temporal.kept  # the model frame before, as written: the frame just remembered
            after_render, after_depth = frame(after)
            made[after] = make(after, after_render, after_depth,  # blended with the model frame before
                               neighbours=chosen(after, (after_render, after_depth)), apart=after - before)
            read_ahead(t + 1)
            camera = (camera_path.K[after], camera_path.world_from_cam[after])
            temporal.remember(after_render, made[after]["enhanced"], after_depth, *camera, model=True,
                              parallax=made[after].get("parallax"), blended=made[after].pop("blended", None))
            # what it carries (fade_along), for its turn below (an older filter's kept frame has no map)
            made[after]["parallax"] = getattr(temporal.kept, "parallax", None)
            anchors[after] = temporal.kept
            anchors[before] = kept
            temporal.restore(kept)
        return make(t, render, depth, carry_between=(anchors[before], anchors[after], (t - before) / (after - before)))

    def backward_pass() -> tuple[float, int]:
        """TemporalConfig.both_ways: from the last frame back to the first, each first-pass frame
        blended with the frame after it as written (read back where it was written before), into
        frames/, and measured; the seconds spent on the frames written now, and their number."""
        back = TemporalFilter(temporal.config)  # only blends: never carries, never told of a change
        later, pairs_back, spent, written_now = None, [], 0.0, 0

        def read_back(t: int) -> tuple[Tensor, Tensor, Tensor]:  # by the background thread, a frame ahead
            return *load_frame(t), read_image(first_dir / f"{t:05d}.png")

        ahead = behind.submit(read_back, total - 1)
        for t in reversed(range(total)):
            if should_stop is not None and should_stop():
                raise PathCancelled(total)
            began = time.perf_counter()
            render, depth, first = ahead.result()
            if t > 0:
                ahead = behind.submit(read_back, t - 1)
            camera = (camera_path.K[t], camera_path.world_from_cam[t])
            out_png = frame_dir / f"{t:05d}.png"
            written = out_png.is_file()
            if written:
                final = read_image(out_png)
            else:
                final = _quantise(back(render, first, depth, *camera))
                behind.write(out_png, final)
                written_now += 1
            moved = None if written else back.last_warp  # frame t + 1 moved into t: the pair's flicker
            back.remember(render, final, depth, *camera, parallax=None if written else back.last_parallax,
                          blended=(False, 1) if written else None)
            current = measure(t, render, final, depth, per_frame[t])
            if later is not None:
                pairs_back.append(measure_pair(current, later, t, moved, back=True))
            later = current
            if not written:
                spent += time.perf_counter() - began
            if progress is not None:
                progress(2 * total - t, steps)
        waited = time.perf_counter()
        behind.drain()
        per_pair.extend(reversed(pairs_back))
        return spent + (time.perf_counter() - waited if written_now else 0.0), written_now

    # TemporalConfig.carry_nearer: each frame's distance to its nearest training photo, once (the
    # gate schedule and the carries judge by the same numbers)
    photos = None
    if temporal is not None and temporal.config.carry_nearer > 0:
        photos = [enhancer.photo_distance(camera_path.world_from_cam[t], exclude=excluded(t)) for t in range(total)]
    # between: the model frames, in order (TemporalConfig.schedule), worked out from the cameras
    # alone, so a resumed path places them where the first run did
    model_frames = None
    if between:
        if temporal.config.schedule == "gate":
            model_frames = gated_schedule(camera_path.world_from_cam[:, :3, 3].double(),
                                          photos or [math.inf] * total, every, temporal.config.carry_nearer)
        else:
            model_frames = sorted({*range(0, total, every), total - 1})
    try:
        for t in range(total):
            if should_stop is not None and should_stop():
                raise PathCancelled(t)
            began = time.perf_counter()
            made_before = sum(e["made"] for e in made.values())
            if t in made:
                entry = made.pop(t)
                render, depth = entry["render"], entry["depth"]
            else:
                render, depth = frame(t)
                read_ahead(t + 1)
                neighbours, changed = None, False
                if temporal is not None and not between:  # between: make_between chooses for its model frames
                    # Chosen for every frame, read back or not: a resumed path keeps the same chain.
                    neighbours = chosen(t, (render, depth))
                    if temporal.config.keep_within > 0:
                        nearest = [enhancer.train[p] for p in enhancer.candidates(
                            camera_path.world_from_cam[t], temporal.config.keep_within, exclude=excluded(t))]
                        neighbours = sticky_neighbours(last_neighbours, neighbours, nearest)
                    changed = last_neighbours is not None and set(neighbours) != set(last_neighbours)
                    if changed:
                        changes.append(t)
                    last_neighbours = neighbours
                entry = (make_between(t, render, depth) if between
                         else make(t, render, depth, neighbours=neighbours, changed=changed))
            made_now = entry["made"] or sum(e["made"] for e in made.values()) > made_before
            enhanced = entry["enhanced"]
            if entry["made"]:
                behind.write(first_dir / f"{t:05d}.png", entry["image"])
                done_now += 1
            row = {"frame": t, "view": scene.frames[matches[t]].name if matches[t] is not None else None}
            if entry["neighbours"] is not None:  # the model's, where it ran (or would have, read back)
                row["neighbours"] = entry["neighbours"]
            if temporal is not None and every > 1:
                row["carried"] = entry["carried"]
                if entry["agreement"] is not None:
                    row["carry_agreement_db"] = round(entry["agreement"], 2)
                if entry["mutual"] is not None:
                    row["between_agreement_db"] = round(entry["mutual"], 2)
                if entry["change"] is not None:
                    row["carry_change_db"] = round(entry["change"], 2)
                if entry["nearer"] is not None:
                    row["carry_nearer"] = round(entry["nearer"], 3) if math.isfinite(entry["nearer"]) else None
            per_frame.append(row)
            if not both_ways:  # both ways: the second pass measures the frames it writes
                current = measure(t, render, enhanced, depth, row)
                if prev is not None:  # the filter's move of the last frame, where it made one into this frame
                    per_pair.append(measure_pair(prev, current, t - 1,
                                                 moved=None if temporal is None or between else temporal.last_warp))
                prev = current
            if temporal is not None:  # the frame as written, whether made now or read back
                temporal.remember(render, enhanced, depth, camera_path.K[t], camera_path.world_from_cam[t],
                                  model=not entry["carried"], parallax=entry.get("parallax"),
                                  blended=entry.get("blended"))
            if between:  # the model frames before the one this frame was carried from are done with
                for done in [m for m in anchors if m < model_frames[bisect.bisect_right(model_frames, t) - 1]]:
                    anchors.pop(done)
            if temporal is not None:  # frames later than t look back this far at most (settles)
                rule.pop(t - temporal.config.change_frames - 1, None)
            if progress is not None:
                progress(t + 1, steps)
            if made_now:
                making += time.perf_counter() - began
        waited = time.perf_counter()
        behind.drain()  # the last frames' writes: part of making them (and what the second pass reads)
        if done_now:
            making += time.perf_counter() - waited
        if both_ways:  # what this call made is what it wrote into frames/: the second pass's frames
            spent, done_now = backward_pass()
            making += spent
    finally:
        behind.close()
    report = summarise_flicker(per_pair, per_frame)
    report["frames"] = total
    report["enhanced_now"] = done_now
    report["frames_per_second"] = done_now / making if done_now and making > 0 else None
    atomic_write(output / FLICKER_FILE, json.dumps(finite_for_json(report), indent=1).encode())

    video_path = sbs_path = None
    if video:
        video_path, sbs_path = output / VIDEO_FILE, output / SIDE_BY_SIDE_FILE
        with Mp4Writer(video_path, fps=fps, crf=quality) as enhanced_video, \
                Mp4Writer(sbs_path, fps=fps, crf=quality) as side_video:
            for t in range(total):
                enhanced = read_image(frame_dir / f"{t:05d}.png")
                render = read_image(pairs[t][0])
                enhanced_video.write(enhanced)
                side_video.write(side_by_side(render, enhanced))
    return PathResult(output=output, frames=total, enhanced_now=done_now, seconds=time.perf_counter() - start,
                      video=video_path, side_by_side=sbs_path, flicker=report, cached_views=enhancer.cached_views(),
                      warnings=warnings, enhance_seconds=making)


class _Background:
    """The one thread that reads frames ahead and writes enhanced ones behind (the module docstring)."""

    def __init__(self):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="roguenerf-path")
        self._writes: deque[Future] = deque()
        self._failed = False  # set by the thread: the writes after a failed one are not made

    def submit(self, fn, *args) -> Future:
        return self._pool.submit(fn, *args)

    def _write(self, path: Path, image: Tensor) -> None:
        from roguenerf.imageio import write_png

        if self._failed:  # frames stay in order on disk: none after one that was not written
            return
        try:
            write_png(path, image, strategy="rle")  # rle: the same pixels in a quarter of zlib's time
        except BaseException:
            self._failed = True
            raise

    def write(self, path: Path, image: Tensor) -> None:
        """Write ``image`` to ``path`` as an 8-bit PNG, atomically, behind; wait while more than
        :data:`WRITES_PENDING` are, and raise the error of a write that failed."""
        self._writes.append(self._pool.submit(self._write, path, image))
        while len(self._writes) > WRITES_PENDING or (self._writes and self._writes[0].done()):
            self._writes.popleft().result()

    def drain(self) -> None:
        """Wait for every write handed over; raise the first error."""
        while self._writes:
            self._writes.popleft().result()

    def close(self) -> None:
        """Wait for everything handed over (errors are :meth:`drain`'s to raise) and stop the thread."""
        self._pool.shutdown(wait=True)


def _quantise(image: Tensor) -> Tensor:
    """What an 8-bit PNG of ``image`` reads back as (flicker is measured on what was written)."""
    return (image.clamp(0, 1) * 255).round() / 255


def _match_views(scene, camera_path: CameraPath) -> list[int | None]:
    """Scene index of the view each path camera coincides with (same pose and intrinsics), or None."""
    poses = scene.poses()
    Ks = scene.intrinsics()
    extent = float((poses[:, :3, 3] - poses[:, :3, 3].mean(0)).norm(dim=-1).max()) or 1.0
    out: list[int | None] = []
    for pose, K in zip(camera_path.world_from_cam, camera_path.K):
        dt = (poses[:, :3, 3] - pose[:3, 3]).norm(dim=-1) / extent
        dr = (poses[:, :3, :3] - pose[:3, :3]).abs().amax(dim=(-2, -1))
        dk = (Ks - K).abs().amax(dim=(-2, -1))
        ok = (dt < POSE_MATCH_TOL) & (dr < POSE_MATCH_TOL) & (dk < 1e-3)
        hits = [i for i in ok.nonzero().flatten().tolist()
                if (scene.frames[i].width, scene.frames[i].height) == (camera_path.width, camera_path.height)
                and scene.frames[i].image_path is not None]
        out.append(hits[0] if hits else None)
    return out
