"""Input tokens a request takes under each prompt style (`prompt_style: clarified | paper`), per method.

For each of the four methods and each context length, the mean over the first `--episodes` episodes of the split of:
  1. the dry run's own estimator (`ZeroShotRun.input_tokens`, what `degusta predict --dry-run` prints) for the
     GPT-4o configs (configs/zeroshot_<method>_gpt4o.yaml: 768 px images, GPT-4o's tile rule);
  2. the same estimator for the shipped tiny base (configs/predict_hf_base_zeroshot.yaml, `--set method=<m>`:
     its image tokens read from its processor, text at ~3 characters a token);
  3. the tiny base's real count, offline: its processor and chat template on the prompt as the hf backend sends it
     (cut down by the base's `degusta_base.json` prompt options: the five object sheets as one canvas); with the text
     tokens alone beside it (the part the styles differ in).
Nothing is generated and no weights are loaded.

Usage (the dataset first):
    degusta data generate naturalistic --out data/naturalistic
    python benchmarks/bench_prompt_styles.py [--dataset data/naturalistic] [--split test] [--contexts 0 4] [--episodes 20]
"""

from __future__ import annotations

import argparse
import os
import statistics
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

METHODS = ("louma", "logma", "mouma", "mogma")
STYLES = ("clarified", "paper")


def zeroshot_run(config: str, overrides: list[str]):
    """A `ZeroShotRun` of a shipped predict config (nothing is built or loaded) and its dataset."""
    from degusta_learn.methods import build_config, get_method
    from degusta_learn.prompting.runner import ZeroShotRun
    from degusta_learn.scene import load_dataset

    _, cfg = build_config(config, overrides, "method", get_method)
    ds = load_dataset(cfg.dataset)
    return ZeroShotRun(cfg, ds), ds


class TinyBaseCounter:
    """The shipped tiny base's real prompt tokens: its processor, chat template and prompt options, offline."""

    def __init__(self, image_size: int):
        from transformers import AutoConfig

        from degusta_learn.vlm.hub import resolve_model
        from degusta_learn.vlm.inputs import ChatFormat, set_image_budget
        from degusta_learn.vlm.load import load_processor
        from degusta_learn.vlm.record import locate_record, read_record

        folder = str(resolve_model("tiny_vlm_base", "model.name", weights=False))
        self.processor = load_processor(folder, "model.name")
        set_image_budget(self.processor, AutoConfig.from_pretrained(folder, local_files_only=True), image_size)
        self.fmt = ChatFormat(self.processor)
        self.options = read_record(locate_record(folder)).prompt

    def count(self, prompt) -> tuple[int, int]:
        """(input ids of the request, tokens of its text parts alone) for `prompt` as the hf backend sends it."""
        from degusta_learn.vlm.inputs import encode_prompt
        from degusta_learn.vlm.prompt_options import adapt_prompt

        sent = adapt_prompt(prompt, self.options)
        ids = encode_prompt(self.processor, self.fmt, sent)["input_ids"]
        text = sum(len(self.processor.tokenizer(p, add_special_tokens=False)["input_ids"])
                   for p in sent.parts if isinstance(p, str))
        return int(ids.shape[1]), text


def mean_tokens(run, episodes, counter: TinyBaseCounter | None = None) -> dict[str, dict[str, float]]:
    """{style: {"estimate": mean, ("real", "text": means with `counter`)}} over `episodes`."""
    out = {}
    for style in STYLES:
        prompts = [run.prompt(ep, style)[0] for ep in episodes]
        row = {"estimate": statistics.mean(run.input_tokens(p) for p in prompts)}
        if counter is not None:
            real = [counter.count(p) for p in prompts]
            row["real"] = statistics.mean(r for r, _ in real)
            row["text"] = statistics.mean(t for _, t in real)
        out[style] = row
    return out


def pair(rows: dict, key: str) -> str:
    c, p = rows["clarified"][key], rows["paper"][key]
    return f"{c:,.0f} / {p:,.0f} ({p - c:+,.0f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", default="data/naturalistic")
    ap.add_argument("--split", default="test")
    ap.add_argument("--contexts", type=int, nargs="+", default=[0, 4])
    ap.add_argument("--episodes", type=int, default=20, help="episodes averaged per method and context length")
    ap.add_argument("--no-tokenizer", action="store_true", help="skip the tiny base's real token counts")
    args = ap.parse_args()
    if not Path(args.dataset).is_dir():
        raise SystemExit(f"no dataset at {args.dataset}: degusta data generate naturalistic --out {args.dataset}")
    from degusta_learn.scene import make_episodes

    common = [f"dataset={args.dataset}", f"split={args.split}"]
    counter = None if args.no_tokenizer else TinyBaseCounter(image_size=256)
    print(f"Mean input tokens a request, clarified / paper (paper - clarified); {args.split} split, first "
          f"{args.episodes} episodes per row\n")
    print("| method | k | dry-run estimate, GPT-4o @ 768 px | dry-run estimate, tiny base @ 256 px | "
          "tiny base, real tokenizer | of which text |")
    print("|---|---:|---:|---:|---:|---:|")
    for method in METHODS:
        for k in args.contexts:
            over = [*common, f"context={k}"]
            gpt, ds = zeroshot_run(f"configs/zeroshot_{method}_gpt4o.yaml", over)
            tiny, _ = zeroshot_run("configs/predict_hf_base_zeroshot.yaml", [*over, f"method={method}"])
            episodes = make_episodes(ds, k, args.split, gpt.cfg.seed)[:args.episodes]
            g = mean_tokens(gpt, episodes)
            t = mean_tokens(tiny, episodes, counter)
            real = (pair(t, "real"), pair(t, "text")) if counter else ("-", "-")
            print(f"| {method} | {k} | {pair(g, 'estimate')} | {pair(t, 'estimate')} | {real[0]} | {real[1]} |")


if __name__ == "__main__":
    main()
