"""Replay recorded answers from a file: reproduce a published zero-shot run without calling any API.

`backend.path` is either
- a JSONL file with one sampled answer a line: `{"episode": "p001/t2/k4", "sample": 0, "text": "[...]"}`
  (`"sample": "greedy"`: the greedy answer `aggregation: greedy_votes_pooled` asks for), or
- a predictions.jsonl written by a zero-shot run (its `diagnostics.responses` hold the raw answers,
  `diagnostics.greedy_response` the greedy one; a text_llm run's `diagnostics.summary`, the preference summary its
  second step was given, is its first step's answer, found under the episode id plus `#summary`).

Answers are looked up by the prompt's episode id and sample index (at temperature 0, the greedy answer where one
is recorded); a missing answer counts as a failed sample. What it is: local (costs nothing), not cached (the file is the cache), every recorded answer
of an episode in one look-up, `structured_output` accepted and ignored (answers of either kind parse).

Example config:
    backend: {name: replay, path: runs/mogma_gpt4o/predictions.jsonl}
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from degusta_learn.errors import DegustaError
from degusta_learn.files.jsonio import read_jsonl
from degusta_learn.prompting.backends.base import Backend, BackendConfig, Completion
from degusta_learn.task.prompt import Prompt
from degusta_learn.task.text_llm_prompt import SUMMARY_SUFFIX
from degusta_learn.vlm.settings import DecodingSettings, ModelSettings


@dataclass
class ReplayConfig(BackendConfig):
    """The `backend:` keys of the replay backend."""

    name: str = "replay"
    path: str | None = None
    """The JSONL file of recorded answers (required)."""

    answer_keys = ("path",)


GREEDY = "greedy"
"""The sample name of a recorded greedy answer."""


def read_replay(path: str | Path) -> dict[str, dict[int | str, str]]:
    """{episode id: {sample index (or "greedy"): answer text}} from either file format above."""
    out: dict[str, dict[int | str, str]] = {}
    for lineno, row in read_jsonl(path):
        where = f"{path}:{lineno}"
        if not isinstance(row, dict) or not isinstance(row.get("episode"), str):
            raise DegustaError(f"{where}: episode: expected an object with a string 'episode'")
        answers = out.setdefault(row["episode"], {})
        if "text" in row:
            sample = row.get("sample", len(answers))
            if sample != GREEDY and (not isinstance(sample, int) or isinstance(sample, bool) or sample < 0):
                raise DegustaError(f"{where}: sample: expected an integer >= 0 or \"greedy\", got {str(sample)[:40]!r}")
            if not isinstance(row["text"], str):
                raise DegustaError(f"{where}: text: expected a string")
            answers[sample] = row["text"]
        else:
            diagnostics = row.get("diagnostics")
            if diagnostics is not None and not isinstance(diagnostics, dict):
                raise DegustaError(f"{where}: diagnostics: expected an object, got {type(diagnostics).__name__}")
            responses = (diagnostics or {}).get("responses")
            if not isinstance(responses, list):
                raise DegustaError(f"{where}: expected 'text' (one answer) or diagnostics.responses (a list)")
            for i, text in enumerate(responses):
                if isinstance(text, str):
                    answers[i] = text
            if isinstance(diagnostics.get("greedy_response"), str):
                answers[GREEDY] = diagnostics["greedy_response"]
            if isinstance(diagnostics.get("summary"), str):  # text_llm's step 1, recorded as step 2 was given it
                out.setdefault(row["episode"] + SUMMARY_SUFFIX, {})[0] = diagnostics["summary"]
    return out


class ReplayBackend(Backend):
    """Answers from a file; `complete(prompt, n)` returns the episode's recorded samples 0..n-1 (at temperature 0
    its recorded greedy answer, if there is one)."""

    name = "replay"
    config_class = ReplayConfig
    per_sample = False  # one look-up gives every recorded sample
    cacheable = False  # nothing to save: the file is the cache
    takes_schema = True  # ignored: recorded answers of either kind parse
    key_env = None
    default_model = "replay"  # a label: the recorded answers are whichever model's

    @classmethod
    def is_local(cls, cfg: ReplayConfig) -> bool:
        return True

    def __init__(self, answers: dict[str, dict[int, str]], model: str = "replay"):
        self.answers, self.model = answers, model

    @classmethod
    def from_config(cls, cfg: ReplayConfig, model: ModelSettings, decoding: DecodingSettings | None = None,
                    grid=None, catalog=None) -> ReplayBackend:
        if not cfg.path:
            raise DegustaError("backend.path: the replay backend needs the file of recorded answers")
        return cls(read_replay(cfg.path), model=model.name)

    def complete(self, prompt: Prompt, n: int, temperature: float, max_tokens: int,
                 seed: int | None = None) -> list[Completion]:
        recorded = self.answers.get(prompt.episode or "", {})
        if temperature == 0 and GREEDY in recorded:
            return [Completion(text=recorded[GREEDY], input_tokens=0, output_tokens=0)]
        return [Completion(text=recorded[i], input_tokens=0, output_tokens=0) for i in range(n) if i in recorded]
