"""A domain tokenizer for small VLMs trained here: answer literals, object ids and grid cells as single tokens.

The tiny test models use a plain byte-level BPE (`random_models.common.train_tokenizer`), which spends ~30 tokens on one
answer item. A model that must *learn* the task on a CPU should spend its steps on decisions, not on
spelling punctuation, so this tokenizer

- keeps every literal piece of `prompting.format_answer` (`[{'type': '`, `', 'id': `, `, 'position': ['`,
  `', '`, ...) as one added token, so an item reads type | literal | id | literal | cell | ', ' | cell ...;
- pre-tokenizes grid cell ids (`D5`) and numbers up to three digits as units, so BPE makes each object
  id (0-124) and each cell one token;
- is otherwise a byte-level BPE (any text encodes) trained with the `tokenizers` library, in under a
  second, on the task corpus (prompt texts, perception questions, answers).

A grid answer item then costs 7 + 2 x cells tokens (about 13) instead of about 30. Constrained decoding
is unaffected: it reads decoded text, whatever the segmentation.

Example:
    tok = domain_tokenizer(IDEFICS3_SPECIAL, vocab_size=2048)      # a tokenizers.Tokenizer
"""

from __future__ import annotations

import random

# A space before an object type, a number or a grid cell is a token of its own, so "cup", "17" and "C7" are
# the same tokens in a question ("the cup with object_reference_id 17") as in an answer ("'cup', 'id': 17").
_CONTENT = r"cup|fork|knife|plate|spoon|[0-9]|[A-Z][0-9]"
_PRETOKENS = (rf"\s(?={_CONTENT})|[A-Z][0-9]{{1,2}}(?![0-9A-Za-z_])|[0-9]{{1,3}}| ?[A-Za-z_]+| ?[^\sA-Za-z0-9]+|\s+")


def answer_literals() -> list[str]:
    """The literal pieces between the slots of the grid and unmarked answer formats (format_answer)."""
    return ["[{'type': '", "', 'id': ", ", 'position': ['", "', '", "'], 'cardinal_direction': '",
            "'}, {'type': '", "'}]", ", 'position': [", "], 'rotation': ", "}, {'type': '", "}]"]


def perception_corpus(n: int = 300, seed: int = 0) -> list[str]:
    """Texts of the perception questions (pretrain/tasks.py) with varied names, types and numbers."""
    from degusta_learn.pretrain.tasks import describe_question, gomo_question, list_question, locate_question

    rng = random.Random(seed)
    types = ["cup", "fork", "knife", "plate", "spoon"]
    lines = []
    for _ in range(n):
        name = f"final_state_{rng.randint(1, 4)}.jpg"
        t = rng.choice(types)
        lines += [list_question(name, types), describe_question(name, t, rng.randint(0, 124)),
                  gomo_question(f"objects_{t}.jpg", t, rng.randint(4, 25), rng.randint(1, 5), rng.randint(1, 5)),
                  locate_question(name, [(rng.choice(types), rng.randint(0, 124)) for _ in range(rng.randint(1, 8))]),
                  str(rng.randint(0, 124))]
    return lines


def domain_tokenizer(special_tokens: list[str], vocab_size: int = 2048):
    """Train the domain tokenizer (see the module docstring); special tokens get the first ids."""
    from tokenizers import AddedToken, Regex, Tokenizer, decoders, models, pre_tokenizers, trainers

    from degusta_learn.vlm.random_models.common import task_corpus

    tok = Tokenizer(models.BPE())
    tok.pre_tokenizer = pre_tokenizers.Sequence([
        pre_tokenizers.Split(Regex(_PRETOKENS), behavior="isolated"),
        pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False)])
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(vocab_size=vocab_size, special_tokens=special_tokens, show_progress=False,
                                  initial_alphabet=pre_tokenizers.ByteLevel.alphabet())
    corpus = task_corpus(n_answers=1500) + perception_corpus()
    corpus += [",".join(f"{chr(65 + c)}{r}" for c in range(12) for r in range(1, 13))] * 20
    corpus += [" ".join(str(i) for i in range(1000))] * 5 + [",".join(str(i) for i in range(256))] * 30
    tok.train_from_iterator(corpus, trainer=trainer)
    tok.add_tokens([AddedToken(s, normalized=False, special=False) for s in answer_literals()])
    return tok
