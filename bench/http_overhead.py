"""What HTTP ``POST /enhance`` adds to the library call, for one 504 x 378 render.

    python -m bench.http_overhead --output bench/results/http_overhead.csv [--repeats 15]
                                  [--warmup 2] [--checkpoint PATH] [--no-breakdown]

Writes ``http_overhead.csv`` (one row per quantity: median, quartiles, min, max), ``.json``
(the same plus every sample, the server's log tail and the breakdown) and ``.png`` (bar chart)
next to ``--output``; every file carries date, machine and commit (``bench.common.stamp``).

Set-up (everything real, nothing mocked):

* A toy scene of 504 x 378 (``make_toy_scene``: seed 3, 2 training + 1 test view, as in
  ``tests/service/test_service_flow.py::test_enhance_bit_for_bit_and_latency_504x378``).
* The service as a subprocess, started like ``./dev serve`` / the end-to-end tests:
  ``service.server.run(host="127.0.0.1", port=<free>, data_dir=<temporary>)`` with embedded
  defaults (every ``ROGUENERF_*`` variable removed; the API and its sibling worker start, the
  worker idles). The scene is registered over HTTP. Checkpoint: by default none is uploaded,
  so the service uses the bundled default (``roguenerf/weights/default.safetensors``), exactly
  as for a user's scene; ``--checkpoint PATH`` uploads PATH instead (e.g. a micro one).
* In this process the same library objects: ``load_scene(<the toy folder>)``, the same
  checkpoint file, ``SceneEnhancer(scene, model)``.

Compared, alternating (HTTP, library, HTTP, library, ...) so both see the same machine load,
each after ``--warmup`` untimed calls (the first /enhance builds the server's SceneEnhancer and
encodes the neighbour photos; the first library call does the same here):

* **HTTP round trip**: ``httpx.Client.post("/enhance", files=render PNG + depth .npy,
  data=scene_id + camera JSON)`` on a kept-alive loopback connection, until the whole PNG
  body is received. Client-side multipart encoding and response reading are included: a
  user pays them.
* **library call**: what a Python user does with the same bytes: ``read_image(render
  bytes)``, ``read_depth(npy bytes)``, intrinsics + OpenGL->OpenCV pose from the same camera
  JSON, ``SceneEnhancer.enhance``, ``write_png(None, image)`` (library default PNG level).
* **library enhance**: the ``SceneEnhancer.enhance`` part of that call alone.
* **server enhance** / **server total**: the ``X-Enhance-Seconds`` (enhance inside the
  server) and ``X-Total-Seconds`` (handler start -> response built) headers.

Summary (medians):

* ``overhead = http_median / library_call_median - 1``: the issue's criterion, "HTTP /enhance
  adds at most 10 % to the library call". The service compresses its answers faster than
  ``write_png``'s default (``service.routers.enhance.RESPONSE_PNG``), so this can be negative.
* the same against "the same work": the library call with its PNG encoded the way the
  service encodes its answers: what HTTP adds to identical work.
* the median of the per-pair ratios.
* "HTTP-only seconds": per pair, (HTTP - server enhance) - (same work - library enhance), each
  side's enhance time taken from its own ``EnhanceResult.seconds``: what HTTP adds, without
  any difference in compute speed between the two processes (which under load swings a few
  % either way from run to run and would otherwise be counted as HTTP overhead); also as a
  share of the library call.

The two PNGs' bytes differ (different compression), so every HTTP answer is checked to decode
to exactly the pixels of the library call's PNG; the run exits 1 if one does not.

The breakdown (skip with ``--no-breakdown``) attributes the difference: a GET /healthz round
trip; the full upload to /enhance with an unknown scene id (body transfer, uvicorn, multipart
parsing, form validation, scene lookup in a thread, JSON 404: everything HTTP costs except
the computation); client-side multipart encoding; Starlette's multipart parser on the same
body in this process; one thread-pool hop; the service's decoders and checks; PNG encoding
with the library's defaults and as the service answers; and handler time outside enhance
(X-Total - X-Enhance).

Threads: the service sets no torch thread count, so both sides run with torch's default
(the launcher prints the server's ``torch.get_num_threads()`` and the run stops if it
differs from this process's; OMP_NUM_THREADS etc. are inherited by the server).

Caveats:

* Client, server and library share the machine's cores; run on an otherwise idle machine.
  The pairs alternate, so slow drift hits both sides alike, but not a burst in one call.
* Loopback only: no network latency or bandwidth (the upload is ~0.9 MB, the answer
  ~0.14 MB); a real network adds their transfer time.
* The server's worker process is idle but polls its SQLite queue (a few ms every 2 s).
* Under load (e.g. other jobs on the cores) the enhance times of the two processes differ by
  several % from run to run, in either direction: trust "HTTP-only seconds" then, and take
  the ratios from an idle machine.
* The toy scene has 2 training views (2 neighbours: the default checkpoint's count); a scene
  with more photos changes the enhance time, not the HTTP overhead in seconds.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from bench.common import REPO, RESULTS, beside, stamp, write_csv, write_json

HEIGHT, WIDTH = 378, 504
SCENE_SEED = 3
UNKNOWN_SCENE = "0" * 32
"""A well-formed scene id that is never registered: /enhance parses the whole upload and
looks it up, then answers 404."""


# ----------------------------------------------------------------------------- helpers
def _quantiles(xs: list[float]) -> dict:
    xs = sorted(xs)
    if not xs:
        return {"median": None, "p25": None, "p75": None, "min": None, "max": None, "n": 0}
    q = statistics.quantiles(xs, n=4, method="inclusive") if len(xs) > 1 else [xs[0]] * 3
    return {"median": statistics.median(xs), "p25": q[0], "p75": q[2], "min": xs[0], "max": xs[-1],
            "n": len(xs)}


def _timed(fn, n: int) -> tuple[list[float], object]:
    out, last = [], None
    for _ in range(n):
        t0 = time.perf_counter()
        last = fn()
        out.append(time.perf_counter() - t0)
    return out, last


def _ms(x: float | None) -> str:
    return "n/a" if x is None else f"{1000 * x:8.1f} ms"


class Service:
    """``service.server.run`` in a subprocess on a free loopback port (like ``./dev serve``)."""

    def __init__(self, data_dir: Path, log_path: Path):
        from tests.service_helpers import free_port

        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = log_path
        env = {k: v for k, v in os.environ.items() if not k.startswith("ROGUENERF_")}
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH")) if p)
        code = ("import torch; print('bench: server torch threads', torch.get_num_threads(), flush=True)\n"
                "from service.server import run\n"
                f"run(host='127.0.0.1', port={self.port}, data_dir={str(data_dir)!r})\n")
        self._log = open(log_path, "wb")
        self.proc = subprocess.Popen([sys.executable, "-c", code], env=env, cwd=REPO,
                                     stdout=self._log, stderr=subprocess.STDOUT)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_ready(self, timeout: float = 120) -> float:
        import httpx

        t0 = time.perf_counter()
        while time.perf_counter() - t0 < timeout:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the service exited with {self.proc.returncode}:\n{self.log()[-4000:]}")
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return time.perf_counter() - t0
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise RuntimeError(f"the service was not ready after {timeout} s:\n{self.log()[-4000:]}")

    def torch_threads(self) -> int | None:
        for line in self.log().splitlines():
            if line.startswith("bench: server torch threads"):
                return int(line.split()[-1])
        return None

    def stop(self) -> None:
        """Ctrl-C, as a user stops ``./dev serve`` (the API then drains its worker)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()  # the worker has --exit-with-parent
                self.proc.wait(10)
        self._log.close()


