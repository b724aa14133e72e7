"""Zero-shot visual prompting (the DegustaBot methods louma, logma, mouma, mogma) against a VLM.

runner.py is the predict method (cache, concurrency, retries, cost ledger), backends/ talks to the VLMs (OpenAI-
compatible servers, Anthropic, Gemini, a local `hf` model, replay), cache.py, costs.py and estimate.py keep what was
asked and what it cost. The task contract the methods share with fine-tuning (prompts, the answer format and its
parser, the grammar, aggregation) is `degusta_learn.task`. See docs/prompting.md.
"""
