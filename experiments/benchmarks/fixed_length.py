"""Two-pass decoding: the list's length from sampled answers, its items from the greedy decoder (point 35).

A fine-tune's greedy answers stop early, while the median length of its sampled answers follows the person's
count (`benchmarks/reaggregate.py`). This re-decodes the episodes greedily with the answer grammar holding each
list to that episode's length (`AnswerGrammar(length=L)`: the list may not close before L distinct objects and
must close at L), so the objects added to reach the count come from the greedy decoder, conditioned on the items
before them, and then scores it as `reaggregate.py` scores its rows (against the greedy and the sampled runs,
and `population_mean`).

Usage (the sampled run first: `degusta predict ... --set n=5 --set temperature=0.5`, see reaggregate.py):
    python benchmarks/fixed_length.py --dataset data/naturalistic --episodes RUN/episodes.jsonl \\
        --adapter RUN/checkpoints/tiny_vlm_lora/adapter --greedy RUN/predictions/tiny_vlm_lora.jsonl \\
        --sampled OUT/sampled.jsonl --out OUT/fixed_length.jsonl
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ["HF_HUB_OFFLINE"] = "1"
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--episodes", required=True)
    ap.add_argument("--base", default=None, help="the base model folder (default: the shipped base)")
    ap.add_argument("--adapter", required=True, help="the fine-tune's adapter folder")
    ap.add_argument("--greedy", required=True, help="the same fine-tune's greedy predictions (n 1)")
    ap.add_argument("--sampled", required=True, help="its predictions with n > 1 sampled answers (the lengths)")
    ap.add_argument("--out", required=True, help="where the fixed-length predictions go (reused if present)")
    ap.add_argument("--repeats", choices=("forbid", "skip"), default="forbid",
                    help="forbid: the grammar refuses an object named again, so the items added to reach the length "
                         "are new objects (the model's best unused id); skip: the backend's decoding (repeats "
                         "written and dropped: a model held past its own end loops on them)")
    args = ap.parse_args()

    import reaggregate

    from degusta_learn.methods import run_predict
    from degusta_learn.prompting.backends.hf import HFBackend
    from degusta_learn.render.grid import Grid
    from degusta_learn.scene import load_dataset, read_predictions
    from degusta_learn.shipped import BASE_DIR
    from degusta_learn.vlm.grammar import AnswerGrammar

    ds = load_dataset(args.dataset)
    sampled = {p.episode: p for p in read_predictions(args.sampled, ds.catalog)}
    lengths = {}
    for episode, prediction in sampled.items():
        answers = reaggregate.parsed_answers(prediction, ds.catalog, Grid(8, 8))
        if answers:
            lengths[episode] = reaggregate.median_length(answers)

    plain = HFBackend.complete

    def complete(self, prompt, n, temperature, max_tokens, seed=None):
        """The backend's own decoding, with the grammar held to the episode's sampled length."""
        from degusta_learn.prompting.answers import answer_kind

        kind = answer_kind(prompt.method)
        length = lengths.get(prompt.episode)
        grammar = AnswerGrammar(kind, self.catalog, self.grid, length=length)
        if args.repeats == "forbid":
            grammar.allowing_repeats = lambda: grammar  # generate's skip then keeps the distinct grammar
        self._grammars[kind] = grammar
        return plain(self, prompt, n, temperature, max_tokens, seed)

    if not Path(args.out).is_file():
        HFBackend.complete = complete
        try:
            run_predict("configs/predict_hf_base_finetuned.yaml",
                        [f"dataset={args.dataset}", f"episodes={args.episodes}", f"out={args.out}",
                         f"model.name={args.base or BASE_DIR}", f"model.adapter={args.adapter}", "decoding.n=1",
                         "decoding.temperature=0"])
        finally:
            HFBackend.complete = plain
    sys.argv = [sys.argv[0], "--dataset", args.dataset, "--episodes", args.episodes, "--greedy", args.greedy,
                "--sampled", args.sampled, "--extra", f"fixed length={args.out}"]
    reaggregate.main()


if __name__ == "__main__":
    main()
