import dataclasses

import numpy as np
import pytest
import torch

from pivla.data.transforms import batch_to_tensors
from pivla.model.cms import CMSModel
from pivla.model.config import BackboneConfig, ModelConfig
from pivla.training.losses import LossConfig, actor_loss, critic_loss, unified_loss

CFG = ModelConfig(image_size=32, backbone=BackboneConfig(d_model=64, n_layers=1, vision_channels=(16, 16, 32, 32)))


def fake_batch(cfg=CFG, B=3, S=2, seed=0):
    rng = np.random.default_rng(seed)
    K, D, H, n = cfg.chunk, cfg.action_dim, cfg.horizon, len(cfg.cameras)
    actions = rng.uniform(-1, 1, (B, K, D)).astype(np.float32)
    batch = {
        "images": rng.integers(0, 255, (B, n, 32, 32, 3), dtype=np.uint8),
        "text_ids": rng.integers(1, 10, (B, 16)),
        "text_mask": np.ones((B, 16), bool),
        "proprio": rng.normal(size=(B, cfg.proprio_dim)).astype(np.float32),
        "actions": actions,
        "bins": np.clip(((actions + 1) / 2 * 256).astype(np.int64), 0, 255),
        "action_mask": np.ones((B, K), np.float32),
        "imitate": np.ones(B, np.float32),
        "advantages": rng.normal(size=(B, K)).astype(np.float32),
        "returns": rng.uniform(size=(B, H + 1)).astype(np.float32),
        "value_mask": np.ones((B, H + 1), np.float32),
        "sp_index": rng.integers(0, K, (B, S)),
        "sp_images": rng.integers(0, 255, (B, S, n, 32, 32, 3), dtype=np.uint8),
        "sp_proprio": rng.normal(size=(B, S, cfg.proprio_dim)).astype(np.float32),
        "sp_mask": np.ones((B, S), np.float32),
    }
    return batch_to_tensors(batch)


def test_head_shapes():
    torch.manual_seed(0)
    m = CMSModel(CFG, vocab_size=12)
    out = m(fake_batch())
    assert out.logits.shape == (3, 8, 7, 256)
    assert out.continuous.shape == (3, 8, 7)
    assert out.latents.shape == (3, 8, m.latent_dim)
    assert out.values.shape == (3, 5) and out.value_now.shape == (3,)
    assert out.h_cog.shape == (3, CFG.backbone.n_cog_tokens, 64) and out.h_mot.shape == (3, 8, 64)
    assert m.decoder(out.latents).shape == (3, 8, 3, CFG.decoder_size, CFG.decoder_size)
    assert m.target(fake_batch()["images"]).shape == (3, m.latent_dim)


def _grads(model, loss):
    model.zero_grad(set_to_none=True)
    loss.backward()
    groups = {
        "backbone": model.backbone, "discrete": model.discrete_head, "continuous": model.continuous_head,
        "value": model.value_head, "state": model.state_predictor, "decoder": model.decoder,
    }
    got = {k for k, mod in groups.items()
           if any(p.grad is not None and p.grad.abs().sum() > 0 for p in mod.parameters())}
    if model.log_sigma.grad is not None and model.log_sigma.grad.abs().sum() > 0:
        got.add("log_sigma")
    assert all(p.grad is None for p in model.target.parameters()), "the target encoder must never train"
    return got


