"""Fine-tuning small open VLMs on lifted images (see docs/finetune.md).

Model loading, generation, the answer grammar, constrained decoding and the tiny model builders live in
`degusta_learn.vlm` (shared with the zero-shot `hf` backend). Here: data.py renders training examples on
the fly; collate.py turns them into batches supervising only the answer; lora.py sets up LoRA / full /
QLoRA; loss.py, module.py and train.py train with Lightning (`degusta train`, kind finetune); vocab.py
is the domain tokenizer of pretrain/ (the tiny base). Nothing here imports torch at package import time.
"""
