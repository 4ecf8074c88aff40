"""The full RoGUENeRF enhancer (STUB: signatures are the contract)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor, nn


@dataclass
class NeighbourBatch:
    """Neighbours of each target in a batch; N may be 0.

    features: ``(B, N, F, Hs, Ws)`` conv_H features of the neighbour *photos* (cached per scene).
    depth: ``(B, N, 1, Hs, Ws)`` the neighbours' rendered z-depth.
    K: ``(B, N, 3, 3)``; world_from_cam: ``(B, N, 4, 4)`` OpenCV.
    """

    features: Tensor
    depth: Tensor
    K: Tensor
    world_from_cam: Tensor


class Enhancer(nn.Module):
    def encode_neighbours(self, photos: Tensor) -> Tensor:
        """conv_H: ``(N, 3, H, W)`` photos in [0,1] -> ``(N, F, H, W)``. Independent of the target."""
        raise NotImplementedError

    def forward(self, render: Tensor, depth: Tensor, K: Tensor, world_from_cam: Tensor,
                neighbours: NeighbourBatch | None) -> Tensor:
        """Enhance renders.

        Args:
            render: ``(B, 3, H, W)`` in [0, 1]; depth ``(B, 1, H, W)`` z-depth (missing <= 0 / NaN);
            K ``(B, 3, 3)``; world_from_cam ``(B, 4, 4)`` OpenCV; neighbours or None.
        Returns:
            ``(B, 3, H, W)`` = render + Uformer(...) (global residual), any H x W.
        """
        raise NotImplementedError
