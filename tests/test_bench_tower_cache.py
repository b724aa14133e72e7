"""benchmarks/bench_tower_cache.py on a random-weight tiny base: same losses through the cache, pictures counted."""

from benchmark_support import load_benchmark

from degusta_learn.pretrain.base import BaseArchitecture
from degusta_learn.pretrain.export import save_random_base


def test_the_cache_changes_no_loss_and_counts_an_epochs_distinct_pictures(small_dataset_dir, tmp_path, capsys):
    base = save_random_base(tmp_path / "base", BaseArchitecture(
        vision_channels=[8, 8, 16, 16], vision_stem=8, text_hidden=32, text_layers=2, text_heads=4, text_kv_heads=1,
        text_intermediate=64, vocab_size=2048))
    r = load_benchmark("bench_tower_cache").main(["--dataset", str(small_dataset_dir), "--base", str(base),
                                                  "--batches", "1", "--epoch-steps", "2", "--threads", "1"])
    assert r["loss_difference"] == 0.0
    assert r["pictures"] == 2 * 8 * 6  # two batches of 8 MOGMA context-4 prompts, 6 pictures each
    assert r["distinct"] < r["pictures"] // 2  # one object sheet, a few tables, a person's arrangements
    assert "ratio" in capsys.readouterr().out
