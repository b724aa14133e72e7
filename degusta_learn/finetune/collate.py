"""Batching with correct labels: only the answer and its end-of-turn token are supervised.

For each example the prompt (user turn + generation prompt, with images) goes through the model's
processor exactly as at generation time, and the completion (`ChatFormat.completion_text`: template
lead + answer + end-of-turn token) is tokenized separately and appended, so training sees the very
prompt tokens generation will see. An example's follow-up turns (`Example.followups`, several questions
about one image) are appended after it, each question's turn unsupervised and its answer supervised.
Labels are -100 on every prompt, image and padding token; labels are NOT shifted (the loss shifts once).
Nothing is ever truncated: an example longer than the budget raises a DegustaError that names
`data.max_length` and the image-token share.

Example:
    collate = Collator(processor, fmt, max_length=2048, image_token_id=model.config.image_token_id)
    batch = collate([examples[0], examples[1]])   # input_ids, attention_mask, labels, pixel_values, ...
"""

from __future__ import annotations

import torch

from degusta_learn.errors import DegustaError
from degusta_learn.vlm.inputs import ChatFormat, prompt_messages

IGNORE = -100


class Collator:
    """Examples -> a padded batch with labels (see the module docstring)."""

    def __init__(self, processor, fmt: ChatFormat, max_length: int, image_token_id: int | None,
                 key: str = "data.max_length", list_end_weight: float = 1.0):
        """`list_end_weight` != 1: batches carry `label_weights`, that weight on the answer tokens deciding the
        list's length (`list_decisions`) and 1 on the other supervised tokens."""
        self.processor, self.fmt, self.max_length = processor, fmt, max_length
        self.image_token_id, self.key = image_token_id, key
        self.list_end_weight = float(list_end_weight)
        self.pad_id = processor.tokenizer.pad_token_id
        if self.pad_id is None:
            self.pad_id = fmt.end_id

    def encode(self, examples) -> tuple[dict, list[tuple[list[int], list[int]]], list[int]]:
        """(processor output for the prompts, (completion ids, labels) per example, prompt length per example).

        The one place prompt + answer tokens are counted with the processor: batches (`__call__`) and
        `token_counts` both go through it (`text_counts` tokenizes the same texts without the processor).
        """
        tok = self.processor.tokenizer
        texts, images = [], []
        for ex in examples:
            messages, ims = prompt_messages(ex.prompt)
            texts.append(self.fmt.prompt_text(messages))
            images.append(ims)
        has_images = any(images)
        if has_images and not all(images):
            raise DegustaError("data.include: some examples of a batch have images and some none; "
                               "include at least one image group for every example")
        tok.padding_side = "right"
        enc = self.processor(text=texts, images=images if has_images else None, padding=True,
                             add_special_tokens=False, return_tensors="pt")
        completions = [self._completion(ex) for ex in examples]
        prompt_lens = enc["attention_mask"].sum(dim=1).tolist()
        return enc, completions, prompt_lens

    def _completion(self, ex) -> tuple[list[int], list[int]]:
        """(token ids, labels) of the answer, then of each follow-up turn (`Example.followups`): the
        question's turn unsupervised (IGNORE), its answer supervised."""
        tok = self.processor.tokenizer
        ids = tok(self.fmt.completion_text(ex.answer), add_special_tokens=False)["input_ids"]
        labels = list(ids)
        for question, answer in getattr(ex, "followups", ()):
            asked = tok(self.fmt.followup_text(question), add_special_tokens=False)["input_ids"]
            said = tok(self.fmt.completion_text(answer), add_special_tokens=False)["input_ids"]
            ids, labels = ids + asked + said, labels + [IGNORE] * len(asked) + said
        return ids, labels

    def token_counts(self, examples) -> list[dict]:
        """Per example: {"total", "image", "text", "answer"} tokens, exactly as a batch would hold them
        (no budget check: the caller compares "total" with `max_length`)."""
        return self._counts(*self.encode(examples))

    def text_counts(self, examples) -> list[dict]:
        """Per example, WITHOUT the image processor: {"prompt": tokens of the prompt text with each image left
        as the chat template's placeholder (not expanded), "layout": the prompt images' (width, height) in
        order, "answer": answer (and follow-up) tokens, as `token_counts` counts them}. The processor expands a
        placeholder by the image's size alone, so among examples of one layout `token_counts`' prompt length
        (image + text) is "prompt" plus a constant (`finetune.token_count.token_budget` measures it per layout)."""
        texts, layouts = [], []
        for ex in examples:
            messages, ims = prompt_messages(ex.prompt)
            texts.append(self.fmt.prompt_text(messages))
            layouts.append(tuple(tuple(im.size) for im in ims))
        if not texts:
            return []
        ids = self.processor.tokenizer(texts, add_special_tokens=False)["input_ids"]
        return [{"prompt": len(p), "layout": layout, "answer": len(self._completion(ex)[0])}
                for p, layout, ex in zip(ids, layouts, examples)]

    def _counts(self, enc, completions, prompt_lens) -> list[dict]:
        out = []
        for b, (p, (c, _)) in enumerate(zip(prompt_lens, completions)):
            n_img = 0
            if self.image_token_id is not None:
                n_img = int((enc["input_ids"][b] == self.image_token_id).sum())
            out.append({"total": p + len(c), "image": n_img, "text": p - n_img, "answer": len(c)})
        return out

    def budget_error(self, ex, counts: dict) -> DegustaError:
        """The one-line error of an example over the budget (`counts` as `token_counts` gives them)."""
        return DegustaError(f"{self.key}: episode {ex.episode} needs {counts['total']} tokens ({counts['image']} "
                            f"image tokens, {counts['text']} other prompt tokens, {counts['answer']} answer tokens) "
                            f"but the budget is {self.max_length}; nothing is truncated (cutting image tokens "
                            "breaks the model): lower model.image_size, compose images (data.compose), drop image "
                            f"groups (data.include) or raise {self.key} up to the model's context")

    def __call__(self, examples) -> dict:
        enc, completions, prompt_lens = self.encode(examples)
        lengths = [p + len(c) for p, (c, _) in zip(prompt_lens, completions)]
        if max(lengths) > self.max_length:
            for ex, counts in zip(examples, self._counts(enc, completions, prompt_lens)):
                if counts["total"] > self.max_length:
                    raise self.budget_error(ex, counts)
        T = max(lengths)
        B = len(examples)
        seq_shape = tuple(enc["input_ids"].shape)
        out = {k: v for k, v in enc.items() if not (torch.is_tensor(v) and tuple(v.shape) == seq_shape)}
        input_ids = torch.full((B, T), self.pad_id, dtype=torch.long)
        attention = torch.zeros((B, T), dtype=torch.long)
        labels = torch.full((B, T), IGNORE, dtype=torch.long)
        per_token = {k: torch.zeros((B, T), dtype=v.dtype) for k, v in enc.items()
                     if k not in ("input_ids", "attention_mask") and torch.is_tensor(v) and tuple(v.shape) == seq_shape}
        for b, (p, (c, supervised)) in enumerate(zip(prompt_lens, completions)):
            real = enc["attention_mask"][b].bool()
            input_ids[b, :p] = enc["input_ids"][b][real]
            input_ids[b, p:p + len(c)] = torch.tensor(c, dtype=torch.long)
            attention[b, :p + len(c)] = 1
            labels[b, p:p + len(c)] = torch.tensor(supervised, dtype=torch.long)
            for k, v in per_token.items():
                v[b, :p] = enc[k][b][real]
        out.update(input_ids=input_ids, attention_mask=attention, labels=labels, **per_token)
        if self.list_end_weight != 1.0:
            weights = (labels != IGNORE).float()
            for b, (p, (c, _)) in enumerate(zip(prompt_lens, completions)):
                for i in list_decisions(self.processor.tokenizer, c):
                    weights[b, p + i] = self.list_end_weight
            out["label_weights"] = weights
        return out


def list_decisions(tokenizer, ids: list[int]) -> list[int]:
    """Indices of the tokens of an answer's ids that decide its list's length: those whose text carries, at
    the top level of the answer's list (inside its "[", outside every item), the "," going on to another item
    or the "]" ending the list. Text outside any list (before the "[") counts for nothing.

    Example: "[{'id': 3, 'position': ['A1']}, {'id': 5, ...}]" -> the token with "}," (or ",") and the last "]".
    """
    out, depth = [], 0
    for i, token in enumerate(ids):
        text = tokenizer.decode([token], skip_special_tokens=False, clean_up_tokenization_spaces=False)
        decides = False
        for ch in text:
            if ch in "[{":
                depth += 1
            elif ch in "]}":
                decides = decides or (ch == "]" and depth == 1)
                depth = max(depth - 1, 0)
            elif ch == "," and depth == 1:
                decides = True
        if decides:
            out.append(i)
    return out


def supervised_text(tokenizer, batch: dict, row: int) -> str:
    """Decode the supervised tokens of one row (what the loss trains on)."""
    labels = batch["labels"][row]
    return tokenizer.decode(labels[labels != IGNORE].tolist(), skip_special_tokens=False)
