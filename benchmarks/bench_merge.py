"""Predicting with a LoRA adapter folded into the base weights (`load_vlm(merge_adapter=True)`, what the `hf`
backend does) vs the adapter kept beside every adapted layer (peft's default): speed and answers.

Both models answer the same test episodes' prompts (the paper's `mogma` prompt, constrained decoding, as
`configs/predict_hf_base_finetuned.yaml` runs them), alternating episode by episode so that the machine's load
falls on both alike; the ratio of their total times is the result. Greedy answers must be the same text
(merging changes only float rounding); with sampling the same seeds give the same samples unless rounding
flips a near-tie.

Usage:
    python benchmarks/bench_merge.py --adapter RUN/adapter [--base tiny_vlm_base] [--episodes 12]
        [--n 5 --temperature 1.0]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ["HF_HUB_OFFLINE"] = "1"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="tiny_vlm_base")
    ap.add_argument("--adapter", required=True, help="a fine-tune's adapter folder (RUN/adapter)")
    ap.add_argument("--dataset", default="data/naturalistic")
    ap.add_argument("--episodes", type=int, default=12)
    ap.add_argument("--n", type=int, default=1)
    ap.add_argument("--temperature", type=float, default=0.0)
    args = ap.parse_args()

    import copy

    from degusta_learn.prompting.backends.hf import HFBackend
    from degusta_learn.render.grid import Grid
    from degusta_learn.render.lifting import Renderer
    from degusta_learn.scene import load_dataset, make_episodes
    from degusta_learn.task.prompt import build_prompt
    from degusta_learn.vlm.load import load_vlm

    ds = load_dataset(args.dataset)
    episodes = make_episodes(ds, 4, "test", 0)[: args.episodes]
    backend = HFBackend(args.base, adapter=args.adapter, constrained=True, device="cpu", grid=Grid(),
                        catalog=ds.catalog)  # merged, as predict runs it
    kept = copy.copy(backend)  # the same prompt options and grammar; the adapter beside its layers
    kept.vlm, _ = load_vlm(args.base, adapter=args.adapter, device="cpu")
    renderer = Renderer.for_dataset(ds, size=backend.record.render_size if backend.record else 256)
    warm = build_prompt("mogma", ds, episodes[0], renderer, Grid(), "png")
    for b in (backend, kept):  # the grammar, the chat format and the first-call allocations, out of the timing
        b.complete(warm, 1, 0.0, 160, seed=0)
    seconds = {"merged": 0.0, "kept": 0.0}
    same = 0
    for i, ep in enumerate(episodes):
        prompt = build_prompt("mogma", ds, ep, renderer, Grid(), "png")
        texts = {}
        for name, b in (("merged", backend), ("kept", kept))[:: 1 if i % 2 == 0 else -1]:
            t0 = time.perf_counter()
            out = b.complete(prompt, args.n, args.temperature, 160, seed=i)
            seconds[name] += time.perf_counter() - t0
            texts[name] = [c.text for c in out]
        same += texts["merged"] == texts["kept"]
    ratio = seconds["kept"] / seconds["merged"]
    print(f"{len(episodes)} episodes, n={args.n}, temperature {args.temperature}: adapter kept {seconds['kept']:.1f} s, "
          f"merged {seconds['merged']:.1f} s, speed-up {ratio:.2f}x; identical answers in {same}/{len(episodes)} "
          f"episodes")


if __name__ == "__main__":
    main()
