"""The target encoder on ONNX Runtime: same latents as PyTorch, a cache keyed on the weights, and clear
fallbacks (tiny random model)."""

import logging

import numpy as np
import pytest
import torch

from pivla.data.normalize import ActionStats, NormStats, StandardStats
from pivla.data.text import WordTokenizer
from pivla.model import encoder_runtime as er
from pivla.model.cms import CMSModel
from pivla.model.config import BackboneConfig, ModelConfig, TargetEncoderConfig
from pivla.policy import Policy

pytestmark = pytest.mark.skipif(not er.onnx_available(), reason="onnxruntime / onnxscript not installed")


def make_policy(run_dir, runtime="onnx", seed=0, target="ema", downsample=1, cameras=1, stages=0, pool_grid=1):
    torch.manual_seed(seed)
    cfg = ModelConfig(image_size=32, backbone=BackboneConfig(d_model=64, n_layers=1, vision_channels=(16, 16, 32, 32)),
                      target_encoder=TargetEncoderConfig(name=target, grid=4, downsample=downsample, cameras=cameras,
                                                         stages=stages, pool_grid=pool_grid))
    text = WordTokenizer.build(["pick up the block"], cfg.max_text_len)
    stats = NormStats(ActionStats([-1.0] * 7, [1.0] * 7),
                      StandardStats([0.0] * cfg.proprio_dim, [1.0] * cfg.proprio_dim))
    return Policy(CMSModel(cfg, len(text.vocab)), stats, text, run_dir=run_dir, encoder_runtime=runtime)


def obs(seed):
    rng = np.random.default_rng(seed)
    o = {c: rng.integers(0, 255, (32, 32, 3), dtype=np.uint8) for c in ("agentview_rgb", "eye_in_hand_rgb")}
    o.update(ee_pos=np.zeros(3, np.float32), ee_ori=np.zeros(3, np.float32), gripper_states=np.zeros(2, np.float32),
             instruction="pick up the block")
    return o


def test_onnx_latents_match_torch_and_the_graph_is_cached(tmp_path):
    p = make_policy(tmp_path)
    assert p.encoder_runtime == "onnx"
    cached = list(tmp_path.glob("target_encoder-*.onnx"))
    assert len(cached) == 1
    p_torch = make_policy(tmp_path, runtime="torch")
    for s in range(3):
        np.testing.assert_allclose(p.encode(obs(s)), p_torch.encode(obs(s)), atol=1e-5, rtol=1e-4)
    # a batch (calibration) goes through PyTorch and agrees with the single encodings
    batch = p.encode_batch([obs(0), obs(1)])
    np.testing.assert_allclose(batch[1], p.encode(obs(1)), atol=1e-5, rtol=1e-4)
    # switching the runtime of a loaded policy
    p.set_encoder_runtime("torch")
    assert p.encoder_runtime == "torch" and p._onnx_encoder is None


def test_cache_is_reused_rebuilt_when_damaged_and_replaced_for_new_weights(tmp_path, monkeypatch):
    make_policy(tmp_path)
    (path,) = tmp_path.glob("target_encoder-*.onnx")

    def no_export(*args, **kwargs):
        raise AssertionError("exported although the cached graph belongs to these weights")

    with monkeypatch.context() as m:
        m.setattr(er, "export_onnx", no_export)
        assert make_policy(tmp_path).encoder_runtime == "onnx"
    path.write_bytes(b"not an onnx graph")
    p = make_policy(tmp_path)
    assert p.encoder_runtime == "onnx" and path.read_bytes() != b"not an onnx graph"
    make_policy(tmp_path, seed=1)  # other weights: their own graph, the old one removed
    (new,) = tmp_path.glob("target_encoder-*.onnx")
    assert new != path
    # same weights, downsampled input: another graph, which agrees with PyTorch
    p = make_policy(tmp_path, seed=1, downsample=2)
    (down,) = tmp_path.glob("target_encoder-*.onnx")
    assert down != new and p.encoder_runtime == "onnx"
    np.testing.assert_allclose(p.encode(obs(0)), make_policy(None, "torch", seed=1, downsample=2).encode(obs(0)),
                               atol=1e-5, rtol=1e-4)


