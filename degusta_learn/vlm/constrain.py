"""Constrained decoding: a LogitsProcessor that keeps generated text inside the answer grammar.

At every step, for every sequence, the generated ids are decoded to text (the *decoded prefix*: with a
byte-level BPE a token's meaning depends on its neighbours, so the automaton reads the text, never
single token ids), the grammar state after that text is computed (cached by text), and every token
whose text would leave the grammar gets -inf. Which tokens fit a state is found by walking a trie of
the vocabulary's token strings together with the automaton, so only viable branches are visited (fast
even for Qwen's 150k vocabulary); results are cached per state. End-of-turn / EOS ids are allowed only
once the answer is complete, and then only they are. When the remaining budget of new tokens is down
to what closing the answer needs (one character per token, worst case), the grammar runs in closing
mode: no new cells or objects, only the way to "]". So a constrained answer always parses.

Example:
    proc = GrammarLogitsProcessor(AnswerGrammar("grid", catalog, grid), tokenizer, prompt_len, stop_ids,
                                  max_new_tokens=256)
    model.generate(**inputs, logits_processor=LogitsProcessorList([proc]), max_new_tokens=256)
"""

from __future__ import annotations

import torch

from degusta_learn.errors import DegustaError
from degusta_learn.vlm.grammar import AnswerGrammar

_VOCAB_CACHE: dict[int, tuple] = {}


def token_trie(tokenizer, alphabet: set[str]) -> dict:
    """Trie {char: node} of the vocabulary's token strings; a node's ids are under key None.

    Only tokens whose text uses `alphabet` characters are kept (no other token can ever fit).
    """
    key = id(tokenizer)
    if key in _VOCAB_CACHE and _VOCAB_CACHE[key][0] == frozenset(alphabet):
        return _VOCAB_CACHE[key][1]
    special = set(tokenizer.all_special_ids)
    n = len(tokenizer)
    texts = tokenizer.batch_decode([[i] for i in range(n)], skip_special_tokens=False,
                                   clean_up_tokenization_spaces=False)
    root: dict = {}
    for i, text in enumerate(texts):
        if i in special or not text or not set(text) <= alphabet:
            continue
        node = root
        for ch in text:
            node = node.setdefault(ch, {})
        node.setdefault(None, []).append(i)
    _VOCAB_CACHE[key] = (frozenset(alphabet), root)
    return root


class GrammarLogitsProcessor:
    """Masks every token that cannot continue a valid answer (a `transformers` LogitsProcessor)."""

    def __init__(self, grammar: AnswerGrammar, tokenizer, prompt_len: int, stop_ids: list[int],
                 max_new_tokens: int):
        if max_new_tokens <= grammar.max_chars_to_close:
            raise DegustaError(f"max_new_tokens: constrained decoding needs more than "
                               f"{grammar.max_chars_to_close} new tokens to guarantee a closed answer, "
                               f"got {max_new_tokens}")
        self.grammar, self.tokenizer = grammar, tokenizer
        self.prompt_len, self.stop_ids = prompt_len, list(stop_ids)
        self.max_new_tokens = max_new_tokens
        alphabet = set("[]{}',: \n.0123456789")
        for _, lit in grammar.parts:
            alphabet |= set(lit)
        alphabet |= {c for t in grammar.types for c in t}
        alphabet |= {c for c in "ABCDEFGHIJKLMNOPQRSTUVWXYZ_"}
        self.trie = token_trie(tokenizer, alphabet)
        self._states: dict[str, tuple] = {"": grammar.start()}
        self._masks: dict[tuple, torch.Tensor] = {}

    def state_of(self, text: str):
        """Grammar state after `text` (None if invalid), advancing from the longest cached prefix.

        The history is read without closing mode: it was valid when generated; closing mode only
        restricts what may come next.
        """
        if text in self._states:
            return self._states[text]
        base = text[:-1]
        while base not in self._states:
            base = base[:-1]
        state = self._states[base]
        if state is not None:
            state = self.grammar.feed(state, text[len(base):])
        self._states[text] = state
        return state

    def allowed(self, state, closing: bool) -> list[int]:
        if self.grammar.is_complete(state):
            return list(self.stop_ids)
        out: list[int] = []
        stack = [(self.trie, state)]
        while stack:
            node, st = stack.pop()
            for ch, child in node.items():
                if ch is None:
                    continue
                nxt = self.grammar.step(st, ch, closing)
                if nxt is None:
                    continue
                out.extend(child.get(None, ()))
                stack.append((child, nxt))
        return out

    def __call__(self, input_ids: torch.LongTensor, scores: torch.FloatTensor) -> torch.FloatTensor:
        new = input_ids[:, self.prompt_len:]
        closing = self.max_new_tokens - new.shape[1] <= self.grammar.max_chars_to_close
        mask = torch.full_like(scores, float("-inf"))
        for row in range(scores.shape[0]):
            text = self.tokenizer.decode(new[row], skip_special_tokens=False, clean_up_tokenization_spaces=False)
            state = self.state_of(text)
            if state is None:  # cannot happen under this processor; finish the sequence instead
                mask[row, self.stop_ids] = 0
                continue
            key = (state, closing)
            if key not in self._masks:
                ids = torch.tensor(self.allowed(state, closing) or self.stop_ids, dtype=torch.long)
                m = torch.full((scores.shape[1],), float("-inf"), dtype=scores.dtype)
                m[ids[ids < scores.shape[1]]] = 0
                self._masks[key] = m
            mask[row] = self._masks[key].to(scores.device)
        return scores + mask