# ----------------------------------------------------------------------------- the two calls
def library_call(enhancer, view: dict) -> tuple[bytes, object, dict]:
    """A Python user's call with the same bytes; returns (PNG, EnhanceResult, stage seconds)."""
    from roguenerf.geometry import intrinsics_matrix, opengl_to_opencv
    from roguenerf.imageio import read_depth, read_image, write_png

    t0 = time.perf_counter()
    render = read_image(view["render"])
    depth = read_depth(view["depth"])
    cam = view["camera"]
    K = intrinsics_matrix(cam["fl_x"], cam["fl_y"], cam["cx"], cam["cy"], dtype=torch.float64)
    pose = opengl_to_opencv(torch.tensor(cam["transform_matrix"], dtype=torch.float64))
    t1 = time.perf_counter()
    result = enhancer.enhance(render, depth, K, pose)
    t2 = time.perf_counter()
    png = write_png(None, result.image)
    t3 = time.perf_counter()
    return png, result, {"decode": t1 - t0, "enhance": t2 - t1, "encode": t3 - t2, "total": t3 - t0}


def http_call(client, scene_id: str, view: dict):
    from tests.service_helpers import enhance

    t0 = time.perf_counter()
    r = enhance(client, scene_id, view)
    _ = r.content
    return r, time.perf_counter() - t0