def test_a_graph_that_disagrees_with_torch_is_not_used_nor_cached(tmp_path, monkeypatch, caplog):
    real = er.OnnxEncoder.__call__
    with monkeypatch.context() as m:
        m.setattr(er.OnnxEncoder, "__call__", lambda self, images: real(self, images) + 0.1)
        with caplog.at_level(logging.WARNING):
            p = make_policy(tmp_path, runtime="auto")
        assert p.encoder_runtime == "torch" and "disagrees with PyTorch" in caplog.text
        assert not list(tmp_path.glob("target_encoder-*.onnx"))
        with pytest.raises(RuntimeError, match="encoder_runtime 'onnx'"):
            make_policy(tmp_path, runtime="onnx")
    # a cached graph that disagrees (the encoder's code changed since) is exported again, then used
    make_policy(tmp_path)
    real_export, calls, exports = er.export_onnx, [], []

    def off_on_first_call(self, images):  # the cached graph's check fails, the fresh graph's passes
        calls.append(1)
        return real(self, images) + (0.1 if len(calls) == 1 else 0.0)

    def counted_export(*args):
        exports.append(1)
        return real_export(*args)

    with monkeypatch.context() as m:
        m.setattr(er.OnnxEncoder, "__call__", off_on_first_call)
        m.setattr(er, "export_onnx", counted_export)
        assert make_policy(tmp_path).encoder_runtime == "onnx"
    assert len(exports) == 1 and len(list(tmp_path.glob("target_encoder-*.onnx"))) == 1


def test_runtime_choice_is_checked(tmp_path):
    with pytest.raises(ValueError, match="encoder_runtime must be one of"):
        make_policy(tmp_path, runtime="tensorrt")
    # a weight-free thumbnail target is not exported: auto stays on PyTorch, onnx says why
    assert make_policy(tmp_path, runtime="auto", target="thumbnail").encoder_runtime == "torch"
    with pytest.raises(RuntimeError, match="only the small backbone's CNN"):
        make_policy(tmp_path, runtime="onnx", target="thumbnail")
    # no run directory: exported in memory, nothing written
    assert make_policy(None).encoder_runtime == "onnx"


@pytest.mark.parametrize("stages", [0, 3])
def test_downsampled_two_camera_target_matches_torch_and_refuses_a_wrong_shape(tmp_path, stages):
    """The graph starts after the NumPy pooling and centring: both cameras, 4x smaller, all or three CNN
    stages, same latents as the PyTorch target on the full picture; an input of another shape is refused."""
    p = make_policy(tmp_path, downsample=4, cameras=2, stages=stages)
    assert p.encoder_runtime == "onnx" and p._onnx_encoder.input_shape == (1, 2, 3, 8, 8)
    p_torch = make_policy(None, "torch", downsample=4, cameras=2, stages=stages)
    for s in range(3):
        np.testing.assert_allclose(p.encode(obs(s)), p_torch.encode(obs(s)), atol=1e-5, rtol=1e-4)
    assert p.encode(obs(0)).shape == (64,)  # two cameras of 32 channels (stages 3 and 4 both have 32)
    with pytest.raises(ValueError, match=r"takes images of shape \(1, 2, 3, 8, 8\), got \(1, 2, 3, 16, 16\)"):
        p._onnx_encoder(np.zeros((1, 2, 3, 16, 16), np.float32))
    # the result is a copy: a later encoding does not change an earlier latent
    first = p.encode(obs(0))
    kept = first.copy()
    p.encode(obs(1))
    np.testing.assert_array_equal(first, kept)
    # a bad picture is refused by name, and the next good one encodes as before
    bad = {**obs(0), "eye_in_hand_rgb": obs(0)["eye_in_hand_rgb"].astype(np.float32)}
    with pytest.raises(ValueError, match="'eye_in_hand_rgb' must be an HxWx3 uint8 image"):
        p.encode(bad)
    np.testing.assert_array_equal(p.encode(obs(0)), kept)
    # a picture of another size is resized to the model's first, as in the batch path
    big = {**obs(2), "agentview_rgb": np.repeat(np.repeat(obs(2)["agentview_rgb"], 2, 0), 2, 1)}
    np.testing.assert_allclose(p.encode(big), p_torch.encode(big), atol=1e-5, rtol=1e-4)


def test_a_grid_pooled_target_matches_torch(tmp_path):
    """pool_grid 2: the last feature map averaged per quadrant (4 x 32 numbers), in the ONNX graph as in
    PyTorch."""
    p = make_policy(tmp_path, pool_grid=2)
    p_torch = make_policy(None, "torch", pool_grid=2)
    assert p.encoder_runtime == "onnx" and p.encode(obs(0)).shape == (128,)
    for s in range(3):
        np.testing.assert_allclose(p.encode(obs(s)), p_torch.encode(obs(s)), atol=1e-5, rtol=1e-4)
