"""The stage profiler reports the real forward's stages with known FLOP counts; runtime settings."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from roguenerf import native, runtime
from roguenerf.fastpath import reference_mode
from roguenerf.models import build_enhancer
from roguenerf.profiling import STAGES, StageProfile, stage
from tests.model_helpers import make_views, randomise


@pytest.mark.parametrize("fast, kernels", [(True, True), (True, False), (False, False)])
def test_stage_flops_match_the_architecture(fast, kernels):
    h, w, n = 40, 56, 2
    model = randomise(build_enhancer("micro")).eval()
    render, depth, K, P, nb = make_views(model, n=n, h=h, w=w)
    f = model.config.features
    with torch.inference_mode() if fast else torch.no_grad(), reference_mode(not fast), native.disabled(not kernels):
        with StageProfile(count_flops=True) as prof:
            model(render, depth, K, P, nb)
    rows = {r["stage"]: r for r in prof.rows()}
    # With the C kernels the max-pool is done inside the attention kernel: no "fusion" stage
    # (without pool_spread nothing is left for it).
    stages = [s for s in STAGES if not (kernels and s == "fusion")]
    assert [s for s in STAGES if s in rows] == stages
    px = h * w
    # conv_I: 3 -> F and F -> F, 3x3, 2 FLOPs per multiply-add (fused kernels counted alike)
    assert rows["encoders"]["gflop"] * 1e9 == pytest.approx(2 * px * 9 * (3 * f + f * f))
    # conv_merge: 2F -> F, 3x3
    assert rows["merge"]["gflop"] * 1e9 == pytest.approx(2 * px * 9 * 2 * f * f)
    a = model.config.attention_hidden
    camera = n * 2 * (9 * a + a)  # camera attention: 9 -> A -> 1 per neighbour
    if fast:
        # The target's half of the first conv, [I^f, D_k] (F + 1 channels), once; per neighbour
        # the conv reads the packed buffer [H', D_i, mask]: oneDNN with a zero weight for the
        # mask, the C kernel only the F + 1 channels it needs.
        per_neighbour = f + 1 if kernels else f + 2
        expected = 2 * px * 9 * ((f + 1) * a + n * (per_neighbour * a + a)) + camera
    else:  # pixel attention: (2F + 2) -> A -> 1 per neighbour
        expected = n * 2 * px * 9 * ((2 * f + 2) * a + a) + camera
    assert rows["attention"]["gflop"] * 1e9 == pytest.approx(expected, rel=1e-9)
    assert rows["uformer"]["gflop"] > 0 and rows["reprojection"]["seconds"] > 0
    assert prof.total_seconds >= sum(r["seconds"] for r in rows.values()) - 1e-6


def test_stage_is_free_outside_a_profile_and_profiles_do_not_nest():
    with stage("encoders"):
        pass  # no profile: nothing recorded, no error
    with StageProfile() as prof:
        with stage("encoders"):
            with stage("uformer"):  # nested: counted to the outer stage
                pass
        with pytest.raises(RuntimeError):
            with StageProfile():
                pass
    assert "uformer" not in prof.seconds and "encoders" in prof.seconds


def test_runtime_configure_sets_threads_and_keeps_memory():
    before = torch.get_num_threads()
    try:
        applied = runtime.configure(threads=1)
        assert applied["threads"] == torch.get_num_threads() == 1
        assert applied["keep_freed_memory"] is True  # glibc here
    finally:
        torch.set_num_threads(before)


RELEASE_CHILD = r"""
import json
from roguenerf import native, runtime
runtime.configure(threads=1)
import torch

def rss_mb():
    return next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmRSS:")) / 1024

base = rss_mb()
blocks = [torch.ones(n * 2**20 // 4) for n in (96, 64, 80)]  # 240 MB touched, freed below
del blocks
kept = rss_mb()
released = runtime.release_freed_memory()
print(json.dumps({"base": base, "kept": kept, "after": rss_mb(), "released": released}))
"""


def test_release_freed_memory_returns_kept_blocks_to_the_os():
    # configure() keeps freed blocks (faster reuse); between tiles of different shapes the
    # enhancer hands them back, or the kept heap fragments and the RSS grows tile after tile.
    out = subprocess.run([sys.executable, "-c", RELEASE_CHILD], capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["released"] is True
    assert r["kept"] - r["base"] > 200  # freed, yet still resident: kept for reuse
    assert r["kept"] - r["after"] > 200  # handed back


def test_freed_memory_guard_trims_once_the_process_grew_by_its_margin():
    """Known answers with a scripted RSS: the first call trims; later ones only once the RSS is
    more than ``margin`` above what it was after the last trim (issue 51: trimming between every
    tile of a 2016 x 1512 view doubled its system time)."""
    readings = iter([500, 480,   # first call: trims, base 480
                     700,        # +220: kept
                     980,        # +500 > 300: trims ...
                     600,        # ... base 600
                     899,        # +299: kept
                     901, 610])  # +301: trims, base 610
    trims = []
    guard = runtime.FreedMemoryGuard(300, rss=lambda: next(readings), trim=lambda: trims.append(1))
    assert [guard() for _ in range(5)] == [True, False, True, False, True]
    assert guard.trims == len(trims) == 3
    unknown = runtime.FreedMemoryGuard(300, rss=lambda: None, trim=lambda: trims.append(1))
    assert [unknown(), unknown()] == [True, True]  # no RSS to read: trims every time, as before
    assert runtime.resident_bytes() > 10 << 20  # this process, read from /proc