@pytest.mark.parametrize("term,expected", [
    ("il", {"backbone", "discrete", "continuous"}),
    ("actor", {"backbone", "continuous", "log_sigma"}),
    ("critic", {"backbone", "value"}),
    ("sp", {"backbone", "state"}),
    ("recon", {"decoder"}),
])
def test_each_term_reaches_only_its_heads(term, expected):
    torch.manual_seed(0)
    m = CMSModel(CFG, vocab_size=12)
    b = fake_batch()
    only = {"use_rl": False, "use_sp": False, "use_recon": False}
    if term == "il":
        loss, _ = unified_loss(m, m(b), b, LossConfig(**only))
    elif term == "actor":
        out = m(b)
        loss = actor_loss(out.continuous, m.log_sigma, b["actions"], b["advantages"], b["action_mask"])
    elif term == "critic":
        out = m(b)
        loss = critic_loss(out.values, out.value_now, b["returns"], b["value_mask"])
    elif term == "sp":
        out = m(b)
        cfg = LossConfig(use_rl=False, use_recon=False)
        full, _ = unified_loss(m, out, b, cfg)
        il, _ = unified_loss(m, out, b, LossConfig(**only))
        loss = full - il
    else:
        out = m(b)
        full, _ = unified_loss(m, out, b, LossConfig(use_rl=False, use_sp=False, use_recon=True))
        il, _ = unified_loss(m, out, b, LossConfig(**only))
        loss = full - il
    assert _grads(m, loss) == expected


def test_the_positive_only_actor_term_ignores_negative_advantages():
    """actor_positive_only: a sample whose advantages are all negative moves nothing, and the loss is the signed
    term's with the negative advantages set to zero; unified_loss passes the switch on."""
    torch.manual_seed(0)
    m = CMSModel(CFG, vocab_size=12)
    b = fake_batch()
    out = m(b)
    adv = b["advantages"].clone()
    adv[0] = -adv[0].abs() - 0.1
    one_sided = actor_loss(out.continuous, m.log_sigma, b["actions"], adv, b["action_mask"], positive_only=True)
    signed = actor_loss(out.continuous, m.log_sigma, b["actions"], adv.clamp_min(0), b["action_mask"])
    assert torch.allclose(one_sided, signed)
    assert not torch.allclose(one_sided, actor_loss(out.continuous, m.log_sigma, b["actions"], adv, b["action_mask"]))
    (grad,) = torch.autograd.grad(one_sided, out.continuous, retain_graph=True)
    assert grad[0].abs().sum() == 0 and grad[1:].abs().sum() > 0
    cfg = dict(use_sp=False, use_recon=False, critic_coef=0.0)
    b["advantages"] = adv
    on, _ = unified_loss(m, out, b, LossConfig(actor_positive_only=True, **cfg))
    off, _ = unified_loss(m, out, b, LossConfig(**cfg))
    il, _ = unified_loss(m, out, b, LossConfig(use_rl=False, use_sp=False, use_recon=False))
    assert torch.allclose(on - il, LossConfig().alpha * one_sided, atol=1e-6) and not torch.allclose(on, off)


def test_auxiliary_terms_off_the_trunk_train_only_their_heads():
    """aux_on_trunk=False: L_RL (then the critic alone) and L_SP reach the value head and the state predictor, never
    the backbone or an action head, and the full loss's backbone gradient is imitation's exactly."""
    torch.manual_seed(0)
    m = CMSModel(CFG, vocab_size=12)
    b = fake_batch()
    cfg = LossConfig(aux_on_trunk=False, use_recon=False)
    out = m(b, aux_on_trunk=False)
    full, logs = unified_loss(m, out, b, cfg)
    il, _ = unified_loss(m, out, b, LossConfig(use_rl=False, use_sp=False, use_recon=False))
    assert "rl_actor" not in logs and "rl_critic" in logs and "sp" in logs
    assert _grads(m, full - il) == {"value", "state"}
    full, _ = unified_loss(m, m(b, aux_on_trunk=False), b, cfg)
    _grads(m, full)
    with_aux = [p.grad.clone() for p in m.backbone.parameters()]
    il, _ = unified_loss(m, m(b), b, LossConfig(use_rl=False, use_sp=False, use_recon=False))
    _grads(m, il)
    assert all(torch.allclose(a, p.grad, atol=1e-7) for a, p in zip(with_aux, m.backbone.parameters()))


def test_ema_target_moves_towards_online_encoder():
    torch.manual_seed(0)
    m = CMSModel(CFG, vocab_size=12)
    with torch.no_grad():
        for p in m.backbone.vision.parameters():
            p.add_(1.0)
    before = [p.clone() for p in m.target.parameters()]
    m.update_target()
    for b, a, o in zip(before, m.target.parameters(), m.backbone.vision.parameters()):
        torch.testing.assert_close(a, b + (o.detach() - b) * (1 - CFG.target_encoder.ema_decay))


