"""Constrained decoding: the answer grammar as a token mask, and a sampler that records what it changed.

`GrammarLogitsProcessor` (a `transformers` LogitsProcessor) masks every token that cannot continue a
valid answer. At every step, for every sequence, the generated ids are decoded to text (the *decoded
prefix*: with a byte-level BPE a token's meaning depends on its neighbours, so the automaton reads the
text, never single token ids), the grammar state after that text is computed (cached by text), and every
token whose text would leave the grammar gets -inf. Which tokens fit a state is found by walking a trie of
the vocabulary's token strings together with the automaton, so only viable branches are visited (fast
even for Qwen's 150k vocabulary); results are cached per state. End-of-turn / EOS ids are allowed only
once the answer is complete, and then only they are. When the remaining budget of new tokens is down to
what closing the answer needs (one character per token, worst case: `AnswerGrammar.max_chars_to_close`),
the grammar runs in closing mode: no new cells or objects, only the way to "]". So a constrained answer
always parses.

`Sampler` picks every next token itself, by the Gumbel-max trick: token = argmax(logits / T + G) with
Gumbel noise G drawn from one seeded generator per sequence (T = 0: plain argmax). That is exact
sampling at temperature T (no top-k / top-p), and it couples free and constrained decoding: with the same
seeds, a free run picks the same tokens as the constrained one until the first step where the grammar
refused the free pick. So the sampler records, per sequence,

- `grammar_changed`: the grammar refused the token free decoding would have picked (else the constrained
  answer *is* the free answer, token for token);
- `forced_close`: in closing mode, the budget refused the token the grammar alone would have allowed (the
  token budget closed the answer early: fewer cells or objects than the model was writing);

- `repeat_stop` (`on_repeat="stop"`): the free pick named again an object an earlier item had placed
  (`AnswerGrammar.repeats`), which the grammar refuses. A small model that has listed what it sees starts
  over; forced onto the next unused id it would go on inventing objects until the token budget runs out
  (measured: 16-19 items where the free answer had 5). So the sequence stops
  there and `generate` keeps the items before the repeat (the answer ends after its last complete item).
  (`on_repeat: skip`, generate's default, gives the sampler a grammar that allows the repeat instead:
  `AnswerGrammar.allowing_repeats`);
- `alternatives` (`on_repeat="substitute"`, with a grammar that allows repeats): where the model's pick names an
  object again, the ids of that item's type not yet placed, ranked by the model's scores at that step; `generate`
  gives the item the best one no other item names (`substitute_repeats`);

and a free pass with the same seeds (`generate.generate_answers`) gives the exact free answer of every
sequence the grammar changed. The sampler hands `generate` a one-hot distribution, so `generate` must run
with do_sample=True, temperature 1, top_k 0, top_p 1 (nothing else reshapes it).

Example:
    proc = GrammarLogitsProcessor(AnswerGrammar("grid", catalog, grid), tokenizer, prompt_len, stop_ids,
                                  max_new_tokens=256)
    sampler = Sampler(temperature=1.0, seeds=[0, 1], stop_ids=stop_ids, grammar=proc)
    model.generate(**inputs, logits_processor=LogitsProcessorList([sampler]), max_new_tokens=256,
                   do_sample=True, temperature=1.0, top_k=0, top_p=1.0, num_return_sequences=2)
    sampler.grammar_changed, sampler.forced_close     # one flag per sequence
"""

from __future__ import annotations

import weakref

import torch

from degusta_learn.errors import DegustaError
from degusta_learn.task.grammar import AnswerGrammar

