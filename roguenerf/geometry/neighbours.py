"""The paper's neighbour selection (section 3.2) (STUB)."""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor


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

    Args:
        target_world_from_cam: ``(4, 4)``.
        train_world_from_cam: ``(M, 4, 4)``.
    Returns:
        ``(min(n, M - excluded),)`` int64 indices ordered nearest first (deterministic ties).
    """
    raise NotImplementedError
