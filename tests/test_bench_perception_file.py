"""benchmarks/bench_perception.py writes strict JSON: the model card's reader refuses NaN."""

import json
import math

from benchmark_support import load_benchmark

from degusta_learn.files.jsonio import atomic_write_json, read_json


def test_perception_results_are_written_without_nan(tmp_path):
    """A task no question asked scores NaN (e.g. `transcribe_f1` among the perception questions); the file the
    bench writes, which `--write-card` reads back with the strict reader, holds null there instead."""
    bench = load_benchmark("bench_perception")
    result = bench.finite_or_null({"scores": {"transcribe_f1": math.nan, "object_f1": 0.25, "n": 3},
                                   "by": [math.inf, 1.0], "model": "m"})
    assert result == {"scores": {"transcribe_f1": None, "object_f1": 0.25, "n": 3}, "by": [None, 1.0], "model": "m"}
    assert "NaN" not in json.dumps(result)
    atomic_write_json(tmp_path / "perception.json", result)
    assert read_json(tmp_path / "perception.json") == result
