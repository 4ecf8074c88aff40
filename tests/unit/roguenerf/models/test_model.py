"""The enhancer: configs and variants, identity start, neighbour handling, NaN safety,
gradients, ablation switches, scale invariance, import hygiene."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest
import torch

from roguenerf.errors import InputError
from roguenerf.models import VARIANTS, EnhancerConfig, NeighbourBatch, build_enhancer, make_config
from roguenerf.models.enhancer import Enhancer, median_depth
from tests.model_helpers import make_views, randomise

pytestmark = pytest.mark.usefixtures("one_thread")


def small(variant: str = "micro", **overrides) -> Enhancer:
    torch.manual_seed(0)
    return build_enhancer(variant, **overrides)


# ---------------------------------------------------------------- configs and variants


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_config_round_trips_through_json(variant):
    cfg = make_config(variant, flow_iters=3)
    text = json.dumps(cfg.to_dict())
    again = EnhancerConfig.from_dict(json.loads(text))
    assert again == cfg
    assert isinstance(again.uformer.depths, tuple)


def test_from_dict_rejects_unknown_keys_and_wrong_types():
    d = make_config("nano").to_dict()
    with pytest.raises(InputError, match="unknown keys.*'colour'"):
        EnhancerConfig.from_dict({**d, "colour": "red"})
    with pytest.raises(InputError, match=r"config.uformer: unknown keys.*'heads'"):
        EnhancerConfig.from_dict({**d, "uformer": {**d["uformer"], "heads": 3}})
    with pytest.raises(InputError, match="config.use_attention: expected bool"):
        EnhancerConfig.from_dict({**d, "use_attention": "yes"})
    with pytest.raises(InputError, match="config.uformer.depths"):
        EnhancerConfig.from_dict({**d, "uformer": {**d["uformer"], "depths": [1.5] * 9}})
    with pytest.raises(InputError, match="num_heads"):
        EnhancerConfig.from_dict({**d, "uformer": {**d["uformer"], "num_heads": [3] * 9}})
    # Missing keys take the defaults (older checkpoints stay loadable).
    assert EnhancerConfig.from_dict({"variant": "x"}) == EnhancerConfig(variant="x")


def test_make_config_caller_overrides_win():
    cfg = make_config("T", flow_iters=1, win_size=4, use_attention=False)
    assert (cfg.flow_iters, cfg.uformer.win_size, cfg.use_attention) == (1, 4, False)
    assert cfg.uformer.embed_dim == 16 and cfg.variant == "T"
    assert make_config("S", uformer={"embed_dim": 16}).uformer.embed_dim == 16
    with pytest.raises(InputError, match="unknown keys.*'flow_iterations'"):
        make_config("T", flow_iterations=1)
    with pytest.raises(InputError, match="variant: expected one of"):
        make_config("XXL")


def test_paper_variants():
    heads = (1, 2, 4, 8, 16, 16, 8, 4, 2)
    for name, embed, depths in [("T", 16, (2,) * 9), ("S", 32, (2,) * 9), ("B", 32, (1, 2, 8, 8, 2, 8, 8, 2, 1))]:
        cfg = make_config(name)
        assert (cfg.uformer.embed_dim, cfg.uformer.depths, cfg.uformer.num_heads) == (embed, depths, heads)
        assert cfg.uformer.win_size == 8 and cfg.features == 64
    assert make_config("nano").uformer.depths == (1,) * 9
    assert make_config("nano").flow_iters < make_config("T").flow_iters


def test_build_enhancer_from_config_with_overrides():
    model = build_enhancer(make_config("micro"), use_refinement=False, win_size=2)
    assert model.flow is None and model.config.uformer.win_size == 2


# ---------------------------------------------------------------- behaviour


def test_untrained_enhancer_is_exactly_the_identity():
    model = small()
    r, d, K, P, nb = make_views(model, n=2)
    assert torch.equal(model(r, d, K, P, nb), r)


@pytest.mark.parametrize("n", [0, 1, 2, 5, 8])
def test_any_number_of_neighbours(n):
    model = randomise(small())
    r, d, K, P, nb = make_views(model, b=2, n=n, h=37, w=53)
    y = model(r, d, K, P, nb)
    assert y.shape == (2, 3, 37, 53) and torch.isfinite(y).all()
    if n == 0:
        assert torch.equal(y, model(r, d, K, P, None))


@pytest.mark.parametrize(("h", "w"), [(378, 504), (512, 512)])
def test_large_images(h, w):
    model = randomise(small("nano")).eval()
    with torch.inference_mode():
        r, d, K, P, nb = make_views(model, n=1, h=h, w=w)
        y = model(r, d, K, P, nb)
    assert y.shape == (1, 3, h, w) and torch.isfinite(y).all()


def test_output_is_invariant_to_neighbour_order():
    model = randomise(small())
    r, d, K, P, nb = make_views(model, n=4)
    perm = torch.tensor([2, 0, 3, 1])
    shuffled = NeighbourBatch(nb.features[:, perm], nb.depth[:, perm], nb.K[:, perm], nb.world_from_cam[:, perm])
    a, b = model(r, d, K, P, nb), model(r, d, K, P, shuffled)
    assert torch.equal(a, b)
    assert not torch.allclose(a, model(r, d, K, P, NeighbourBatch(
        nb.features[:, :2], nb.depth[:, :2], nb.K[:, :2], nb.world_from_cam[:, :2])))


def test_missing_depth_never_gives_nan():
    model = randomise(small())
    r, d, K, P, nb = make_views(model, n=2)
    d = d.clone()
    d[..., :10, :] = float("nan")
    d[..., 10:20, :] = 0.0
    d[..., 20:25, :] = -1.0
    d[..., 25:28, :] = float("inf")
    ndepth = nb.depth.clone()
    ndepth[:, 0, ..., :, :16] = float("nan")
    ndepth[:, 1] = 0.0
    nb = NeighbourBatch(nb.features, ndepth, nb.K, nb.world_from_cam)
    r = r.requires_grad_()
    y = model(r, d, K, P, nb)
    y.square().mean().backward()
    assert torch.isfinite(y).all()
    assert torch.isfinite(r.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    # All depth missing: still finite.
    y = model(r, torch.full_like(d, float("nan")), K, P, nb)
    assert torch.isfinite(y).all()


def test_every_parameter_receives_a_gradient():
    """At initialisation only the zero-initialised output projection can learn (everything
    upstream is multiplied by its zero weights); after two Adam steps the output projection
    and the flow increment head are non-zero and every parameter gets a non-zero gradient."""
    model = small("micro", depths=(2,) * 9)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    r, d, K, P, _ = make_views(model, b=2, n=2, h=32, w=40)
    photos = torch.rand(2, 3, 32, 40, generator=torch.Generator().manual_seed(1))
    target = torch.rand_like(r)

    def step():
        opt.zero_grad()
        _, _, _, _, nb = make_views(model, b=2, n=2, h=32, w=40, photos=photos)
        (model(r, d, K, P, nb) - target).abs().mean().backward()

    step()
    moving = {name for name, p in model.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert moving == {"uformer.output_proj.weight", "uformer.output_proj.bias"}
    opt.step()
    step()
    opt.step()
    step()
    dead = [name for name, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert dead == []


@pytest.mark.parametrize(("switch", "gone"), [
    ("use_neighbours", {"conv_H", "flow", "pixel_attention", "camera_attention"}),
    ("use_alignment", set()),
    ("use_refinement", {"flow"}),
    ("use_attention", {"pixel_attention", "camera_attention"}),
    ("use_uformer", {"uformer"}),
])
def test_each_ablation_switch_changes_the_computation(switch, gone):
    full = randomise(small())
    ablated = build_enhancer("micro", **{switch: False})
    names = {name.split(".")[0] for name, _ in ablated.named_parameters()}
    assert not names & gone
    assert all(getattr(ablated, g) is None for g in gone)
    # Shared weights: whatever both models have is identical, so any difference comes from the switch.
    shared = {k: v for k, v in full.state_dict().items()
              if k in ablated.state_dict() and ablated.state_dict()[k].shape == v.shape}
    missing, _ = ablated.load_state_dict(shared, strict=False)
    if switch not in ("use_neighbours", "use_uformer"):
        assert missing == []
    if switch == "use_uformer":
        randomise(ablated)
    r, d, K, P, nb = make_views(full, n=2)
    with torch.no_grad():
        assert not torch.allclose(full(r, d, K, P, nb), ablated(r, d, K, P, nb), atol=1e-5)


def test_pool_spread_starts_as_the_model_it_widens_and_sees_disagreement():
    """A pool_spread model made from one without (conv_merge's new inputs at zero weight) computes
    the same; once those weights move, two neighbours that disagree change the output, while one
    neighbour (max - min of one map is 0) or none leave it as it was."""
    from roguenerf.training.loop import transfer_weights

    plain = randomise(small())
    spread = build_enhancer(dataclasses.replace(plain.config, pool_spread=True))
    report = transfer_weights(plain, spread)
    assert report["widened"] == ["conv_merge"] and report["fresh"] == [] and report["dropped"] == []
    f = plain.config.features
    weight = spread.conv_merge[0].weight
    assert weight.shape[1] == 3 * f and not weight[:, 2 * f:].any()
    r, d, K, P, nb = make_views(plain, n=2)
    one = NeighbourBatch(nb.features[:, :1], nb.depth[:, :1], nb.K[:, :1], nb.world_from_cam[:, :1])
    with torch.no_grad():
        torch.testing.assert_close(spread(r, d, K, P, nb), plain(r, d, K, P, nb), rtol=0, atol=1e-6)
        weight[:, 2 * f:].normal_(0.0, 0.5, generator=torch.Generator().manual_seed(3))
        assert (spread(r, d, K, P, nb) - plain(r, d, K, P, nb)).abs().max() > 1e-3
        torch.testing.assert_close(spread(r, d, K, P, one), plain(r, d, K, P, one), rtol=0, atol=1e-6)
        torch.testing.assert_close(spread(r, d, K, P, None), plain(r, d, K, P, None), rtol=0, atol=1e-6)


def test_only_the_merge_is_widened_between_configs():
    """A larger variant's extra input channels are not appended features: its layers start fresh
    (the zero-initialised output projection keeps the untrained model the identity)."""
    from roguenerf.training.loop import transfer_weights

    small_model, larger = randomise(small("micro")), build_enhancer("nano")
    src, dst = small_model.uformer.output_proj.weight, larger.uformer.output_proj.weight
    assert src.shape[0] == dst.shape[0] and src.shape[1] < dst.shape[1]  # the shapes a generic rule would widen
    report = transfer_weights(small_model, larger)
    assert report["widened"] == [] and "uformer" in report["fresh"]
    assert not larger.uformer.output_proj.weight.any()


def test_without_neighbours_the_neighbours_are_ignored():
    model = randomise(small(use_neighbours=False))
    r, d, K, P, nb = make_views(model, n=2)
    assert torch.equal(model(r, d, K, P, nb), model(r, d, K, P, None))
    with pytest.raises(InputError, match="use_neighbours=False"):
        model.encode_neighbours(torch.rand(1, 3, 8, 8))


def test_alignment_uses_the_geometry():
    """With 3D alignment the neighbours' poses matter; without it (Uformer+NN) they do not."""
    for aligned in (True, False):
        model = randomise(small(use_alignment=aligned, use_attention=False))
        r, d, K, P, nb = make_views(model, n=1)
        moved = NeighbourBatch(nb.features, nb.depth, nb.K, nb.world_from_cam.clone())
        moved.world_from_cam[..., 0, 3] += 0.3
        with torch.no_grad():
            same = torch.allclose(model(r, d, K, P, nb), model(r, d, K, P, moved), atol=1e-6)
        assert same != aligned


def test_scale_invariance():
    """Scene units are arbitrary: depths and translations times 1e4 give the same output."""
    model = randomise(small("micro"))
    with torch.no_grad():
        a = model(*make_views(model, n=3, unit=1.0))
        b = model(*make_views(model, n=3, unit=1e4))
    assert torch.allclose(a, b, atol=1e-4)


def test_median_depth_ignores_missing_values():
    d = torch.tensor([[[[1.0, 2.0, 3.0], [float("nan"), 0.0, -5.0]]], [[[float("nan")] * 3, [0.0] * 3]]])
    assert torch.equal(median_depth(d), torch.tensor([2.0, 1.0]))


def test_input_errors_name_the_argument():
    model = small()
    r, d, K, P, nb = make_views(model, n=1)
    with pytest.raises(InputError, match=r"render: expected shape \(\*, 3, \*, \*\), got \(1, 4, 48, 64\)"):
        model(torch.rand(1, 4, 48, 64), d, K, P, nb)
    with pytest.raises(InputError, match=r"depth: expected shape \(1, 1, 48, 64\)"):
        model(r, d[..., :10], K, P, nb)
    with pytest.raises(InputError, match="neighbours.depth"):
        model(r, d, K, P, NeighbourBatch(nb.features, nb.depth[..., :5], nb.K, nb.world_from_cam))


def test_import_roguenerf_does_not_import_the_service_stack():
    code = ("import sys, roguenerf, roguenerf.models; "
            "print(sorted(m for m in ('fastapi', 'huey', 'uvicorn', 'starlette') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_config_module_imports_no_model_code():
    """Imports run one way (config <- enhancer): config.py imports nothing from the models,
    not even lazily inside a function (the old build_enhancer knot)."""
    import ast
    from pathlib import Path

    import roguenerf.models.config as config_module

    tree = ast.parse(Path(config_module.__file__).read_text())
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    assert not {m for m in imported if m and m.startswith("roguenerf.models")}, imported
    from roguenerf import build_enhancer as exported
    from roguenerf.models.enhancer import build_enhancer

    assert exported is build_enhancer


@pytest.mark.parametrize("fast", [True, False])
def test_enhancer_checks_every_neighbour_camera_once_for_all(fast):
    """The enhancer validates the target's and all neighbours' K and poses up front (reproject
    then skips its own per-neighbour checks): a bad neighbour is refused by name, and a pose
    within the orthonormality tolerance gives the same output as the exact one."""
    model = randomise(build_enhancer("micro").eval())
    render, depth, K, P, nb = make_views(model, n=3, h=24, w=32)
    mode = torch.inference_mode() if fast else torch.no_grad()
    with mode:
        want = model(render, depth, K, P, nb)
        reflected = nb.world_from_cam.clone()
        reflected[0, 2, :3, 0] *= -1
        with pytest.raises(InputError, match=r"neighbours\.world_from_cam.*det"):
            model(render, depth, K, P, dataclasses.replace(nb, world_from_cam=reflected))
        bad_K = nb.K.clone()
        bad_K[0, 1, 0, 0] = -5.0
        with pytest.raises(InputError, match=r"neighbours\.K.*fx > 0"):
            model(render, depth, K, P, dataclasses.replace(nb, K=bad_K))
        noisy = nb.world_from_cam.double().clone()
        noisy[..., :3, :3] += 1e-7 * torch.randn(noisy[..., :3, :3].shape, generator=torch.Generator().manual_seed(1),
                                                 dtype=torch.float64)
        got = model(render, depth, K, P, dataclasses.replace(nb, world_from_cam=noisy))
    torch.testing.assert_close(got, want, atol=1e-4, rtol=0)
