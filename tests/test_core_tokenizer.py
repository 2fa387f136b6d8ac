import numpy as np
import torch

from pivla.model.tokenizer import ActionTokenizer, bin_centers, decode, dequantize, encode


def test_bin_centers_uniform_on_unit_interval():
    c = bin_centers(256)
    assert c.shape == (256,)
    np.testing.assert_allclose(c[0], -1 + 1 / 256)
    np.testing.assert_allclose(c[-1], 1 - 1 / 256)
    np.testing.assert_allclose(np.diff(c), 2 / 256, rtol=1e-5)


def test_round_trip_within_half_a_bin():
    tok = ActionTokenizer()
    x = np.random.default_rng(0).uniform(-1, 1, size=(1000, 7)).astype(np.float32)
    err = np.abs(tok.decode(tok.encode(x)) - x)
    assert err.max() <= (1 / 256) + 1e-6  # half of the bin width 2/256


def test_encode_clips_out_of_range_and_matches_torch():
    x = np.array([-5.0, -1.0, 0.0, 0.999, 1.0, 7.0], np.float32)
    b = encode(x)
    assert b.tolist() == [0, 0, 128, 255, 255, 255]
    assert encode(torch.from_numpy(x)).tolist() == b.tolist()
    assert decode(torch.from_numpy(b), bin_centers()).shape == (6,)


def test_dequantize_eq12_hand_computed():
    # 4 bins on [-1,1]: centres -0.75, -0.25, 0.25, 0.75
    centers = bin_centers(4)
    probs = np.array([[0.1, 0.2, 0.3, 0.4], [1.0, 0.0, 0.0, 0.0]], np.float32)
    expected = [0.1 * -0.75 + 0.2 * -0.25 + 0.3 * 0.25 + 0.4 * 0.75, -0.75]
    np.testing.assert_allclose(dequantize(probs, centers), expected, atol=1e-6)
    np.testing.assert_allclose(dequantize(torch.from_numpy(probs), centers).numpy(), expected, atol=1e-6)
