"""benchmarks/bench_perception.py: where the training curve of a benchmarked model goes."""

from benchmark_support import load_benchmark


def test_only_the_shipped_base_writes_the_docs_figure(tmp_path, monkeypatch):
    bench = load_benchmark("bench_perception")
    monkeypatch.chdir(tmp_path)
    assert bench.curve_path("checkpoints/tiny_vlm_base", "runs/x") == "docs/images/base_perception_curve.png"
    assert bench.curve_path(str(tmp_path / "checkpoints" / "tiny_vlm_base"), "runs/x") == bench.SHIPPED_CURVE
    assert bench.curve_path("/work/pilots/base_tr3", "runs/x") == "runs/x/perception_curve.png"
