"""Constrained decoding: our automaton + trie (`vlm/constrain.py`) vs xgrammar on the same grammar.

Vocabulary: the real SmolVLM-256M-Instruct tokenizer (byte-level BPE, 49,152 tokens + 128 added = 49,280
logits), read from /work/shared/reference-models (offline). Catalog: `scene.default_catalog()` (125 objects,
5 types), grid 8 x 8, stop token `<end_of_utterance>`.

Engines, each doing what a `transformers` LogitsProcessor does at one decoding step (mask the logits):
  ours      `GrammarLogitsProcessor(AnswerGrammar(kind, catalog, grid), ...)(input_ids, scores)`: decode
            the generated ids, advance the automaton, walk the vocabulary trie (masks cached per state).
  xgr-ebnf  xgrammar 0.2.x on an EBNF of *the same text grammar* (`ebnf_of` below, generated from the
            `AnswerGrammar`: same literals, types, ids per type, cells, directions, coordinate and rotation
            forms, the same max_items / max_cells bounds): `matcher.accept_token(previous)`,
            `fill_next_token_bitmask`, `apply_token_bitmask_inplace`.
  xgr-json  xgrammar on `prompting.answers.answer_schema` (the JSON-schema form of the answer that
            `backend.structured_output` sends to vLLM/SGLang/OpenAI), compact separators; its output is JSON
            `{"objects": [...]}`, which `read_answer` reads into the same items.

(c) Per-token overhead: random walks are sampled from OUR mask (uniform over allowed tokens, so the
    token sequences are valid for both), then both `ours` and `xgr-ebnf` replay exactly those sequences,
    interleaved walk by walk (the machine is shared: compare the ratio within one run). Each walk starts
    fresh (a new processor / a new matcher, as one `generate` call would); setup (vocabulary trie, grammar
    compile) is timed separately. xgr-json is timed on its own walks (its text differs).
(d)+(e) Exactness and the two semantic rules: each engine samples N walks from its own mask (uniform
    over allowed tokens: the worst a model can do inside the grammar) until the stop token or the budget
    of `--max-new-tokens`; the text is read by `read_answer`. Counted: outputs that do not parse or are
    cut by the budget, items dropped for "id N is a X, not a Y" (id-of-type), items dropped for "id
    already placed" (no repeated id), and objects whose cells repeat a cell (our grammar also forbids).

Needs xgrammar (not a dependency of the project): `pip install --no-deps xgrammar apache-tvm-ffi` (its
declared torch/triton requirements would otherwise reinstall torch; the CPU path needs neither triton nor CUDA).

Usage:
    python benchmarks/bench_constrained.py                       # ~2 min on 1 shared CPU core
    python benchmarks/bench_constrained.py --time-walks 10 --exact-walks 50
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import statistics
import time

os.environ["HF_HUB_OFFLINE"] = "1"

TOKENIZER = "/work/shared/reference-models/SmolVLM-256M-Instruct"


def ebnf_of(g) -> str:
    """The `AnswerGrammar` `g` as an xgrammar EBNF (everything but the no-repeat rules, which no CFG of
    reasonable size can state: ids placed once per answer, cells once per object)."""
    q = json.dumps
    rules = []
    item_names = []
    for i, t in enumerate(g.types):
        if not g.ids[t]:
            continue
        body = []
        for kind, value in g.parts:
            if kind == "lit":
                body.append(q(value))
            elif value == "type":
                body.append(q(t))
            elif value == "id":
                body.append("(" + " | ".join(q(x) for x in g.ids[t]) + ")")
            elif value == "cell":  # the cells loop (the opening quote is in the literal before)
                n = min(g.max_cells, len(g.cells))
                body.append(f'cell "\'" (", \'" cell "\'"){{0,{n - 1}}}')
            else:
                body.append(value)
        item_names.append(f"item{i}")
        rules.append(f"item{i} ::= " + " ".join(body))
    rules.insert(0, f'root ::= [ \\n]{{0,2}} "[" item (", " item){{0,{g.max_items - 1}}} "]"')
    rules.insert(1, "item ::= " + " | ".join(item_names))
    if g.kind == "grid":
        rules.append("cell ::= " + " | ".join(q(c) for c in g.cells))
        rules.append("dir ::= " + " | ".join(q(d) for d in g.directions))
    else:
        rules.append('coord ::= "0" | "1" | "0." [0-9]{1,3} | "1." ("0"){1,3}')
        rules.append('rot ::= "0" | [1-9] [0-9]? | [12] [0-9] [0-9] | "3" [0-5] [0-9]')
    return "\n".join(rules)


class Ours:
    name = "ours"
    mask_times = None  # one call computes the mask and applies it

    def __init__(self, grammar, tok, stop_ids, max_new_tokens):
        from degusta_learn.vlm.constrain import GrammarLogitsProcessor

        self.make = lambda: GrammarLogitsProcessor(grammar, tok, 1, stop_ids, max_new_tokens)
        t = time.perf_counter()
        self.make()  # builds (and caches) the vocabulary trie
        self.setup_s = time.perf_counter() - t

    def start(self):
        import torch

        self.proc, self.ids = self.make(), torch.zeros((1, 1), dtype=torch.long)  # a 1-token "prompt"

    def step(self, prev, scores):
        import torch

        if prev is not None:
            self.ids = torch.cat([self.ids, torch.tensor([[prev]])], dim=1)
        return self.proc(self.ids, scores)


class Xgr:
    def __init__(self, name, compiled, setup_s, vocab, backend):
        import xgrammar as xgr

        self.name, self.compiled, self.setup_s, self.backend = name, compiled, setup_s, backend
        self.mask_times: list[float] = []
        self.xgr, self.bitmask = xgr, xgr.allocate_token_bitmask(1, vocab)

    def start(self):
        self.matcher = self.xgr.GrammarMatcher(self.compiled)

    def step(self, prev, scores):
        t = time.perf_counter()
        if prev is not None and not self.matcher.accept_token(prev):
            raise AssertionError(f"{self.name} rejected token {prev}")
        self.matcher.fill_next_token_bitmask(self.bitmask)
        self.mask_times.append(time.perf_counter() - t)
        self.xgr.apply_token_bitmask_inplace(scores, self.bitmask, backend=self.backend)
        return scores


def walk(engine, vocab, stop_ids, budget, rng, replay=None):
    """One decoding path: (tokens incl. the stop token if reached, seconds per step).

    Samples uniformly among allowed tokens, or replays `replay` (then the engine must allow it)."""
    import torch

    engine.start()
    tokens, times, prev = [], [], None
    for k in range(budget):
        scores = torch.zeros((1, vocab))
        t = time.perf_counter()
        out = engine.step(prev, scores)
        times.append(time.perf_counter() - t)
        if replay is not None:
            prev = replay[k]
            if not bool(torch.isfinite(out[0, prev])):
                raise AssertionError(f"{engine.name} masks token {prev} of a replayed path")
        else:
            allowed = torch.isfinite(out[0]).nonzero().flatten().tolist()
            prev = rng.choice(allowed)
        tokens.append(prev)
        if prev in stop_ids:
            break
    return tokens, times


_POSITION = re.compile(r"""['"]position['"]\s*:\s*\[([^\]]*)\]""")
_CELL = re.compile(r"""['"]([A-Z]\d+)['"]""")  # (the parser merges a repeated cell silently: count it in the text)