@pytest.mark.parametrize("res_blocks", [(), (1, 1, 1, 1)])
def test_truncated_target_reads_an_earlier_stage_and_follows_it(res_blocks):
    """``stages=2``: the latent pools the online CNN's second stage (its channels, layer-normalised), the
    target keeps no weights of later stages, and the EMA moves each kept weight towards its namesake."""
    torch.manual_seed(0)
    cfg = ModelConfig(image_size=32, backbone=BackboneConfig(d_model=64, n_layers=1, vision_channels=(16, 24, 32, 32),
                                                             res_blocks=res_blocks))
    cfg.target_encoder.stages = 2
    m = CMSModel(cfg, vocab_size=12)
    assert m.latent_dim == 24 and m.target.encoder.grid == 8
    online = dict(m.backbone.vision.named_parameters())
    kept = dict(m.target.encoder.named_parameters())
    assert set(kept) < set(online) and not any(k.startswith(("net.6", "net.9", "res.2", "res.3")) for k in kept)
    images = fake_batch(cfg)["images"]
    z = m.backbone.vision.stages(images[:, :1])[1].mean(dim=(-1, -2)).flatten(1)
    torch.testing.assert_close(m.target(images), torch.nn.functional.layer_norm(z, (24,)) / np.sqrt(24))
    with torch.no_grad():
        for p in m.backbone.vision.parameters():
            p.add_(1.0)
    before = {k: p.clone() for k, p in kept.items()}
    m.update_target()
    for k, p in m.target.encoder.named_parameters():
        torch.testing.assert_close(p, before[k] + (online[k] - before[k]) * (1 - cfg.target_encoder.ema_decay))
    with pytest.raises(ValueError, match="a CNN of 4 stages cannot keep 5"):
        cfg.target_encoder.stages = 5
        CMSModel(cfg, vocab_size=12)
    cfg.target_encoder.stages, cfg.target_encoder.name = 2, "thumbnail"
    with pytest.raises(ValueError, match="stages 2: only the 'ema' and 'frozen' encoders take it"):
        CMSModel(cfg, vocab_size=12)


def test_thumbnail_target_is_the_pooled_image_and_stays_put():
    """The weight-free target: the agent view average-pooled to grid x grid cells, layer-normalised and
    scaled to policy units; training cannot move it and checkpoints carry nothing for it."""
    cfg = ModelConfig(image_size=32, backbone=CFG.backbone)
    cfg.target_encoder.name, cfg.target_encoder.grid = "thumbnail", 4
    m = CMSModel(cfg, vocab_size=12)
    assert m.latent_dim == 3 * 4 * 4 and not list(m.target.parameters())
    assert not any(k.startswith("target.") for k in m.state_dict_for_checkpoint())
    images = fake_batch(cfg)["images"]
    cells = images[:, 0].reshape(3, 3, 4, 8, 4, 8).mean(dim=(3, 5)).reshape(3, -1)
    expected = torch.nn.functional.layer_norm(cells, (48,)) / np.sqrt(48)
    torch.testing.assert_close(m.target(images), expected)
    assert m.target(fake_batch(cfg)["sp_images"]).shape == (3, 2, 48)
    m.update_target()  # a no-op, not an error
    torch.testing.assert_close(m.target(images), expected)
    b = fake_batch(cfg)
    assert _grads(m, unified_loss(m, m(b), b, LossConfig(use_rl=False))[0]) >= {"backbone", "state"}
    with pytest.raises(ValueError, match="grid must be >= 1"):
        cfg.target_encoder.grid = 0
        CMSModel(cfg, vocab_size=12)


