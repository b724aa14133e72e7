"""Local vision-language models, shared by zero-shot prompting (the `hf` backend) and fine-tuning.

hub.py says where a model comes from (a folder, a shipped model, or a Hub id downloaded into the Hugging Face
cache unless HF_HUB_OFFLINE); load.py loads it with its processor and an optional peft adapter;
inputs.py is the chat format, prompt encoding and image budget (and the grid-resolution check);
prompt_options.py cuts a prompt down for a small model (image groups, composed canvases);
grammar.py + constrain.py + generate.py generate answers, optionally constrained to the answer grammar;
tiny.py builds random-weight tiny Idefics3 / Qwen2-VL models offline; replicas.py builds full-size
random-weight replicas of the GPU configs' models; record.py is the typed, versioned record a trained model
folder carries (degusta_finetune.json, degusta_base.json): fine-tuning writes it, the hf backend reads it;
settings.py is the one `model:` and `decoding:` config section every config kind that runs a VLM uses (fine-tuning,
pretraining's validation, every zero-shot predict config).
It stands below `prompting` and `finetune`: it imports only prompting's prompt and answer types, never its
runner or backends, and nothing from finetune.
Nothing here imports torch at package import time.
"""
