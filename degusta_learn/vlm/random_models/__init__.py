"""Random-weight VLMs built offline and saved like Hub models: the one home of the toolkit's model builders.

- tiny.py: tiny Idefics3 (SmolVLM's architecture) and Qwen2-VL models of ~1 MB for CPU tests and smoke configs
  (`build_tiny_idefics3`, `build_tiny_qwen2vl`, `ensure_tiny`);
- replicas.py: full-size replicas of the GPU configs' models (published architecture and processor, random
  weights) to check parameter counts, token budgets and memory offline (`build_replica`, `meta_replica`);
- common.py: the task tokenizer and generation ids every builder shares (also used by `pretrain.base`, which
  builds the tiny base's FastVLM from random weights).
"""