def test_a_target_latent_that_reads_the_proprio():
    """``proprio=w``: the pictures' latent, then w x the normalised proprio / sqrt(P); L_SP predicts both parts
    of o_{t+k}; a latent that reads the proprio refuses to encode without it."""
    cfg = ModelConfig(image_size=32, backbone=CFG.backbone)
    pictures = CMSModel(cfg, vocab_size=12).latent_dim
    cfg.target_encoder.proprio = 2.0
    m = CMSModel(cfg, vocab_size=12)
    assert m.latent_dim == pictures + cfg.proprio_dim
    b = fake_batch(cfg)
    z = m.target(b["sp_images"], b["sp_proprio"])
    assert z.shape == (3, 2, pictures + cfg.proprio_dim)
    torch.testing.assert_close(z[..., :pictures], m.target.picture_latents(b["sp_images"]))
    torch.testing.assert_close(z[..., pictures:], 2.0 * b["sp_proprio"] / np.sqrt(cfg.proprio_dim))
    loss, logs = unified_loss(m, m(b), b, LossConfig(use_rl=False))
    assert torch.isfinite(loss) and logs["sp"] > 0
    with pytest.raises(ValueError, match="reads the proprio too"):
        m.target(b["sp_images"])
    cfg.target_encoder.proprio = -1.0
    with pytest.raises(ValueError, match="proprio weight must be >= 0"):
        CMSModel(cfg, vocab_size=12)


def test_downsampled_target_encodes_the_area_averaged_image():
    """``downsample=2``: the EMA encoder's latent of the agent view averaged over 2 x 2 pixels, at any batch
    shape; a factor that does not divide the image size is refused."""
    cfg = ModelConfig(image_size=32, backbone=CFG.backbone)
    cfg.target_encoder.downsample = 2
    m = CMSModel(cfg, vocab_size=12)
    images = fake_batch(cfg)["images"]
    small = torch.nn.functional.avg_pool2d(images[:, :1].flatten(0, 1), 2).unflatten(0, (3, 1))
    z = m.target.encoder.pooled(small)
    torch.testing.assert_close(m.target(images), torch.nn.functional.layer_norm(z, z.shape[-1:]) / np.sqrt(z.shape[-1]))
    sp = fake_batch(cfg)["sp_images"]
    torch.testing.assert_close(m.target(sp)[:, 1], m.target(sp[:, 1]))
    cfg.target_encoder.downsample = 3
    with pytest.raises(ValueError, match="downsample 3 must divide image_size 32"):
        CMSModel(cfg, vocab_size=12)
    # only the CNN targets downsample: a thumbnail or DINOv2 target refuses the setting instead of ignoring it
    cfg.target_encoder.downsample, cfg.target_encoder.name = 2, "thumbnail"
    with pytest.raises(ValueError, match="downsample 2: only the .ema. and .frozen. encoders take it"):
        CMSModel(cfg, vocab_size=12)


