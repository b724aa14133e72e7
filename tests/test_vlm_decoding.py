"""What constrained decoding records: the free answer behind every constrained one (coupled sampling), the
answers the token budget closed early, token budgets derived from the data, and a vocabulary trie cache
that cannot hand one tokenizer's trie to another."""

from __future__ import annotations

import gc

import pytest
from finetune_support import GRID, dataset, examples, load

from degusta_learn.prompting import AnswerParseError, answer_items, format_answer, parse_answer
from degusta_learn.vlm.constrain import token_trie
from degusta_learn.vlm.generate import answer_token_budget, generate_answers
from degusta_learn.vlm.grammar import AnswerGrammar


class FakeTokenizer:
    """A tokenizer of `words` (one token each), enough for `token_trie`."""

    all_special_ids: list[int] = []

    def __init__(self, words):
        self.words = words

    def __len__(self):
        return len(self.words)

    def batch_decode(self, ids, **_):
        return [self.words[i[0]] for i in ids]


def trie_words(node, prefix=""):
    out = {prefix} if None in node else set()
    for ch, child in node.items():
        if ch is not None:
            out |= trie_words(child, prefix + ch)
    return out


def test_token_trie_is_never_taken_from_a_dead_tokenizer_whose_id_was_reused():
    """The cache was keyed by id(tokenizer): a new tokenizer at a freed address got the old one's trie."""
    alphabet = set("abc")
    first = FakeTokenizer(["a", "b"])
    words = trie_words(token_trie(first, alphabet))  # not inside `assert`: pytest would keep `first` alive
    assert words == {"a", "b"}
    old_id = id(first)
    del first
    gc.collect()
    keep, other = [], ["c", "cc"]  # new tokenizers until one lands at the freed address (CPython reuses it)
    for _ in range(10_000):
        tok = FakeTokenizer(other)
        if id(tok) == old_id:
            break
        keep.append(tok)
    assert trie_words(token_trie(tok, alphabet)) == {"c", "cc"}
    if id(tok) != old_id:  # the allocator (not the code) decides; seen in CI under memory pressure
        pytest.skip("no tokenizer reused the freed address in this run; the cache key was not exercised")


def test_token_trie_follows_added_tokens():
    alphabet = set("abc")
    tok = FakeTokenizer(["a"])
    assert trie_words(token_trie(tok, alphabet)) == {"a"}
    tok.words.append("ab")  # tokenizer.add_tokens(...)
    assert trie_words(token_trie(tok, alphabet)) == {"a", "ab"}


@pytest.fixture(scope="module")
def tiny():
    model, processor = load("idefics3")
    return model, processor, examples(context=2)[0].prompt, AnswerGrammar("grid", dataset().catalog, GRID)


def test_free_pass_gives_exactly_what_free_decoding_writes(tiny, one_torch_thread):
    """Coupled sampling: the free answer recorded beside each constrained one is the answer of a free run
    with the same seed; where the grammar changed nothing, the constrained answer is that free answer."""
    model, processor, prompt, grammar = tiny
    for temperature in (0.0, 1.0):
        con = generate_answers(model, processor, prompt, n=3, temperature=temperature, max_new_tokens=140,
                               constrained=True, grammar=grammar, seed=7, free_pass=True)
        free = generate_answers(model, processor, prompt, n=3, temperature=temperature, max_new_tokens=140, seed=7)
        for c, f in zip(con, free):
            parse_answer(c.text, "grid", dataset().catalog, GRID)
            assert c.decoding["constrained"] and not f.decoding["constrained"]
            if c.decoding["grammar_changed"]:
                assert c.decoding["free_text"] == f.text and c.decoding["free_cut"] == f.decoding["cut"]
            else:
                assert c.decoding["free_text"] is None and c.text == f.text
        # random weights: the grammar changes the answers, and their free versions do not parse
        assert all(c.decoding["grammar_changed"] for c in con)
        with pytest.raises(AnswerParseError):
            parse_answer(con[0].decoding["free_text"], "grid", dataset().catalog, GRID)


def test_budget_closes_are_recorded(tiny, one_torch_thread):
    """A budget just above the closing reserve forces answers shut; a generous one does not."""
    model, processor, prompt, grammar = tiny
    tight = generate_answers(model, processor, prompt, n=4, temperature=1.5, constrained=True, grammar=grammar,
                             max_new_tokens=grammar.max_chars_to_close + 4, seed=1)
    assert any(c.decoding["forced_close"] for c in tight)
    for c in tight:
        parse_answer(c.text, "grid", dataset().catalog, GRID)
    free = generate_answers(model, processor, prompt, n=2, temperature=1.0, max_new_tokens=12, seed=1)
    assert all(c.decoding["cut"] and c.output_tokens == 12 for c in free)


def test_token_budget_fits_every_ground_truth_answer(tiny):
    _, processor, _, grammar = tiny
    ds = dataset()
    tok = processor.tokenizer
    free = answer_token_budget(tok, ds, "grid", GRID)
    con = answer_token_budget(tok, ds, "grid", GRID, grammar=grammar)
    lengths = [len(tok(format_answer(answer_items(list(a.placements), ds.catalog, "grid", GRID), "grid"),
                       add_special_tokens=False)["input_ids"]) for a in ds.arrangements]
    assert free["answer_max"] == max(lengths) and free["answers"] == len(ds.arrangements)
    assert free["max_new_tokens"] > max(lengths)  # the longest answer and its end-of-turn token fit
    # constrained: closing mode starts only after the longest answer (it reserves max_chars_to_close)
    assert con["max_new_tokens"] - grammar.max_chars_to_close > max(lengths)
