"""``roguenerf.ops.pick``: the one rule that chooses every operation's body."""

from __future__ import annotations

import torch

from roguenerf import native, ops
from roguenerf.fastpath import reference_mode
from roguenerf.ops import Body


def test_pick_follows_the_switches_gradient_and_dtype():
    x = torch.rand(1, 4, 8, 8)
    assert native.library() is not None, "a C compiler is part of the test set-up (./dev test installs gcc)"
    with torch.inference_mode():
        assert ops.pick(x) is Body.NATIVE
        assert ops.pick(x, allow_native=False) is Body.FAST
        with native.disabled():
            assert ops.pick(x) is Body.FAST
            with native.disabled(False):
                assert ops.pick(x) is Body.NATIVE
        assert ops.pick(x, x.double()) is Body.TORCH  # every tensor must qualify
        assert ops.pick(torch.empty(1, device="meta")) is Body.TORCH
        with reference_mode():
            assert ops.pick(x) is Body.REFERENCE
    assert ops.pick(x) is Body.TORCH  # gradient recorded (training)
    with torch.no_grad(), reference_mode():
        assert ops.pick(x) is Body.REFERENCE
    assert Body.NATIVE.fast and Body.FAST.fast and not Body.TORCH.fast and not Body.REFERENCE.fast


def test_pick_agrees_with_the_per_tensor_switches():
    """The old per-call tests (``fast_enabled``, ``native.enabled``) and ``pick`` never disagree."""
    from roguenerf.fastpath import fast_enabled

    cases = [torch.rand(2, 3), torch.rand(2, 3).double(), torch.rand(2, 3).half()]
    for grad in (False, True):
        for ref in (False, True):
            for off in (False, True):
                with torch.set_grad_enabled(grad), reference_mode(ref), native.disabled(off):
                    for x in cases:
                        body = ops.pick(x)
                        assert body.fast == fast_enabled(x), (grad, ref, off, x.dtype)
                        assert (body is Body.NATIVE) == native.enabled(x), (grad, ref, off, x.dtype)
                        assert (body is Body.REFERENCE) == ref
