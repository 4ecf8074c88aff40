"""The paper's neighbour selection: 5 nearest by position, then n nearest by Euler angle."""

from __future__ import annotations

import json
import math

import pytest
import torch

from roguenerf.errors import InputError
from roguenerf.geometry import opengl_to_opencv, select_neighbours
from tests.geometry_helpers import zyx


def pose(R, t):
    P = torch.eye(4, dtype=torch.float64)
    P[:3, :3] = R
    P[:3, 3] = torch.as_tensor(t, dtype=torch.float64)
    return P


def test_position_shortlist_then_angle():
    target = pose(zyx(0, 0, 0), [0, 0, 0])
    train = torch.stack(
        [
            pose(zyx(0, 0, 0.9), [0.1, 0, 0]),  # 0: nearest position, large angle
            pose(zyx(0, 0, 0.1), [0.2, 0, 0]),  # 1
            pose(zyx(0, 0, 0.0), [0.3, 0, 0]),  # 2: same orientation
            pose(zyx(0, 0, 0.5), [0.4, 0, 0]),  # 3
            pose(zyx(0, 0, 0.3), [0.5, 0, 0]),  # 4
            pose(zyx(0, 0, 0.0), [5.0, 0, 0]),  # 5: same orientation but far: not in the shortlist
        ]
    )
    assert select_neighbours(target, train, 2).tolist() == [2, 1]
    assert select_neighbours(target, train, 5).tolist() == [2, 1, 4, 3, 0]
    # n > candidates widens the shortlist, so the far view comes in
    assert select_neighbours(target, train, 6).tolist() == [2, 5, 1, 4, 3, 0]
    assert select_neighbours(target, train, 0).shape == (0,)
    assert select_neighbours(target, train, 0).dtype == torch.int64
    assert select_neighbours(target, train, 100).numel() == 6


def test_angle_differences_are_wrapped():
    target = pose(zyx(0, 0, math.pi - 0.05), [0, 0, 0])
    train = torch.stack(
        [
            pose(zyx(0, 0, -math.pi + 0.05), [0.1, 0, 0]),  # 0.1 rad away once wrapped (6.18 unwrapped)
            pose(zyx(0, 0, math.pi - 0.5), [0.1, 0, 0]),  # 0.45 rad away
        ]
    )
    assert select_neighbours(target, train, 1).tolist() == [0]


def test_self_never_selected_but_identical_pose_allowed():
    train = torch.stack([pose(zyx(0, 0, 0.1 * i), [0.1 * i, 0, 0]) for i in range(6)])
    assert 3 not in select_neighbours(train[3], train, 5, exclude=3).tolist()
    assert select_neighbours(train[3], train, 1).tolist() == [3]
    picked = select_neighbours(train[3], train, 5, exclude=[3, 2]).tolist()
    assert picked[0] == 4 and sorted(picked) == [0, 1, 4, 5]
    assert select_neighbours(train[0], train[:1], 2, exclude=0).numel() == 0


def test_ties_are_deterministic():
    target = pose(zyx(0, 0, 0), [0, 0, 0])
    R = zyx(0, 0, 0)
    train = torch.stack([pose(R, [0.1, 0, 0]), pose(R, [-0.1, 0, 0]), pose(R, [0, 0.1, 0])])
    assert select_neighbours(target, train, 3).tolist() == [0, 1, 2]


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_gimbal_lock_ranking(pitch):
    """At pitch exactly +-90 deg a slightly perturbed copy must rank before a clearly different pose."""
    target = pose(zyx(0.4, pitch, 1.0), [0, 0, 0])
    perturbed = pose(zyx(0.45, pitch - math.copysign(1e-3, pitch), 0.95), [0.2, 0, 0])
    different = pose(zyx(0.4, pitch - math.copysign(0.8, pitch), 1.0), [0.2, 0, 0])
    train = torch.stack([different, perturbed])
    assert select_neighbours(target, train, 1).tolist() == [1]
    # and the other way round: the perturbed pose as target finds the locked one
    train = torch.stack([different, target])
    assert select_neighbours(perturbed, train, 1).tolist() == [1]


def test_lego_neighbours_are_close(lego_dir):
    meta = json.loads((lego_dir / "transforms.json").read_text())
    frames = [f for f in meta["frames"] if f["split"] == "train"]
    train = opengl_to_opencv(torch.tensor([f["transform_matrix"] for f in frames], dtype=torch.float64))
    target_frame = next(f for f in meta["frames"] if f["split"] == "test")
    target = opengl_to_opencv(torch.tensor(target_frame["transform_matrix"], dtype=torch.float64))
    idx = select_neighbours(target, train, 2)
    dist = (train[:, :3, 3] - target[:3, 3]).abs().mean(-1)
    five = torch.argsort(dist)[:5]
    assert set(idx.tolist()) <= set(five.tolist())
    # views around lego point at the origin: a chosen neighbour looks nearly the same way
    cos = (train[idx, :3, 2] * target[:3, 2]).sum(-1)
    assert (cos > 0.9).all()


def test_bad_arguments():
    train = torch.eye(4).expand(3, 4, 4)
    with pytest.raises(InputError, match="n: expected an integer >= 0"):
        select_neighbours(torch.eye(4), train, -1)
    with pytest.raises(InputError, match="exclude"):
        select_neighbours(torch.eye(4), train, 1, exclude=7)
    with pytest.raises(InputError, match="train_world_from_cam"):
        select_neighbours(torch.eye(4), torch.eye(4), 1)
    bad = torch.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(InputError, match="target_world_from_cam"):
        select_neighbours(bad, train, 1)
