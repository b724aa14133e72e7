"""Zero-shot visual prompting (the DegustaBot methods louma, logma, mouma, mogma).

prompt.py builds the prompts, answers.py parses answers (never executing them), aggregate.py combines n
sampled answers into one placement list, backends/ talks to the VLMs, runner.py is the predict method
(cache, concurrency, retries, cost ledger). See docs/prompting.md.
"""

from degusta_learn.prompting.answers import (
    Answer, AnswerItem, AnswerParseError, answer_items, answer_kind, format_answer, parse_answer, read_answer,
)
from degusta_learn.prompting.prompt import ImagePart, Prompt, build_prompt

__all__ = ["Answer", "AnswerItem", "AnswerParseError", "ImagePart", "Prompt", "answer_items", "answer_kind",
           "build_prompt", "format_answer", "parse_answer", "read_answer"]