def test_area_downsample_equals_pooling_the_float_tensor():
    """The NumPy pooling in front of AURD's ONNX graph equals ``images_to_tensor`` + ``avg_pool2d``."""
    from pivla.data.transforms import images_to_tensor
    from pivla.model.pixels import area_downsample

    images = np.random.default_rng(0).integers(0, 256, (2, 3, 24, 16, 3), dtype=np.uint8)
    for f in (1, 2, 4):
        got = area_downsample(images, f)
        want = torch.nn.functional.avg_pool2d(images_to_tensor(images).flatten(0, 1), f).unflatten(0, (2, 3))
        assert got.dtype == np.float32 and got.shape == (2, 3, 3, 24 // f, 16 // f)
        np.testing.assert_allclose(got, want.numpy(), atol=1e-6)
    with pytest.raises(ValueError, match="factor 5 must divide the image size 24x16"):
        area_downsample(images, 5)
    # written in place into a given array (AURD's bound graph input); another shape or dtype is refused
    out = np.full((2, 3, 3, 12, 8), np.nan, np.float32)
    assert area_downsample(images, 2, out=out) is out
    np.testing.assert_array_equal(out, area_downsample(images, 2))
    for bad in (np.zeros((2, 3, 3, 8, 12), np.float32), np.zeros((2, 3, 3, 12, 8), np.float64)):
        with pytest.raises(ValueError, match=r"out must be a C-contiguous float32 array of shape \(2, 3, 3, 12, 8\)"):
            area_downsample(images, 2, out=bad)


def test_demo_policy_encodes_its_agent_view_downsampled(tmp_path):
    """The recipe (full demo and quick) trains with the target encoder reading the agent view downsampled 4x
    (its cheap U_pred) at 80 px; a resolution the downsampling does not divide is refused."""
    from pivla.experiments.studies.demo import DemoConfig, quick, train_config
    from pivla.training.config import TrainConfig, with_twin_inputs

    assert TrainConfig().model.image_size == 80 and TrainConfig().model.target_encoder.downsample == 4
    for demo in (DemoConfig(), quick()):
        cfg = train_config(demo, tmp_path / "data", tmp_path / "run").model
        assert cfg.image_size == demo.image_size and cfg.target_encoder.downsample == 4
        target = CMSModel(with_twin_inputs(cfg), vocab_size=12).target
        assert target.downsample == 4 and cfg.target_encoder.stages == 0
        assert len(target.encoder.res) == len(cfg.backbone.vision_channels)
    with pytest.raises(ValueError, match="image size 90 px is not a multiple"):
        train_config(DemoConfig(image_size=90), tmp_path / "data", tmp_path / "run")


def test_the_demo_trains_the_recipe_and_its_cnn_widths_and_refreshes_can_be_set(tmp_path):
    from pivla.experiments.studies.demo import DemoConfig, train_config
    from pivla.training.config import TrainConfig, with_twin_inputs

    recipe = TrainConfig()
    default = train_config(DemoConfig(), tmp_path / "d", tmp_path / "r")
    assert default.model.backbone == recipe.model.backbone and default.value_refresh_every == 0
    fast = train_config(DemoConfig(vision_channels=(16, 32, 64, 128), value_refresh_every=2000), tmp_path / "d",
                        tmp_path / "r")
    assert fast.value_refresh_every == 2000 and fast.every(fast.value_refresh_every) == 2000
    assert dataclasses.replace(fast.model.backbone, vision_channels=recipe.model.backbone.vision_channels) \
        == recipe.model.backbone
    assert fast.loss == recipe.loss and (fast.lr, fast.steps, fast.batch_size) == (recipe.lr, recipe.steps,
                                                                                   recipe.batch_size)
    convs = [m for m in CMSModel(with_twin_inputs(fast.model), vocab_size=12).backbone.vision.net
             if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [16, 32, 64, 128]


def test_spatial_softmax_finds_a_peak_where_it_is():
    """A single strong feature at row 1, column 6 of an 8 x 8 map gives the keypoint at that pixel's
    coordinates in [-1, 1] (x from the column, y from the row)."""
    from pivla.model.backbone import SpatialSoftmax

    kp = SpatialSoftmax(channels=1, keypoints=1)
    with torch.no_grad():
        kp.detect.weight.fill_(1.0)
        kp.detect.bias.zero_()
        kp.log_temperature.fill_(-3.0)  # sharp softmax
    feats = torch.zeros(1, 1, 8, 8)
    feats[0, 0, 1, 6] = 5.0
    xy = kp(feats)[0, 0]
    grid = torch.linspace(-1, 1, 8)
    assert torch.allclose(xy, torch.stack([grid[6], grid[1]]), atol=1e-3)


def test_keypoint_tokens_can_be_switched_off():
    """keypoints=0 drops the spatial-softmax tokens (and their parameters); both variants give the same heads."""
    on = CMSModel(CFG, vocab_size=10)
    off_cfg = ModelConfig(image_size=32, backbone=BackboneConfig(d_model=64, n_layers=1,
                                                                 vision_channels=(16, 16, 32, 32), keypoints=0))
    off = CMSModel(off_cfg, vocab_size=10)
    assert on.backbone.keypoints is not None and off.backbone.keypoints is None
    assert not any("keypoints" in k or "kp_" in k for k in off.state_dict())
    batch = fake_batch()
    assert on(batch).continuous.shape == off(batch).continuous.shape == (3, CFG.chunk, CFG.action_dim)


def test_spatial_softmax_reads_checkpoints_with_a_0d_temperature():
    """The temperature is (1,) so FSDP can shard it; state dicts written when it was 0-d still load."""
    from pivla.model.backbone import SpatialSoftmax

    kp = SpatialSoftmax(channels=4, keypoints=2)
    old = {k: v.clone() for k, v in kp.state_dict().items()}
    old["log_temperature"] = torch.tensor(-1.5)
    kp.load_state_dict(old)
    assert kp.log_temperature.shape == (1,) and float(kp.log_temperature) == -1.5


def test_residual_stages_keep_resolution_and_feed_keypoints():
    """Residual blocks add parameters but not stages (same grid); keypoints can read a finer stage; the
    default (no blocks) has exactly the state-dict keys it always had, so old checkpoints load."""
    from pivla.model.backbone import ConvEncoder

    plain, deep = ConvEncoder((16, 16, 32, 32), 32), ConvEncoder((16, 16, 32, 32), 32, (0, 1, 1, 0))
    x = torch.rand(2, 1, 3, 32, 32)
    assert [s.shape for s in plain.stages(x)] == [s.shape for s in deep.stages(x)]
    assert set(plain.state_dict()) < set(deep.state_dict())
    assert all(k.startswith("net.") for k in plain.state_dict())
    with pytest.raises(ValueError, match="one count per stage"):
        ConvEncoder((16, 16, 32, 32), 32, (1, 1))
    fine = ModelConfig(image_size=32, backbone=BackboneConfig(d_model=64, n_layers=1, vision_channels=(16, 16, 32, 32),
                                                              res_blocks=(0, 1, 1, 0), keypoint_stage=-3))
    m = CMSModel(fine, vocab_size=10)
    assert m.backbone.keypoints.detect.in_channels == 16
    assert m(fake_batch()).continuous.shape == (3, CFG.chunk, CFG.action_dim)


def test_pooled_image_tokens_replace_the_grid():
    """grid_tokens=False gives each camera one pooled token (plus its keypoint token): the same heads from a
    much shorter sequence."""
    def cfg(grid: bool) -> ModelConfig:
        return ModelConfig(image_size=32, backbone=BackboneConfig(d_model=64, n_layers=1,
                                                                  vision_channels=(16, 16, 32, 32), grid_tokens=grid))

    grid, pooled = CMSModel(cfg(True), vocab_size=10), CMSModel(cfg(False), vocab_size=10)
    n_cam = len(CFG.cameras)
    assert grid.backbone.img_pos.shape[:3] == (1, n_cam, grid.backbone.vision.grid**2)
    assert pooled.backbone.img_pos.shape[:3] == (1, n_cam, 1)
    assert pooled(fake_batch()).continuous.shape == (3, CFG.chunk, CFG.action_dim)


def test_film_starts_as_the_plain_cnn_and_then_reads_the_instruction():
    """FiLM layers start at zero, so a FiLM model's first forward equals the same weights without FiLM; once
    they move, two instructions give the same pictures different features; the target encoder stays unconditioned."""
    def cfg(film: bool) -> ModelConfig:
        return ModelConfig(image_size=32, backbone=BackboneConfig(d_model=64, n_layers=1,
                                                                  vision_channels=(16, 16, 32, 32), film=film))

    torch.manual_seed(0)
    plain = CMSModel(cfg(False), vocab_size=12)
    film = CMSModel(cfg(True), vocab_size=12)
    missing, unexpected = film.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and missing and all(k.startswith("backbone.film.") for k in missing)
    batch = fake_batch()
    torch.testing.assert_close(film.eval()(batch).continuous, plain.eval()(batch).continuous)
    for lin in film.backbone.film:
        torch.nn.init.normal_(lin.weight, std=0.5)
    same_pictures = dict(batch, images=batch["images"][:1].expand_as(batch["images"]))
    feats = film.backbone.vision.stages(same_pictures["images"], film=film.backbone._film(same_pictures))[-1]
    assert not torch.allclose(feats[0], feats[1])  # one picture, two instructions, two readings
    pictures = batch["images"]
    torch.testing.assert_close(film.backbone.vision.pooled(pictures), plain.backbone.vision.pooled(pictures))