def _service_png() -> dict:
    """The encode_png options of the service's answers ({} = the library defaults)."""
    from service.routers import enhance as enhance_route

    return dict(getattr(enhance_route, "RESPONSE_PNG", {}))


def _pixels(png: bytes):
    from roguenerf.imageio import read_image

    return read_image(png)


# ----------------------------------------------------------------------------- breakdown
def breakdown(client, scene_id: str, view: dict, result_image, n: int) -> dict:
    """Seconds of the HTTP-side pieces, each measured on its own (medians of ``n``)."""
    import httpx
    from starlette.datastructures import Headers
    from starlette.formparsers import MultiPartParser

    from roguenerf.imageio import encode_png, read_depth, read_image
    from service.app import FORM_LIMITS
    from service.limits import check_depth_coverage, decode_field
    from service.routers import enhance as enhance_route
    from service.settings import Settings
    from tests.service_helpers import enhance

    out: dict[str, dict] = {}

    def put(name: str, samples: list[float], what: str) -> None:
        out[name] = {**_quantiles(samples), "what": what}

    samples, r = _timed(lambda: client.get("/healthz"), n)
    assert r.status_code == 200, r.text
    put("healthz_round_trip", samples, "GET /healthz over the same kept-alive connection")

    samples, r = _timed(lambda: enhance(client, UNKNOWN_SCENE, view), n)
    assert r.status_code == 404, r.text
    put("upload_404_round_trip", samples,
        "POST /enhance with the same files and an unknown scene id: upload, uvicorn/h11, multipart "
        "parse, form validation, scene lookup in a thread, JSON 404 (no decode, no compute)")

    files = {"render": ("render.png", view["render"], "image/png"),
             "depth": ("depth.npy", view["depth"], "application/octet-stream")}
    data = {"scene_id": scene_id, "camera": json.dumps(view["camera"])}
    builder = httpx.Client(base_url="http://127.0.0.1:1")

    def build():
        request = builder.build_request("POST", "/enhance", files=files, data=data)
        return request, b"".join(request.stream)

    samples, (request, body) = _timed(build, n)
    builder.close()
    put("client_multipart_encode", samples, f"httpx builds the {len(body)}-byte multipart body")

    chunk = 65536  # what uvicorn hands the app per receive() at most, roughly

    async def parse():
        async def stream():
            for i in range(0, len(body), chunk):
                yield body[i:i + chunk]

        parser = MultiPartParser(Headers(raw=[(b"content-type", request.headers["content-type"].encode())]),
                                 stream(), **FORM_LIMITS)
        form = await parser.parse()
        got = (await form["render"].read(), await form["depth"].read())
        await form.close()
        return got

    async def parse_many():
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            got = await parse()
            times.append(time.perf_counter() - t0)
        return times, got

    samples, (render_bytes, depth_bytes) = asyncio.run(parse_many())
    assert render_bytes == view["render"] and depth_bytes == view["depth"]
    put("server_multipart_parse", samples, "Starlette's MultiPartParser (app limits) on that body, "
        "64 KiB chunks, plus UploadFile.read() of both parts, in this process")

    async def hops():
        from fastapi.concurrency import run_in_threadpool

        await run_in_threadpool(lambda: None)
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            await run_in_threadpool(lambda: None)
            times.append(time.perf_counter() - t0)
        return times

    put("threadpool_hop", asyncio.run(hops()), "one run_in_threadpool round trip (the route makes two)")

    limit = Settings().max_upload_pixels
    samples, _ = _timed(lambda: decode_field("render", read_image, view["render"], max_pixels=limit), n)
    put("decode_render", samples, "read_image of the render PNG (same in the library call)")
    samples, depth = _timed(lambda: decode_field("depth", read_depth, view["depth"], scale=1.0,
                                                 max_pixels=limit), n)
    put("decode_depth", samples, "read_depth of the .npy (same in the library call)")

    def checks():
        camera = enhance_route.parse_camera(json.dumps(view["camera"]))
        enhance_route.camera_tensors(camera)
        check_depth_coverage(depth)

    samples, _ = _timed(checks, n)
    put("service_checks", samples, "camera JSON parse + validation, pose/intrinsics checks, depth coverage")

    service_png = _service_png()
    samples, png6 = _timed(lambda: encode_png(result_image), n)
    put("encode_png_library_default", samples, f"encode_png with the library's defaults ({len(png6)} bytes)")
    samples, png_s = _timed(lambda: encode_png(result_image, **service_png), n)
    put("encode_png_service", samples, f"encode_png as the service answers, {service_png} ({len(png_s)} bytes)")
    out["_sizes"] = {"request_body_bytes": len(body), "png_library_default_bytes": len(png6),
                     "png_service_bytes": len(png_s), "service_png": service_png}
    return out


