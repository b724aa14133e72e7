"""What every random-weight VLM builder shares: the task tokenizer, its transformers wrapper, generation ids.

The tiny models (tiny.py), the full-size replicas (replicas.py) and the tiny base's FastVLM (pretrain/base.py) are
built from these: a byte-level BPE trained in well under a second on the task's own texts (`train_tokenizer`,
`task_corpus`), wrapped as a transformers tokenizer without token_type_ids (`wrap_tokenizer`), and the generation
config's eos / pad / bos ids (`set_generation_ids`).
"""

from __future__ import annotations

import random

# Paper prompts (appendix) and the words every answer uses: the tokenizer's training text.
_PAPER_PROMPTS = (
    "My preferences for setting a table are shown in the images named final_state_N.jpg. You are helping me "
    "set the table in initial_state_1.jpg according to my preferences. What objects should I place in this "
    "image, where should I place them, and how should they be oriented? Please list all grid cells the object "
    "will intersect after it is placed. Give the orientation as the closest cardinal direction [N, NE, E, SE, "
    "S, SW, W, NW] the object is pointing in after it is placed. The top of the image is N. Give your answer as "
    "a python list formatted as follows: [{'type':object_type, 'id': object_reference_id, "
    "'position':[grid_cell_ids], 'cardinal_direction':direction}]. Give grid_cell_ids as a list of string. "
    "Give object_id as an integer. Include only this list in your response.",
    "Give a position in [x,y] where each value is a number between 0 and 1. Give rotation as the number of "
    "degrees clockwise from image north. Give your answer as a python list formatted as follows: "
    "[{'type':object_type, 'id': object_reference_id, 'position': [x, y], 'rotation': degrees}].",
    "The objects you can use are shown in the images named cup.jpg, fork.jpg, knife.jpg, plate.jpg, spoon.jpg, "
    "each object marked with its id. Placement order in final_state_1.jpg: plate, fork, knife, spoon, cup.",
)


_TYPES = ("cup", "fork", "knife", "plate", "spoon")


_DIRECTIONS = ("N", "NE", "E", "SE", "S", "SW", "W", "NW")


def task_corpus(n_answers: int = 400, seed: int = 0) -> list[str]:
    """In-domain training text for the tiny tokenizers: prompts, answers, cell ids, numbers."""
    rng = random.Random(seed)
    cells = [f"{chr(65 + c)}{r}" for c in range(12) for r in range(1, 13)]
    lines = list(_PAPER_PROMPTS)
    for _ in range(n_answers):
        items = []
        for _ in range(rng.randint(1, 6)):
            t = rng.choice(_TYPES)
            pos = sorted(rng.sample(cells, rng.randint(1, 4)))
            items.append(f"{{'type': '{t}', 'id': {rng.randint(0, 124)}, 'position': {pos}, "
                         f"'cardinal_direction': '{rng.choice(_DIRECTIONS)}'}}")
            items.append(f"{{'type': '{t}', 'id': {rng.randint(0, 124)}, 'position': "
                         f"[{rng.random():.3f}, {rng.random():.3f}], 'rotation': {rng.randint(0, 359)}}}")
        lines.append("[" + ", ".join(items) + "]")
    lines += _prompt_texts()
    lines.append(" ".join(str(i) for i in range(400)))
    lines.append(" ".join(f"final_state_{i}.jpg initial_state_{i}.jpg" for i in range(1, 6)))
    return lines


def _prompt_texts() -> list[str]:
    """The prompting part's own task texts and chat-template words (the bulk of every prompt)."""
    from degusta_learn.names import PROMPT_METHODS
    from degusta_learn.render.grid import Grid
    from degusta_learn.task.prompt import task_text

    lines = ["User: Assistant: system You are a helpful assistant. user assistant",
             "These are the objects I have, one image per object type. Each object is marked with its "
             "object_reference_id.", "objects.jpg shows the images objects_cup.jpg, objects_fork.jpg, "
             "objects_knife.jpg side by side, each titled with its name:"]
    for method in PROMPT_METHODS:
        for k in (0, 1, 2, 4):
            names = [f"final_state_{i}.jpg" for i in range(1, k + 1)]
            lines.append(task_text(method, names, "initial_state_1.jpg", Grid(8, 8), list(_TYPES)))
    for k in range(1, 5):
        lines.append(f"Placement order in final_state_{k}.jpg: " + ", ".join(_TYPES[(k + i) % 5] for i in range(6)) + ".")
    return lines * 4


def train_tokenizer(special_tokens: list[str], vocab_size: int = 1024):
    """A byte-level BPE (`tokenizers`) trained on `task_corpus()`; special tokens get the first ids."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers

    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(vocab_size=vocab_size, special_tokens=special_tokens, show_progress=False,
                                  initial_alphabet=pre_tokenizers.ByteLevel.alphabet())
    tok.train_from_iterator(task_corpus(), trainer=trainer)
    return tok


def wrap_tokenizer(tok, cls, special: list[str], **tokens):
    """Wrap a `tokenizers.Tokenizer` as a transformers tokenizer without token_type_ids."""
    wrapped = cls(tokenizer_object=tok, **tokens)
    wrapped.add_special_tokens({"additional_special_tokens": [s for s in special if s not in tokens.values()]})
    wrapped.model_input_names = ["input_ids", "attention_mask"]
    return wrapped


def set_generation_ids(model, tokenizer, eos_id: int, pad_id: int) -> None:
    gc = model.generation_config
    gc.eos_token_id, gc.pad_token_id, gc.bos_token_id = eos_id, pad_id, tokenizer.bos_token_id