def judge(tokens, tok, stop_ids, kind, catalog, grid) -> dict:
    """What `read_answer` makes of one walk's text (counts)."""
    from degusta_learn.task.answers import AnswerParseError, read_answer
    stopped = bool(tokens) and tokens[-1] in stop_ids
    text = tok.decode(tokens[:-1] if stopped else tokens, skip_special_tokens=True)
    out = dict.fromkeys(("parsed", "unclosed", "empty", "type", "repeat", "cells", "other", "items"), 0)
    try:
        ans = read_answer(text, kind, catalog, grid)
    except AnswerParseError:
        out["unclosed" if not stopped else "other"] = 1
        return out
    errs = ans.item_errors
    out.update(parsed=1, empty=int(not ans.items and not errs), type=sum(", not a " in e for e in errs),
               repeat=sum("already placed" in e for e in errs), items=len(ans.items) + len(errs),
               cells=sum(len(set(c)) < len(c) for c in map(_CELL.findall, _POSITION.findall(text))))
    out["other"] = len(errs) - out["type"] - out["repeat"]
    return out


def us(times):
    if not times:
        return float("nan"), float("nan")
    xs = sorted(times)
    return 1e6 * statistics.fmean(xs), 1e6 * xs[min(len(xs) - 1, int(0.95 * len(xs)))]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kinds", nargs="+", default=["grid", "unmarked"])
    ap.add_argument("--time-walks", type=int, default=20, help="walks replayed by both engines per kind")
    ap.add_argument("--exact-walks", type=int, default=100, help="walks sampled by each engine per kind")
    ap.add_argument("--max-new-tokens", type=int, default=256)
    ap.add_argument("--apply-backend", default="auto",
                    help="xgrammar apply_token_bitmask_inplace backend (auto = its CPU kernel here)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import torch
    import xgrammar as xgr
    from transformers import AutoTokenizer

    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import default_catalog
    from degusta_learn.task.answer_format import answer_schema
    from degusta_learn.task.grammar import AnswerGrammar

    torch.set_num_threads(args.threads)
    tok = AutoTokenizer.from_pretrained(TOKENIZER)
    vocab = len(tok)
    stop_ids = [tok.convert_tokens_to_ids("<end_of_utterance>")]
    catalog, grid = default_catalog(), Grid(8, 8)
    t = time.perf_counter()
    info = xgr.TokenizerInfo.from_huggingface(tok, vocab_size=vocab, stop_token_ids=stop_ids)
    compiler = xgr.GrammarCompiler(info, max_threads=args.threads)
    info_s = time.perf_counter() - t
    print(f"tokenizer {TOKENIZER.rsplit('/', 1)[-1]}: {vocab} logits; xgrammar TokenizerInfo {info_s:.2f} s; "
          f"torch {torch.__version__}, {args.threads} thread(s), apply backend {args.apply_backend}")
    for kind in args.kinds:
        g = AnswerGrammar(kind, catalog, grid)
        ours = Ours(g, tok, stop_ids, args.max_new_tokens)
        t = time.perf_counter()
        ebnf = Xgr("xgr-ebnf", compiler.compile_grammar(xgr.Grammar.from_ebnf(ebnf_of(g))),
                   time.perf_counter() - t, vocab, args.apply_backend)
        t = time.perf_counter()
        js = Xgr("xgr-json", compiler.compile_json_schema(json.dumps(answer_schema(kind, catalog, grid)),
                                                          any_whitespace=False, separators=(",", ":")),
                 time.perf_counter() - t, vocab, args.apply_backend)
        engines = (ours, ebnf, js)
        rng = random.Random(args.seed)
        # (c) the same token sequences through ours and xgr-ebnf, interleaved
        total = {e.name: [] for e in engines}
        n_tok = 0
        for w in range(args.time_walks):
            path, _ = walk(ours, vocab, stop_ids, args.max_new_tokens, rng)
            n_tok += len(path)
            for eng in ((ours, ebnf) if w % 2 else (ebnf, ours)):
                total[eng.name] += walk(eng, vocab, stop_ids, len(path), rng, replay=path)[1]
        mask = {ebnf.name: list(ebnf.mask_times)}
        # (d), (e) each engine's own random walks
        js.mask_times.clear()
        stats = {}
        for eng in engines:
            acc: dict = {}
            for _ in range(args.exact_walks):
                tokens, times = walk(eng, vocab, stop_ids, args.max_new_tokens, rng)
                if eng is js:
                    total[js.name] += times
                for k, v in judge(tokens, tok, stop_ids, kind, catalog, grid).items():
                    acc[k] = acc.get(k, 0) + v
            stats[eng.name] = acc
        mask[js.name] = list(js.mask_times)
        mask[ours.name] = total[ours.name]
        m_ours = us(total[ours.name])[0]
        print(f"\n[{kind}] timing: {args.time_walks} paths sampled from ours, replayed by ours and xgr-ebnf, "
              f"{n_tok} tokens ({n_tok / args.time_walks:.0f}/path; xgr-json on its own walks); exactness: "
              f"{args.exact_walks} own walks per engine, budget {args.max_new_tokens} tokens")
        print("| engine | setup s | mask us/token mean / p95 | mask+apply us/token mean / p95 | vs ours | "
              "parsed | unclosed at budget | empty | id-of-type violations | repeated ids | "
              "objects w/ repeated cells | other item errors | items |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for eng in engines:
            mm, mp = us(mask[eng.name])
            tm, tp = us(total[eng.name])
            st = stats[eng.name]
            print(f"| {eng.name} | {eng.setup_s:.2f} | {mm:.0f} / {mp:.0f} | {tm:.0f} / {tp:.0f} | "
                  f"{tm / m_ours:.2f}x | {st['parsed']}/{args.exact_walks} | {st['unclosed']} | {st['empty']} | "
                  f"{st['type']} | {st['repeat']} | {st['cells']} | {st['other']} | {st['items']} |")


if __name__ == "__main__":
    main()