# ----------------------------------------------------------------------------- plot
def plot(path: Path, summary: dict, meta: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ["library enhance", "library call total", "HTTP round trip"]
    keys = ["library_enhance_s", "library_call_s", "http_round_trip_s"]
    med = [summary[k]["median"] for k in keys]
    lo = [m - summary[k]["p25"] for m, k in zip(med, keys)]
    hi = [summary[k]["p75"] - m for m, k in zip(med, keys)]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    bars = ax.bar(names, med, yerr=[lo, hi], capsize=4, color=["#9ab", "#579", "#c75"])
    for bar, m, up in zip(bars, med, hi):
        ax.text(bar.get_x() + bar.get_width() / 2, m + up, f"{m * 1000:.0f} ms", ha="center", va="bottom",
                fontsize=9)
    budget = 1.10 * summary["library_call_s"]["median"]
    ax.axhline(budget, color="k", ls="--", lw=1, label="library call + 10 %")
    ax.set_ylabel("seconds (median, bars: quartiles)")
    ax.legend(loc="lower right", fontsize=8)
    o = summary["overhead"]
    ax.set_title(f"POST /enhance {WIDTH}x{HEIGHT}: HTTP adds {o['vs_library_call']:+.1%} to the library call, "
                 f"{o['vs_library_same_work']:+.1%} to the same work\n({meta['repeats']} alternating pairs, "
                 f"{meta['torch_threads']} torch threads both sides)", fontsize=9)
    fig.suptitle(f"{meta['date']} - {meta['commit']}\n{meta['machine']}", fontsize=7, y=0.995)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--output", type=Path, default=RESULTS / "http_overhead.csv",
                   help="CSV to write; .json and .png go next to it")
    p.add_argument("--repeats", type=int, default=15, help="timed (HTTP, library) pairs")
    p.add_argument("--warmup", type=int, default=2, help="untimed calls of each kind first")
    p.add_argument("--checkpoint", type=Path, default=None,
                   help="upload this checkpoint with the scene (default: none, the service uses the "
                        "bundled default)")
    p.add_argument("--no-breakdown", action="store_true", help="skip the per-piece breakdown")
    args = p.parse_args(argv)
    if args.repeats < 1 or args.warmup < 1:
        p.error("--repeats and --warmup must be >= 1 (the first /enhance builds the server's cache)")

    import httpx

    from roguenerf import SceneEnhancer, load_checkpoint, load_scene
    from roguenerf.imageio import encode_png
    from tests.service_helpers import make_checkpoint, make_scene, register, view_request, zip_folder

    service_png = _service_png()
    threads = torch.get_num_threads()
    meta = {**stamp(), "torch_threads": threads, "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "default"),
            "repeats": args.repeats, "warmup": args.warmup,
            "size": f"{WIDTH}x{HEIGHT}", "service_png": service_png}
    print(f"{meta['date']}  {meta['commit']}  {meta['machine']}", flush=True)

    with tempfile.TemporaryDirectory(prefix="roguenerf-http-bench-") as tmp:
        tmp = Path(tmp)
        make_scene(tmp / "scene", seed=SCENE_SEED, height=HEIGHT, width=WIDTH, n_train=2, n_test=1)
        scene = load_scene(tmp / "scene")
        view_index = scene.indices("test")[0]
        view = view_request(scene, view_index)

        if args.checkpoint is not None:
            ckpt, upload = args.checkpoint, args.checkpoint.read_bytes()
        else:
            from roguenerf import default_checkpoint_path

            ckpt = Path(default_checkpoint_path(must_exist=False))
            upload = None
            if not ckpt.is_file():  # no bundled default: a micro checkpoint, as the tests use
                ckpt = make_checkpoint(tmp / "micro.safetensors", seed=1)
                upload = ckpt.read_bytes()
        meta["checkpoint"] = (f"{ckpt.name} (uploaded with the scene)" if upload is not None
                              else f"{ckpt} (the service's bundled default; nothing uploaded)")

        service = Service(tmp / "data", tmp / "server.log")
        try:
            meta["service_start_to_ready_s"] = round(service.wait_ready(), 3)
            server_threads = service.torch_threads()
            meta["server_torch_threads"] = server_threads
            if server_threads != threads:
                raise SystemExit(f"torch threads differ: server {server_threads}, benchmark {threads}; "
                                 "the comparison would not be fair")
            print(f"service ready in {meta['service_start_to_ready_s']} s at {service.url}; torch threads: "
                  f"{threads} here and in the server (torch default, the service sets none)", flush=True)

            with httpx.Client(base_url=service.url, timeout=600) as client:
                r = register(client, zip_folder(tmp / "scene"), upload)
                if r.status_code != 201:
                    raise SystemExit(f"registering the scene failed: {r.status_code} {r.text}")
                scene_id = r.json()["id"]

                model, _ = load_checkpoint(ckpt)
                enhancer = SceneEnhancer(scene, model)
                for _ in range(args.warmup):
                    r, _ = http_call(client, scene_id, view)
                    if r.status_code != 200:
                        raise SystemExit(f"/enhance failed: {r.status_code} {r.text}")
                    library_call(enhancer, view)

                samples = {k: [] for k in ("http_round_trip_s", "server_enhance_s", "server_total_s",
                                           "library_call_s", "library_enhance_s", "library_decode_s",
                                           "library_encode_s", "library_encode_service_png_s",
                                           "library_same_work_s", "http_added_s", "pair_ratio")}
                pixels_identical = bytes_identical = True
                http_bytes = 0
                lib_png = None
                result = None
                for i in range(args.repeats):
                    r, http_s = http_call(client, scene_id, view)
                    if r.status_code != 200:
                        raise SystemExit(f"/enhance failed: {r.status_code} {r.text}")
                    lib_png, result, t = library_call(enhancer, view)
                    t0 = time.perf_counter()
                    encode_png(result.image, **service_png)
                    enc_service = time.perf_counter() - t0
                    same = torch.equal(_pixels(r.content), _pixels(lib_png))
                    pixels_identical &= same
                    bytes_identical &= r.content == lib_png
                    http_bytes = len(r.content)
                    samples["http_round_trip_s"].append(http_s)
                    samples["server_enhance_s"].append(float(r.headers["X-Enhance-Seconds"]))
                    samples["server_total_s"].append(float(r.headers["X-Total-Seconds"]))
                    samples["library_call_s"].append(t["total"])
                    samples["library_enhance_s"].append(t["enhance"])
                    samples["library_decode_s"].append(t["decode"])
                    samples["library_encode_s"].append(t["encode"])
                    samples["library_encode_service_png_s"].append(enc_service)
                    samples["library_same_work_s"].append(t["total"] - t["encode"] + enc_service)
                    samples["pair_ratio"].append(http_s / t["total"] - 1)
                    # Everything but enhance on each side (each side's own EnhanceResult.seconds),
                    # so a difference in compute speed between the two processes cancels out.
                    samples["http_added_s"].append((http_s - samples["server_enhance_s"][-1])
                                                   - (samples["library_same_work_s"][-1] - result.seconds))
                    print(f"pair {i + 1:2d}/{args.repeats}: HTTP {_ms(http_s)} (server enhance "
                          f"{_ms(samples['server_enhance_s'][-1])}), library {_ms(t['total'])} (enhance "
                          f"{_ms(t['enhance'])}), pixels {'identical' if same else 'DIFFER'}", flush=True)
                    if not same:
                        print("ERROR: the HTTP answer's pixels differ from the library call's", flush=True)

                parts = None
                if not args.no_breakdown:
                    parts = breakdown(client, scene_id, view, result.image, max(20, args.repeats))
                client.delete(f"/scenes/{scene_id}")
        finally:
            service.stop()
            server_log = service.log()

    summary = {k: _quantiles(v) for k, v in samples.items()}
    med = {k: v["median"] for k, v in summary.items()}
    diffs = {
        "handler_outside_enhance_s": [t - e for t, e in zip(samples["server_total_s"], samples["server_enhance_s"])],
        "outside_handler_s": [h - t for h, t in zip(samples["http_round_trip_s"], samples["server_total_s"])],
        "http_minus_library_s": [h - lc for h, lc in zip(samples["http_round_trip_s"], samples["library_call_s"])],
    }
    summary.update({k: _quantiles(v) for k, v in diffs.items()})
    summary["overhead"] = {
        "vs_library_call": med["http_round_trip_s"] / med["library_call_s"] - 1,
        "vs_library_same_work": med["http_round_trip_s"] / med["library_same_work_s"] - 1,
        "pair_ratio_median": med["pair_ratio"],
        "http_added_vs_library_call": med["http_added_s"] / med["library_call_s"],
        "server_enhance_vs_library_enhance": med["server_enhance_s"] / med["library_enhance_s"] - 1,
    }
    summary["checks"] = {"pixels_identical": pixels_identical, "bytes_identical": bytes_identical,
                         "http_png_bytes": http_bytes, "library_png_bytes": len(lib_png),
                         "view": scene.frames[view_index].name,
                         "render_bytes": len(view["render"]), "depth_bytes": len(view["depth"])}

    # ------------------------------------------------------------------ report
    o = summary["overhead"]
    print(f"\nPOST /enhance {WIDTH}x{HEIGHT}, {args.repeats} alternating pairs, torch threads {threads} "
          f"(both sides), checkpoint {meta['checkpoint']}")
    for key, label in [("library_enhance_s", "library enhance"),
                       ("library_call_s", "library call (decode + enhance + write_png)"),
                       ("library_same_work_s", "  same, PNG encoded as the service does"),
                       ("http_round_trip_s", "HTTP round trip"),
                       ("server_enhance_s", "  server X-Enhance-Seconds"),
                       ("server_total_s", "  server X-Total-Seconds"),
                       ("handler_outside_enhance_s", "  handler outside enhance"),
                       ("outside_handler_s", "  outside the handler"),
                       ("http_minus_library_s", "HTTP - library (per pair)"),
                       ("http_added_s", "HTTP-only seconds (enhance removed)")]:
        s = summary[key]
        print(f"  {label:44s} median {_ms(s['median'])}   [{_ms(s['p25'])} .. {_ms(s['p75'])}]")
    print(f"  overhead vs library call:   {o['vs_library_call']:+.1%}  (median ratio; per-pair median "
          f"{o['pair_ratio_median']:+.1%}; criterion <= +10 %)")
    print(f"  overhead vs the same work:  {o['vs_library_same_work']:+.1%}")
    print(f"  HTTP-only seconds / library call: {o['http_added_vs_library_call']:+.1%}  (same work on both "
          "sides, each side's enhance time removed)")
    print(f"  server enhance vs library enhance: {o['server_enhance_vs_library_enhance']:+.1%}")
    c = summary["checks"]
    print(f"  pixels identical: {c['pixels_identical']}; PNG bytes identical: {c['bytes_identical']} "
          f"(HTTP {c['http_png_bytes']} B, library {c['library_png_bytes']} B)")
    if parts:
        print("breakdown (medians, each piece measured alone):")
        for name, s in parts.items():
            if not name.startswith("_"):
                print(f"  {name:30s} {_ms(s['median'])}  {s['what']}")

    # ------------------------------------------------------------------ files
    out = beside(args.output, ".csv")
    base = {k: meta[k] for k in ("date", "machine", "commit", "torch_threads", "omp_wait_policy", "size", "repeats")}
    rows = []
    for key, s in summary.items():
        if key in ("overhead", "checks"):
            continue
        rows.append({**base, "quantity": key, "unit": "ratio" if key == "pair_ratio" else "s",
                     **{k: (round(v, 5) if isinstance(v, float) else v) for k, v in s.items()}})
    for key, v in summary["overhead"].items():
        rows.append({**base, "quantity": f"overhead_{key}", "unit": "ratio", "median": round(v, 5)})
    for name, s in (parts or {}).items():
        if not name.startswith("_"):
            rows.append({**base, "quantity": f"breakdown_{name}", "unit": "s",
                         **{k: (round(v, 6) if isinstance(v, float) else v) for k, v in s.items()
                            if k != "what"}})
    write_csv(out, rows)
    write_json(beside(out, ".json"), {**meta, "summary": summary, "breakdown": parts,
                                          "samples": samples,
                                          "server_log_tail": server_log.splitlines()[-30:]})
    plot(beside(out, ".png"), summary, meta)
    print(f"wrote {out}, {beside(out, '.json')}, {beside(out, '.png')}")
    return 0 if pixels_identical else 1


if __name__ == "__main__":
    sys.exit(main())
