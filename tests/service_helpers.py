"""Shared parts of the service/worker tests: toy scenes as zips, tiny checkpoints, a live
uvicorn server on a free loopback port, worker processes, a throwaway redis-server.

Everything is real (HTTP over a socket, SQLite files, subprocesses); nothing is mocked.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent

FAST = dict(
    heartbeat_period=0.3,
    heartbeat_timeout=2.5,
    sweeper_period=0.5,
    worker_poll_max_delay=0.2,
    checkpoint_every_s=0.2,
    finetune_crop=32,
    finetune_batch=1,
    finetune_lr=3e-3,
    finetune_evaluate=False,
    drain_timeout=30.0,
)
"""Settings that make jobs, heartbeats and the sweeper fast enough for tests."""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(predicate, *, timeout: float, interval: float = 0.1, what: str = "condition"):
    """Poll ``predicate`` until it returns a truthy value; that value is returned."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last value: {last!r})")


# ----------------------------------------------------------------------------- library data
def splat_dataset(root: Path, *, views: int = 9, height: int = 36, width: int = 48, seed: int = 0) -> dict:
    """What a 3DGS user has: a COLMAP dataset (``images/`` + ``sparse/0/``) whose photos are a few
    hundred Gaussians' renders (on a wall and a box) plus a little noise, and the trained
    ``point_cloud.ply``. Returns ``dataset``, ``ply``, ``gaussians``, ``poses`` (OpenCV), ``K``."""
    import math

    import torch

    from roguenerf.data.colmap import write_colmap
    from roguenerf.data.toy import look_at
    from roguenerf.imageio import write_png
    from roguenerf.splats import Gaussians, logit, render, write_ply

    g = torch.Generator().manual_seed(seed)
    n = 300
    wall = torch.rand(n // 2, 3, generator=g) * torch.tensor([3.0, 0.05, 2.2]) + torch.tensor([-1.5, 1.5, -1.1])
    box = torch.rand(n - n // 2, 3, generator=g) * 0.8 + torch.tensor([-0.4, 0.0, -0.4])
    sh = torch.randn(n, 4, 3, generator=g) * 0.15
    sh[:, 0] = (torch.rand(n, 3, generator=g) - 0.5) * 2.5
    gaussians = Gaussians(means=torch.cat([wall, box]), sh=sh,
                          opacity=logit(torch.rand(n, generator=g) * 0.3 + 0.69),
                          log_scales=torch.log(torch.rand(n, 3, generator=g) * 0.12 + 0.08),
                          quats=torch.randn(n, 4, generator=g))
    ply = write_ply(root / "point_cloud.ply", gaussians)
    poses = []
    for i in range(views):
        a = math.radians(-25 + 50 * i / max(views - 1, 1))
        eye = torch.tensor([3.0 * math.sin(a), -3.0 * math.cos(a), 0.4], dtype=torch.float64)
        poses.append(look_at(eye, torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64)))
    poses = torch.stack(poses)
    K = torch.tensor([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]], dtype=torch.float64)
    dataset = root / "colmap"
    names = [f"view_{i:02d}.png" for i in range(views)]
    (dataset / "images").mkdir(parents=True)
    for i, name in enumerate(names):
        rgb, _, _ = render(gaussians, poses[i], K, height, width)
        write_png(dataset / "images" / name, (rgb + 0.03 * torch.randn(rgb.shape, generator=g)).clamp(0, 1))
    write_colmap(dataset / "sparse" / "0", names=names, K=K, world_from_cam=poses, widths=width, heights=height)
    return {"dataset": dataset, "ply": ply, "gaussians": gaussians, "poses": poses, "K": K}


def make_scene(root: Path, *, seed: int = 0, height: int = 48, width: int = 64, n_train: int = 6,
               n_test: int = 2):
    from roguenerf import make_toy_scene

    return make_toy_scene(root, seed=seed, n_train=n_train, n_test=n_test, height=height, width=width)


def make_checkpoint(path: Path, *, seed: int = 0) -> Path:
    """A tiny 'micro' enhancer (2 neighbours), randomly initialised with a fixed seed."""
    import torch

    from roguenerf import build_enhancer, save_checkpoint

    torch.manual_seed(seed)
    model = build_enhancer("micro", num_neighbours=2)
    return save_checkpoint(path, model)


