"""The benchmark commands run and report their keys (their numbers are measured, never asserted)."""

import json

from pivla.cli import main
from pivla.data.read import read_dataset


def test_bench_infer_json(capsys):
    assert main(["bench", "infer", "--runs", "3", "--warmup", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"forward_ms_median", "hz", "threads"} <= set(out) and out["forward_ms_median"] > 0


def test_bench_control_json(capsys):
    assert main(["bench", "control", "--steps", "6", "--repeats", "1", "--loop-episodes", "0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"fixed_ms_per_step", "aurd_ms_per_step", "aurd_overhead_pct"} <= set(out)
    assert out["policy_queries"]["aurd"] == out["policy_queries"]["fixed"]  # same plans: the gap is pure overhead
    assert not any(k.startswith("loop_") for k in out)


def test_bench_train_json_for_both_token_layouts_and_the_libero_preset(capsys):
    il_only = ["--loss.no-use-sp", "--loss.no-use-rl", "--loss.no-use-recon"]
    for extra in ([], ["--grid-tokens"], ["--preset", "libero"], il_only):
        assert main(["bench", "train", "--steps", "4", "--batch-size", "2", "--threads", "1", "--json", *extra]) == 0
        out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert out["grid_tokens"] is ("--grid-tokens" in extra) and out["samples_per_s"] > 0
        assert out["value_refresh_ms_per_frame"] > 0
        assert (out["image_size"], out["cameras"]) == ((128, 2) if "--preset" in extra else (80, 2))
        assert out["loss"]["use_sp"] is (extra != il_only)


def test_bench_data_json(capsys, synthetic_data):
    episodes = read_dataset(synthetic_data)
    frames = sum(len(ep.actions) for ep in episodes)
    for store in ("memory", "disk"):
        assert main(["bench", "data", "--data", str(synthetic_data), "--image-store", store, "--json"]) == 0
        out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert out["episodes"] == len(episodes) and out["frames"] == frames and out["image_store"] == store
        assert out["pictures_gb"] == round(frames * 2 * 80 * 80 * 3 / 1e9, 3)  # resized to the recipe's 80 px
        assert {"load_s", "peak_rss_gb", "anon_rss_gb_after", "file_rss_gb_after"} <= set(out)
