"""The task's fixed names, defined once for every layer (dependency-free, so the CLI can use them cheaply).

- `CONTEXT_LENGTHS`: how many past arrangements an episode shows (the paper's 0, 2 and 4).
- `SPLITS`: participant splits an episode set is drawn from.
- `PROMPT_METHODS`: DegustaBot's four visual-prompting methods (objects: labelled or marked; arrangement:
  unmarked or grid-marked).
- `MODEL_PROMPTED_METHODS`: every method that asks a model through the zero-shot runner (its backends, response
  cache, ledger and budget): the four and `text_llm` (the context tables as text, TidyBot-style).
"""

CONTEXT_LENGTHS = (0, 2, 4)
SPLITS = ("train", "val", "test", "all")
PROMPT_METHODS = ("louma", "logma", "mouma", "mogma")
MODEL_PROMPTED_METHODS = (*PROMPT_METHODS, "text_llm")