def zip_folder(folder: Path, *, prefix: str | None = "scene") -> bytes:
    """Zip a scene folder the way `zip -r scene.zip scene/` does (one top-level folder)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            rel = path.relative_to(folder).as_posix()
            name = f"{prefix}/{rel}" if prefix else rel
            if path.is_file():
                zf.write(path, name)
    return buf.getvalue()


def path_zip(scene, *, seed: int, frames_per_segment: int = 2, drop_camera: bool = False, drop_frame: bool = False,
             opencv_axes: bool = False) -> tuple[bytes, int]:
    """A camera-path upload for ``POST /scenes/{id}/paths`` of a toy scene made with ``seed``: a
    nerfstudio camera_path.json through three of its views, rgb/ and depth/ of each frame.
    Broken on purpose: ``drop_camera`` leaves camera_path.json out, ``drop_frame`` frame 1's
    rgb, ``opencv_axes`` writes the poses in OpenCV axes (the user's axis mix-up). Returns
    (zip bytes, frame count)."""
    import math

    from roguenerf.data.toy import make_toy_world, render_toy_view
    from roguenerf.geometry import opencv_to_opengl
    from roguenerf.imageio import encode_npy, encode_png
    from roguenerf.trajectory import smooth_path

    world = make_toy_world(seed)
    height, width = scene.frames[0].height, scene.frames[0].width
    poses = smooth_path(scene.poses([0, 1, 2]), frames_per_segment)
    K = scene.frames[0].K
    fov = math.degrees(2 * math.atan(height / 2 / float(K[1, 1])))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        cams = []
        for t, pose in enumerate(poses):
            rgb, depth = render_toy_view(world, pose, K, height, width)
            if not (drop_frame and t == 1):
                zf.writestr(f"rgb/{t:04d}.png", encode_png((rgb * 0.9).clamp(0, 1)))
            zf.writestr(f"depth/{t:04d}.npy", encode_npy(depth[0].numpy()))
            gl = pose if opencv_axes else opencv_to_opengl(pose)
            cams.append({"camera_to_world": gl.flatten().tolist(), "fov": fov, "aspect": width / height})
        if not drop_camera:
            zf.writestr("camera_path.json", json.dumps({"render_height": height, "render_width": width, "fps": 10,
                                                        "camera_path": cams}))
    return buf.getvalue(), len(poses)


def view_request(scene, index: int) -> dict:
    """The /enhance form of one scene view: its render PNG, depth .npy and camera JSON."""
    from roguenerf.geometry import opencv_to_opengl

    frame = scene.frames[index]
    pose = opencv_to_opengl(frame.world_from_cam.to(__import__("torch").float64))
    K = frame.K
    camera = {
        "transform_matrix": pose.tolist(),
        "convention": "opengl",
        "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
        "depth_type": "z",
    }
    return {
        "render": Path(frame.render_path).read_bytes(),
        "depth": Path(frame.depth_path).read_bytes(),
        "camera": camera,
    }


def enhance(client: httpx.Client, scene_id: str, view: dict, **extra) -> httpx.Response:
    files = {
        "render": ("render.png", view["render"], "image/png"),
        "depth": ("depth.npy", view["depth"], "application/octet-stream"),
    }
    data = {"scene_id": scene_id, "camera": json.dumps(view["camera"]), **extra}
    return client.post("/enhance", files=files, data=data)


def register(client: httpx.Client, archive: bytes, checkpoint: bytes | None = None) -> httpx.Response:
    files = {"archive": ("scene.zip", archive, "application/zip")}
    if checkpoint is not None:
        files["checkpoint"] = ("model.safetensors", checkpoint, "application/octet-stream")
    return client.post("/scenes", files=files)


def wait_job(client: httpx.Client, job_id: str, states, *, timeout: float) -> dict:
    states = {states} if isinstance(states, str) else set(states)

    def done():
        job = client.get(f"/jobs/{job_id}").json()
        return job if job["state"] in states else None

    return wait_until(done, timeout=timeout, interval=0.2, what=f"job {job_id} to reach {sorted(states)}")


# ----------------------------------------------------------------------------- processes
class LiveServer:
    """uvicorn serving ``create_app(settings)`` in a thread on a free loopback port."""

    def __init__(self, settings):
        import uvicorn

        from service.app import create_app

        self.settings = settings
        self.app = create_app(settings)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(uvicorn.Config(self.app, host="127.0.0.1", port=self.port,
                                                    log_level="warning", lifespan="on"))
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)

    def __enter__(self) -> LiveServer:
        self.thread.start()
        wait_until(lambda: self.server.started, timeout=60, what="uvicorn startup")
        return self

    def client(self, **kwargs) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=120, **kwargs)

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(30)


def children_of(pid: int) -> list[int]:
    """The child processes of ``pid`` (Linux /proc)."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text().split()
        out += [int(x) for x in text]
    return out


def alive(pid: int) -> bool:
    """``pid`` runs (a zombie does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


class EmbeddedServer:
    """``service.server.run`` (API + sibling worker) in its own process on a free loopback port,
    with ``FAST`` and ``settings`` as its ``ROGUENERF_*`` environment; output to ``log_path``.
    Entered, it waits until ``ready`` (a route) answers 200 (``started_s``: how long that took);
    on exit it stops it with SIGINT (API and worker stop cleanly), kills it after 60 s, and kills
    a worker still alive."""

    def __init__(self, data_dir: Path, *, log_path: Path, ready: str = "/healthz", **settings):
        self.data_dir, self.log_path, self.ready = data_dir, log_path, ready
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("ROGUENERF_")}
        self.env.update({f"ROGUENERF_{k.upper()}": str(v) for k, v in {**FAST, **settings}.items()})
        self.env["PYTHONPATH"] = str(ROOT)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> EmbeddedServer:
        self.log = open(self.log_path, "wb")
        started = time.perf_counter()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "from service.server import run; "
             f"run(host='127.0.0.1', port={self.port}, data_dir={str(self.data_dir)!r})"],
            env=self.env, cwd=ROOT, stdout=self.log, stderr=subprocess.STDOUT)

        def up():
            try:
                return httpx.get(f"{self.url}{self.ready}", timeout=2).status_code == 200
            except httpx.HTTPError:
                return self.proc.poll() is not None

        try:
            wait_until(up, timeout=120, interval=0.05, what=f"embedded server {self.ready}")
            assert self.proc.poll() is None, self.log_path.read_text()
        except BaseException:
            self.__exit__()
            raise
        self.started_s = time.perf_counter() - started
        return self

    def __exit__(self, *exc) -> None:
        proc = self.proc
        children = children_of(proc.pid) if alive(proc.pid) else []
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
        for child in children:
            if alive(child):
                os.kill(child, signal.SIGKILL)
        self.log.close()


class WorkerProcess:
    """``python -m workers`` as a separate process with the given settings."""

    def __init__(self, settings, log_path: Path):
        env = {k: v for k, v in os.environ.items() if not k.startswith("ROGUENERF_")}
        env.update(settings.env())
        env["PYTHONPATH"] = str(ROOT)
        self.log_path = log_path
        self._log = open(log_path, "ab")
        self.proc = subprocess.Popen([sys.executable, "-m", "workers"], env=env, cwd=ROOT,
                                     stdout=self._log, stderr=subprocess.STDOUT)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_ready(self, timeout: float = 90) -> None:
        wait_until(lambda: "worker ready" in self.log() or self.proc.poll() is not None,
                   timeout=timeout, what="worker startup")
        assert self.proc.poll() is None, f"worker exited early:\n{self.log()}"

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def interrupt(self, timeout: float = 60) -> int:
        self.proc.send_signal(signal.SIGINT)
        return self.proc.wait(timeout)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._log.close()


@contextlib.contextmanager
def redis_server(tmp: Path):
    """Debian's redis-server on a free loopback port, no persistence, in ``tmp``."""
    exe = shutil.which("redis-server")
    if exe is None:
        import pytest

        pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
    port = free_port()
    proc = subprocess.Popen([exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "",
                             "--appendonly", "no", "--dir", str(tmp)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    try:
        def up():
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2) as s:
                s.sendall(b"PING\r\n")
                return s.recv(16).startswith(b"+PONG")
            return False

        wait_until(up, timeout=20, what="redis-server")
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        proc.terminate()
        proc.wait(10)


def tree_digest(folder: Path) -> dict[str, int]:
    """{relative path: size} of every file: compares a scene folder before and after."""
    return {p.relative_to(folder).as_posix(): p.stat().st_size for p in sorted(folder.rglob("*")) if p.is_file()}


def toy_upload(root: Path, **scene) -> dict:
    """A toy scene under ``root`` (``make_scene``'s arguments in ``scene``) with what a test
    uploads: ``folder`` (the scene folder), ``scene``, its ``zip`` bytes and the same written as
    ``zip_file``, a micro checkpoint ``ckpt`` (its path) and ``checkpoint`` (its bytes)."""
    folder = root / "scene"
    loaded = make_scene(folder, **scene)
    archive = zip_folder(folder)
    (root / "scene.zip").write_bytes(archive)
    ckpt = make_checkpoint(root / "micro.safetensors")
    return {"folder": folder, "scene": loaded, "zip": archive, "zip_file": root / "scene.zip", "ckpt": ckpt,
            "checkpoint": ckpt.read_bytes()}


def get_job(client: httpx.Client, job_id: str) -> dict:
    return client.get(f"/jobs/{job_id}").json()


def _postgres_bin() -> Path | None:
    """The folder with Debian's initdb / postgres (not on PATH there), or PATH's."""
    import glob

    found = shutil.which("initdb")
    if found:
        return Path(found).resolve().parent
    versions = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"),
                      key=lambda p: int(Path(p).parts[-3]) if Path(p).parts[-3].isdigit() else 0)
    return Path(versions[-1]).parent if versions else None


class PostgresServer:
    """A throwaway PostgreSQL server on a free loopback port, its cluster in a temp dir.

    Trust authentication on 127.0.0.1 only, no Unix socket, fsync off (a test server).
    As root the server runs as the ``postgres`` user (postgres refuses root).
    :meth:`new_database` gives each test its own database.
    """

    def __init__(self):
        import pwd
        import tempfile

        bindir = _postgres_bin()
        if bindir is None:
            import pytest

            message = "PostgreSQL is not installed (apt-get install -y postgresql; ./dev test does it)"
            if os.environ.get("CI"):
                pytest.fail(message)
            pytest.skip(message)
        self.bindir = bindir
        self.root = Path(tempfile.mkdtemp(prefix="roguenerf-pg-"))
        self.user = None
        if os.geteuid() == 0:
            self.user = "postgres"
            pw = pwd.getpwnam("postgres")
            os.chown(self.root, pw.pw_uid, pw.pw_gid)
        self.data = self.root / "cluster"
        self.port = free_port()
        self.log_path = self.root / "server.log"
        self.proc = None
        self._dbs = 0

    def _run(self, *args: str) -> None:
        subprocess.run([str(self.bindir / args[0]), *args[1:]], check=True, user=self.user,
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=self.root)

    def start(self) -> PostgresServer:
        self._run("initdb", "-D", str(self.data), "-U", "roguenerf", "--auth=trust", "-E", "UTF8",
                  "--no-sync", "--locale=C")
        log = open(self.log_path, "ab")
        try:
            self.proc = subprocess.Popen(
                [str(self.bindir / "postgres"), "-D", str(self.data), "-p", str(self.port),
                 "-c", "listen_addresses=127.0.0.1", "-c", "unix_socket_directories=",
                 "-c", "fsync=off", "-c", "synchronous_commit=off", "-c", "full_page_writes=off",
                 "-c", "max_connections=200", "-c", "shared_buffers=32MB"],
                user=self.user, stdout=log, stderr=subprocess.STDOUT, cwd=self.root)
        finally:
            log.close()
        import psycopg

        def up():
            if self.proc.poll() is not None:
                raise RuntimeError(f"postgres exited:\n{self.log_path.read_text(errors='replace')}")
            try:
                with psycopg.connect(self.url("postgres"), connect_timeout=2):
                    return True
            except psycopg.OperationalError:
                return False

        wait_until(up, timeout=60, interval=0.2, what="postgres")
        return self

    def url(self, database: str) -> str:
        return f"postgresql://roguenerf@127.0.0.1:{self.port}/{database}"

    def new_database(self) -> str:
        """A fresh, empty database; returns its URL."""
        import psycopg

        self._dbs += 1
        name = f"t{os.getpid()}_{self._dbs}"
        with psycopg.connect(self.url("postgres"), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGQUIT)  # immediate shutdown: a throwaway cluster
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> PostgresServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
