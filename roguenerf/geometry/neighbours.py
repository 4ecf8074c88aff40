"""The paper's neighbour selection (section 3.2)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from roguenerf.errors import InputError
from roguenerf.geometry.cameras import check_pose
from roguenerf.geometry.euler import angular_distance


def select_neighbours(
    target_world_from_cam: Tensor,
    train_world_from_cam: Tensor,
    n: int,
    *,
    candidates: int = 5,
    exclude: int | Sequence[int] | None = None,
) -> Tensor:
    """Indices of the ``n`` neighbours of one target pose among the training poses.

    dist_pos = mean |t_k - t_i|; take the ``candidates`` nearest by position, then of those the
    ``n`` nearest by dist_ang = mean |wrap(euler(R_k) - euler(R_i))|. ``exclude`` indices (the
    target itself when it is a training view) are never returned; a training pose identical to
    the target is otherwise allowed. ``n = 0`` gives an empty tensor; ``n > candidates`` widens
    the candidate set to ``n``; fewer available poses than ``n`` returns all that are available.

    dist_ang is :func:`~roguenerf.geometry.euler.angular_distance`: the paper's Euler
    difference, made robust where Euler angles jump (gimbal lock).

    Args:
        target_world_from_cam: ``(4, 4)``.
        train_world_from_cam: ``(M, 4, 4)``.
    Returns:
        ``(min(n, M - excluded),)`` int64 indices ordered nearest first (deterministic ties: the
        nearer position first, then the lower index).
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise InputError(f"n: expected an integer >= 0, got {n!r}")
    if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 1:
        raise InputError(f"candidates: expected an integer >= 1, got {candidates!r}")
    target = check_pose(target_world_from_cam, "target_world_from_cam").double()
    train = check_pose(train_world_from_cam, "train_world_from_cam").double()
    if target.ndim != 2:
        raise InputError(f"target_world_from_cam: expected shape (4, 4), got {tuple(target.shape)}")
    if train.ndim != 3:
        raise InputError(f"train_world_from_cam: expected shape (M, 4, 4), got {tuple(train.shape)}")
    M = train.shape[0]
    excluded = torch.zeros(M, dtype=torch.bool)
    if exclude is not None:
        idx = [exclude] if isinstance(exclude, int) else list(exclude)
        for i in idx:
            if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < M:
                raise InputError(f"exclude: expected training indices in [0, {M}), got {i!r}")
            excluded[i] = True
    available = torch.nonzero(~excluded).squeeze(-1)
    n_out = min(n, available.numel())
    if n_out == 0:
        return torch.empty(0, dtype=torch.int64)

    dist_pos = (train[available, :3, 3] - target[:3, 3]).abs().mean(dim=-1)
    # Stable sorts make ties resolve to the lower index, independent of the platform.
    order = torch.sort(dist_pos, stable=True).indices
    shortlist = available[order[: max(candidates, n_out)]]
    dist_ang = angular_distance(target[:3, :3], train[shortlist, :3, :3])
    ranked = shortlist[torch.sort(dist_ang, stable=True).indices]
    return ranked[:n_out].to(torch.int64)
