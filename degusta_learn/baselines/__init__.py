"""Baselines every method is reported beside.

- `heuristic.py`: `random`, `population_mean`, `copy_nearest`, `consensus` (numpy + scipy; no torch).
  The `oracle` floor lives with the synthetic data (`degusta_learn.synth.oracle`).
- `learned/`: learned PyTorch baselines (the `learned` trainer and method).

Each is a `MethodSpec` registered by name in `degusta_learn.methods.METHODS`; run one with
`degusta predict --config configs/baseline_copy_nearest.yaml`. Nothing is imported here, so
`degusta predict` with a heuristic baseline never imports torch.
"""
