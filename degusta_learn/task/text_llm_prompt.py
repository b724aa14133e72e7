"""The two text-only prompts of `text_llm`, the TidyBot-style method (Wu et al. 2023, "TidyBot: Personalized Robot
Assistance with Large Language Models"): summarise the person's preference from examples, then act on the summary.

1. `summary_prompt`: the catalog as "objects as language" JSON text (`render.lifting.oal_text`), then each context
   table written as text -- the table it was set on (`table_text`: id, name, picture size, surface extent), its
   placement-order line (`render.lifting.order_text`) and its objects in the unmarked answer format
   (`task.prompt.context_answer`, the text `modality: text` writes for louma / mouma: type, id, [x, y], degrees;
   each id's colours and materials are in the catalog JSON) -- and `SUMMARY_TASK`: write the preference summary.
2. `placement_prompt`: the catalog JSON again, the summary (`SUMMARY_LINE`; at context 0, `NO_CONTEXT_LINE`
   instead: there is nothing to summarise), and `placement_task`: set the target table (`table_text`) in the
   answer format of the unmarked methods, read by `task.answers.read_answer` (kind "unmarked").

No image anywhere: a `Prompt` of text parts only. Both prompts are `Prompt(method="louma")`, the method whose
answer format (objects as language, positions and rotations) they ask for. The summary prompt's `episode` is
the episode id + `SUMMARY_SUFFIX`, so the replay backend finds a recorded summary as its own row
(`{"episode": "p001/t2/k4#summary", "sample": 0, "text": "..."}`).

Example:
    prompt = summary_prompt(ds, episode)          # None at context 0
    print(prompt.text)
    print(placement_prompt(ds, episode, "I put the plate in the middle ...").text)
"""

from __future__ import annotations

from degusta_learn.render.lifting import oal_text, order_text
from degusta_learn.scene import Dataset, Episode, Table
from degusta_learn.task.prompt import Prompt, context_answer

ANSWER_METHOD = "louma"
"""The prompting method whose answer format `placement_prompt` asks for (unmarked: [x, y] and degrees)."""
SUMMARY_SUFFIX = "#summary"
"""Appended to the episode id of a summary prompt (what the replay backend looks a recorded summary up by)."""
OBJECTS_LINE = ("These are the objects I have, as JSON; each object's object_reference_id is its \"id\" and its "
                "object_type is its \"class\":\n")
CONVENTIONS = (
    "Below are tables I set, written as text. Each lists the objects I placed, in the order I placed them, as a "
    "python list: each object's type, its id (its colours and materials are in the JSON above), its position [x, y] "
    "and its rotation. x and y are between 0 and 1: x from the left edge and y from the top edge of the table's "
    "picture. Rotation is the number of degrees clockwise from north, the top of the picture.")
SUMMARY_TASK = (
    "Summarize my preferences for setting a table from these examples, in a few short sentences that would let "
    "someone set any other table the way I like it: which objects I choose (their types, colours and materials) "
    "and how many, where I put each type on the table and relative to the others, how I rotate them, and in what "
    "order I place them. Write only the summary.")
SUMMARY_LINE = "This is a summary of my preferences for setting a table:\n"
NO_CONTEXT_LINE = "You have not seen any of my previous table settings."


def table_text(table: Table) -> str:
    """A table as text: its id and name, its picture's size and the extent of its surface in [0, 1] coordinates."""
    x0, y0, x1, y1 = table.bounds
    name = f" ({table.name})" if table.name else ""
    shape = "rectangular" if len(table.surface) == 4 else "round or many-sided"
    return (f"table {table.id}{name}, a picture {table.width} x {table.height} pixels whose {shape} surface lies "
            f"within x {x0:.2f} to {x1:.2f} and y {y0:.2f} to {y1:.2f}")


def context_text(ds: Dataset, episode: Episode) -> list[str]:
    """One text part per context table of the episode: a heading naming its table, its placement order and its
    objects (lines of one part)."""
    parts = []
    for k, trial in enumerate(episode.context, start=1):
        arr = ds.arrangement(episode.participant, trial)
        parts.append("\n".join([f"Table setting {k}, on {table_text(ds.tables[arr.table])}:",
                                order_text(arr, ds.catalog, f"table setting {k}"),
                                context_answer(ANSWER_METHOD, arr, ds.catalog, None)]))
    return parts


def summary_prompt(ds: Dataset, episode: Episode) -> Prompt | None:
    """Step 1: the catalog and the context tables as text, and the request for a summary (None at context 0)."""
    if not episode.context:
        return None
    parts = [OBJECTS_LINE + oal_text(ds.catalog), CONVENTIONS, *context_text(ds, episode), SUMMARY_TASK]
    return Prompt(method=ANSWER_METHOD, parts=parts, episode=episode.id + SUMMARY_SUFFIX, modality="text")


def placement_task(target: Table, types: list[str], has_summary: bool) -> str:
    """Step 2's task paragraph: set `target` in the unmarked answer format (the clarified louma task's sentences)."""
    how = "according to my preferences" if has_summary else "the way I would like it"
    return (f"You are helping me set {table_text(target)}, {how}. What objects should I place on it, where should I "
            "place them, and how should they be oriented? Give a position in [x,y] where each value is a number "
            "between 0 and 1 (x from the left edge, y from the top edge of the table's picture). Give rotation as "
            "the number of degrees clockwise from north, the top of the picture. Give your answer as a python list "
            "formatted as follows: "
            "[{'type': object_type, 'id': object_reference_id, 'position': [x, y], 'rotation': degrees}]. "
            f"object_type is one of {', '.join(types)}. Give object_id as an integer. List the objects in the order "
            "I should place them. Include only this list in your response.")


def placement_prompt(ds: Dataset, episode: Episode, summary: str | None) -> Prompt:
    """Step 2: the catalog, the summary of step 1 (None: context 0, nothing was summarised) and the target table."""
    target = ds.tables[ds.arrangement(episode.participant, episode.target).table]
    preference = NO_CONTEXT_LINE if summary is None else SUMMARY_LINE + summary
    parts = [OBJECTS_LINE + oal_text(ds.catalog), preference,
             placement_task(target, list(ds.catalog.types), summary is not None)]
    return Prompt(method=ANSWER_METHOD, parts=parts, episode=episode.id, modality="text")
