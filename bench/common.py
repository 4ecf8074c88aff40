"""Shared helpers of the benchmarks: where the data is, what machine and commit ran, CSV out.

Every row a benchmark writes carries date, machine and commit, and speed next to error.
"""

from __future__ import annotations

import contextlib
import csv
import datetime as _dt
import json
import os
import platform
import subprocess
import tempfile
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("ROGUENERF_SHARED_DATA", REPO.parent / "shared" / "data"))
LEGO = SHARED_DATA / "lego"
RESULTS = REPO / "bench" / "results"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> str:
    """One line: CPU (or GPU), cores, torch threads, torch version, the CPU kernels torch picked.

    The kernel level (AVX2, AVX512) tells apart machines that report the same CPU name: two
    "Intel(R) Xeon(R) Processor" machines here differed 1.7x in matmul peak.
    """
    gpu = f", {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""
    try:
        isa = f" ({torch.backends.cpu.get_cpu_capability()} kernels)"
    except (AttributeError, RuntimeError):
        isa = ""
    return (f"{_cpu_model()} x{os.cpu_count()} ({torch.get_num_threads()} threads){gpu}, "
            f"torch {torch.__version__}{isa}, {platform.system()} {platform.machine()}")


def commit() -> str:
    """Short hash of HEAD, with "-dirty" when the work tree has changes (read-only git calls)."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                              text=True, timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return head + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


@contextlib.contextmanager
def older_tree(revision: str):
    """``revision`` checked out into a temporary git worktree: yields ``(path, short hash)``, and
    removes the worktree after. Raises SystemExit (as ``--before``'s error) when it is not a revision."""
    rev = subprocess.run(["git", "rev-parse", "--short", revision], cwd=REPO, capture_output=True, text=True)
    if rev.returncode != 0:
        raise SystemExit(f"--before: {revision!r} is not a revision of this repository")
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "before"
        subprocess.run(["git", "worktree", "add", "--detach", "--quiet", str(old), revision], cwd=REPO, check=True)
        try:
            yield old, rev.stdout.strip()
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=REPO, check=False)


def scene_label(scene_dir: Path) -> str:
    """A roguefit output (``scene/preset/fit.json``) is labelled ``scene/preset``; any other
    folder by its name."""
    scene_dir = Path(scene_dir)
    parts = scene_dir.resolve().parts
    return "/".join(parts[-2:]) if (scene_dir / "fit.json").is_file() else scene_dir.name


def stamp() -> dict:
    """The columns every benchmark row starts with."""
    return {"date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "machine": machine(), "commit": commit()}


def write_csv(path: Path, rows: list[dict]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fields: list[str] = []
    for row in rows:
        fields += [k for k in row if k not in fields]
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    return path


def write_json(path: Path, obj) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2) + "\n")
    return path


def save_figure(fig, path: Path) -> Path:
    """Lay out ``fig``, write it as a 120-dpi PNG at ``path`` (its folder made) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


_OUTPUT_SUFFIXES = (".csv", ".json", ".png")


def beside(output: Path, suffix: str) -> Path:
    """``output`` with ``suffix``: a ``.csv``/``.json``/``.png`` ending is replaced, anything else kept.

    ``Path.with_suffix`` would cut ``run_0.5`` to ``run_0``: a dot in a run's name is not a suffix.
    """
    base = output.with_suffix("") if output.suffix in _OUTPUT_SUFFIXES else output
    return base.with_name(base.name + suffix)


def caption_line(fig, rows: list[dict], what: str, *, fontsize: int = 7) -> None:
    """The figure's title: ``what`` (formatted with the first row's columns), then that row's
    machine, commit and date on one line; none without rows."""
    if rows:
        r = rows[0]
        fig.suptitle(f"{what.format(**r)} | {r['machine'][:60]} | {r['commit']} | {r['date'][:10]}",
                     fontsize=fontsize)


def add_stage_switches(p) -> None:
    """``--align``, ``--colour`` and ``--trust`` (on / off) on an argparse parser: the inference
    stages around the model, each on by default as shipped."""
    p.add_argument("--align", choices=["on", "off"], default="on",
                   help="neighbour pose refinement at inference (default on, as shipped)")
    p.add_argument("--colour", choices=["on", "off"], default="on",
                   help="colour matching to the neighbour photos at inference (default on, as shipped)")
    p.add_argument("--trust", choices=["on", "off"], default="on",
                   help="keep only part of the enhancer's change where the neighbours mostly disagree "
                        "(roguenerf.enhance.trust; default on, as shipped)")


def configure_runtime() -> None:
    """:func:`roguenerf.runtime.configure`, and say what it set."""
    from roguenerf import runtime

    print(f"runtime: {runtime.configure()}", flush=True)


def write_outputs(output: Path, rows: list[dict], plot, *, quick: bool = False) -> tuple[Path, Path]:
    """``OUTPUT[_quick].csv`` and ``OUTPUT[_quick].png`` (``plot(rows, path)``); prints both paths."""
    stem = beside(output, "_quick" if quick else "")
    csv_path = write_csv(beside(stem, ".csv"), rows)
    png_path = plot(rows, beside(stem, ".png"))
    print(f"wrote {csv_path} and {png_path}")
    return csv_path, png_path


def starting_checkpoint(explicit: Path | None, scratch: bool) -> Path | None:
    """The checkpoint to fine-tune from: explicit, else the shipped default, else None (scratch)."""
    from roguenerf.checkpoint import default_checkpoint_path

    if scratch:
        return None
    if explicit is not None:
        return explicit
    path = default_checkpoint_path(must_exist=False)
    if path.is_file():
        return path
    print(f"note: no default checkpoint at {path}; fine-tuning from scratch", flush=True)
    return None


def scene_metrics(report: dict) -> dict:
    """Flatten an evaluate() report into CSV columns (PSNR gain = enhanced - render; FLIP: lower is better)."""
    r, e = report["render"], report["enhanced"]
    return {"views": len(report["views"]),
            "render_psnr": round(r["psnr"], 4), "enhanced_psnr": round(e["psnr"], 4),
            "gain_db": round(e["psnr"] - r["psnr"], 4),
            "render_ssim": round(r["ssim"], 5), "enhanced_ssim": round(e["ssim"], 5),
            "render_flip": round(r["flip"], 5), "enhanced_flip": round(e["flip"], 5),
            "latency_s_per_view": round(report["seconds_per_view"], 4)}


def summary_by_setting(rows: list[dict], key: str) -> list[dict]:
    """Per value of ``rows[...][key]`` (in first-seen order): the mean over scenes of each scene's
    mean ``gain_db``, the views with a better FLIP (``flip_change`` < 0), the worst view and the
    worst scene's mean gain. Rows need ``scene``, ``gain_db`` and ``flip_change``."""
    out = []
    for spec in dict.fromkeys(r[key] for r in rows):
        mine = [r for r in rows if r[key] == spec]
        scenes: dict[str, list[float]] = {}
        for r in mine:
            scenes.setdefault(r["scene"], []).append(r["gain_db"])
        means = [sum(g) / len(g) for g in scenes.values()]
        out.append({key: spec, "gain_db": sum(means) / len(means),
                    "views_flip_better": sum(r["flip_change"] < 0 for r in mine), "views": len(mine),
                    "worst_view_gain_db": min(r["gain_db"] for r in mine), "worst_scene_gain_db": min(means)})
    return out

