"""The fused linear / convolution helpers, kept importable here: they live in
:mod:`roguenerf.ops.fused` (and the switches in :mod:`roguenerf.fastpath`)."""

from roguenerf.fastpath import fast_enabled, in_reference_mode, layout_enabled, reference_mode
from roguenerf.ops.fused import channels_last, conv2d, conv_act, linear, linear_add, mkldnn_fused_available

__all__ = ["channels_last", "conv2d", "conv_act", "fast_enabled", "in_reference_mode", "layout_enabled", "linear",
           "linear_add", "mkldnn_fused_available", "reference_mode"]
