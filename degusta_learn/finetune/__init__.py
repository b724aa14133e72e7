"""Fine-tuning small open VLMs on lifted images (see docs/finetune.md).

tiny.py builds random-weight tiny Idefics3 / Qwen2-VL models offline; model.py loads any VLM (hub id
or folder) offline with an optional peft adapter; data.py renders training examples on the fly;
inputs.py + collate.py turn them into batches supervising only the answer; lora.py sets up LoRA /
full / QLoRA; loss.py, module.py and train.py train with Lightning (`degusta train`, kind finetune);
grammar.py + constrain.py + generate.py generate answers, optionally constrained to the answer grammar.
Nothing here imports torch at package import time.
"""
