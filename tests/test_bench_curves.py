"""benchmarks/bench_perception.py and bench_vlm.py: a pilot run's curve never replaces the docs' figure."""

from argparse import Namespace

from benchmark_support import load_benchmark

from degusta_learn.shipped import BASE_DIR


def test_only_the_shipped_base_writes_the_perception_figure(tmp_path, monkeypatch):
    bench = load_benchmark("bench_perception")
    monkeypatch.chdir(tmp_path)
    assert bench.curve_path(str(BASE_DIR), "runs/x") == "docs/images/base_perception_curve.png"
    assert bench.curve_path("runs/tiny_vlm_base", "runs/x") == "runs/x/perception_curve.png"  # another folder
    assert bench.curve_path("/work/pilots/base_tr3", "runs/x") == "runs/x/perception_curve.png"


def test_only_the_documented_fine_tuning_run_writes_the_learning_curve_figure():
    bench = load_benchmark("bench_vlm")
    documented = dict(base=str(BASE_DIR), episodes=None, overrides=[], predict_overrides=[], out="runs/b")
    assert bench.curve_path(Namespace(**documented)) == "docs/images/vlm_learning_curve.png"
    for change in ({"base": "/work/pilots/base_tr3"}, {"episodes": 20}, {"overrides": ["data.context_answers=true"]},
                   {"predict_overrides": ["decoding.on_repeat=stop"]}):
        assert bench.curve_path(Namespace(**{**documented, **change})) == "runs/b/learning_curve.png", change


def test_the_shipped_base_by_name_is_the_documented_run(tmp_path, monkeypatch):
    bench = load_benchmark("bench_perception")
    monkeypatch.chdir(tmp_path)
    assert bench.curve_path("tiny_vlm_base", "runs/x") == "docs/images/base_perception_curve.png"