_TRIES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""tokenizer -> {(alphabet, vocabulary size): trie}; an entry goes when its tokenizer does."""


def token_trie(tokenizer, alphabet: set[str]) -> dict:
    """Trie {char: node} of the vocabulary's token strings; a node's ids are under key None.

    Only tokens whose text uses `alphabet` characters are kept (no other token can ever fit). Cached per
    tokenizer object (weakly: never by `id()`, which a new tokenizer can reuse once the old one is gone),
    alphabet and vocabulary size (tokens added later give a new trie).
    """
    key = (frozenset(alphabet), len(tokenizer))
    try:
        cached = _TRIES.setdefault(tokenizer, {})
    except TypeError:  # a tokenizer that cannot be weakly referenced or hashed: build every time
        cached = {}
    if key in cached:
        return cached[key]
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
    cached[key] = root
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

    def closing(self, n_new: int) -> bool:
        """Whether `n_new` generated tokens leave only the budget that closing the answer needs."""
        return self.max_new_tokens - n_new <= self.grammar.max_chars_to_close

    def state_after(self, new_ids):
        """Grammar state after the generated ids `new_ids` of one row (their decoded text, see `state_of`)."""
        return self.state_of(self.tokenizer.decode(new_ids, skip_special_tokens=False,
                                                   clean_up_tokenization_spaces=False))

    def row_mask(self, new_ids, vocab: int, closing: bool) -> torch.Tensor:
        """(vocab,) additive mask (0 allowed, -inf refused) after the generated ids `new_ids` of one row."""
        state = self.state_after(new_ids)
        key = (state, closing, vocab)
        if key not in self._masks:
            # state None cannot happen under this processor; finish the sequence instead
            ids = self.allowed(state, closing) if state is not None else []
            ids = torch.tensor(ids or self.stop_ids, dtype=torch.long)
            m = torch.full((vocab,), float("-inf"))
            m[ids[ids < vocab]] = 0
            self._masks[key] = m
        return self._masks[key]

    def __call__(self, input_ids: torch.LongTensor, scores: torch.FloatTensor) -> torch.FloatTensor:
        new = input_ids[:, self.prompt_len:]
        closing = self.closing(new.shape[1])
        mask = torch.stack([self.row_mask(row, scores.shape[1], closing) for row in new])
        return scores + mask.to(scores.device, scores.dtype)


class Sampler:
    """Chooses each next token (Gumbel-max at `temperature`, argmax at 0), inside `grammar` if given, and
    records per sequence whether the grammar or the token budget changed the pick (module docstring).

    A `transformers` LogitsProcessor that returns a one-hot distribution: run `generate` with
    do_sample=True, temperature=1.0, top_k=0, top_p=1.0 and one seed per returned sequence.
    """

    def __init__(self, temperature: float, seeds: list[int], stop_ids: list[int],
                 grammar: GrammarLogitsProcessor | None = None, on_repeat: str = "next"):
        """`on_repeat` says what an id naming an object again does (module docstring): "stop" ends the sequence,
        "substitute" records the model's ranked unused ids there, "skip" and "next" leave it to the grammar (one
        that allows repeats: the pick stands; the distinct one: the next-best unused id is forced)."""
        self.temperature, self.seeds, self.stop_ids = float(temperature), list(seeds), set(stop_ids)
        self.grammar, self.on_repeat = grammar, on_repeat
        self.first_stop = next(iter(stop_ids), None)
        self.grammar_changed = [False] * len(seeds)
        self.forced_close = [False] * len(seeds)
        self.repeat_stop = [False] * len(seeds)
        self.alternatives: list[list[list[str]]] = [[] for _ in seeds]
        """Per sequence, one list per item that named an object again (on_repeat "substitute"): the ids of that
        item's type not yet placed, best first by the model's score at that step (Gumbel-perturbed when sampling,
        so the first is the sampler's own next pick)."""
        self.done = [False] * len(seeds)
        self._generators: list[torch.Generator] | None = None

    def noise(self, scores: torch.Tensor) -> torch.Tensor:
        """Gumbel noise, one row per sequence from that sequence's own generator (the same stream every run)."""
        if self._generators is None:
            self._generators = [torch.Generator(device=scores.device).manual_seed(s) for s in self.seeds]
        u = torch.stack([torch.rand(scores.shape[1], generator=g, device=scores.device, dtype=torch.float64)
                         for g in self._generators])
        return -torch.log(-torch.log(u.clamp_min(1e-300)))

    def __call__(self, input_ids: torch.LongTensor, scores: torch.FloatTensor) -> torch.FloatTensor:
        if scores.shape[0] != len(self.seeds):
            raise DegustaError(f"sampler: {scores.shape[0]} sequences but {len(self.seeds)} seeds")
        keys = scores.double()
        if self.temperature > 0:
            keys = keys / self.temperature + self.noise(scores)
        pick = keys.argmax(-1)
        if self.grammar is not None:
            new = input_ids[:, self.grammar.prompt_len:]
            closing = self.grammar.closing(new.shape[1])
            vocab = scores.shape[1]
            for row in range(scores.shape[0]):
                if self.done[row]:
                    continue
                mask = self.grammar.row_mask(new[row], vocab, closing).to(keys.device, keys.dtype)
                chosen = (keys[row] + mask).argmax()
                if chosen != pick[row]:
                    self.grammar_changed[row] = True
                    if self.on_repeat == "stop" and self.first_stop is not None and self._repeats(new[row], int(pick[row])):
                        self.repeat_stop[row] = True
                        pick[row] = self.first_stop
                        continue
                if self.on_repeat == "substitute" and self._repeats(new[row], int(chosen)):
                    self.alternatives[row].append(self._unused_ids(new[row], keys[row] + mask))
                if closing and not self.forced_close[row]:
                    open_mask = self.grammar.row_mask(new[row], vocab, False).to(keys.device, keys.dtype)
                    self.forced_close[row] = bool((keys[row] + open_mask).argmax() != chosen)
                pick[row] = chosen
        for row, token in enumerate(pick.tolist()):
            self.done[row] = self.done[row] or token in self.stop_ids
        out = torch.full_like(scores, float("-inf"))
        out[torch.arange(scores.shape[0], device=scores.device), pick] = 0
        return out

    def _repeats(self, new_ids, token: int) -> bool:
        """Whether `token` after the generated ids `new_ids` names an object the answer already placed."""
        g = self.grammar
        piece = g.tokenizer.decode([token], skip_special_tokens=False, clean_up_tokenization_spaces=False)
        return g.grammar.repeats(g.state_after(new_ids), piece)

    def _unused_ids(self, new_ids, keys: torch.Tensor) -> list[str]:
        """The ids of the current item's type not placed yet that an allowed token writes out here (the slot's
        digits so far and the token's), by `keys` (masked), best first. With a tokenizer that has a token per id
        (the tiny base's) that is every unused id; one that writes numbers digit by digit ranks only the ids
        its next digit completes."""
        g = self.grammar
        state = g.state_after(new_ids)
        allowed = torch.nonzero(torch.isfinite(keys)).flatten()
        out: list[str] = []
        for token in allowed[keys[allowed].argsort(descending=True)].tolist():
            piece = g.tokenizer.decode([token], skip_special_tokens=False, clean_up_tokenization_spaces=False)
            slot = g.grammar.id_number(state, piece)
            if slot is None:
                continue
            number, type_, used, _ = slot
            if number in g.grammar.ids.get(type_, ()) and number not in used and number not in out:
                out.append(number)
        return out
