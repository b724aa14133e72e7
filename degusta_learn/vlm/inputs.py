"""Turn a `Prompt` (+ answer) into model inputs the way the model's own chat template wants them.

One `ChatFormat` per processor, probed once from the chat template:
- the prompt is the user turn rendered with `add_generation_prompt=True` and tokenized with
  `add_special_tokens=False` (templates already hold the BOS: no double BOS);
- the supervised completion is what the template puts after the generation prompt, cut right after
  the end-of-turn token: e.g. `" [...]<end_of_utterance>"` (SmolVLM) or `"[...]<|im_end|>"` (Qwen2-VL);
- the stop ids of generation always include that end-of-turn token (so generation stops where
  training taught it to);
- the template is rendered by `vlm/chat_template.py`: the text `processor.apply_chat_template` writes, with
  bounds on time and size, so a template that loops or grows without end is a one-line error within seconds.

`set_image_budget` makes the image cost explicit: one tile per image for Idefics3/SmolVLM (no 17-tile
blow-ups), fixed pixels for Qwen2-VL; `tokens_per_image` measures it with the real processor.
`check_grid_resolution` refuses a budget coarser than the grid and, given the render size, says where the grid's
cell borders fall among the image tokens (`vlm/token_grid.py`).

Example:
    fmt = ChatFormat(processor, model.generation_config)
    inputs = encode_prompt(processor, fmt, prompt)       # BatchFeature, 1 row
"""

from __future__ import annotations

from PIL import Image

from degusta_learn.errors import DegustaError
from degusta_learn.vlm.chat_template import render_chat

_PROBE = "ANSWER_PROBE_7"
_QUESTION = "QUESTION_PROBE_7"


def prompt_messages(prompt) -> tuple[list[dict], list[Image.Image]]:
    """(chat messages with one user turn, its images in order) from a `prompting.Prompt`."""
    content: list[dict] = []
    images: list[Image.Image] = []
    texts: list[str] = []
    for part in prompt.parts:
        if isinstance(part, str):
            texts.append(part)
            continue
        if texts:
            content.append({"type": "text", "text": ("\n" if images else "") + "\n".join(texts) + " "})
            texts = []
        content.append({"type": "image"})
        images.append(part.image.convert("RGB"))
    if texts:
        content.append({"type": "text", "text": ("\n" if images else "") + "\n".join(texts)})
    return [{"role": "user", "content": content}], images


class ChatFormat:
    """What a processor's chat template does around an answer (probed once; see module docstring)."""

    def __init__(self, processor, generation_config=None):
        self.processor = processor
        tok = self.tokenizer = processor.tokenizer
        if not getattr(processor, "chat_template", None):
            raise DegustaError("model: the processor has no chat template (an instruct/chat VLM is needed)")
        self._template = processor.chat_template
        self._special = dict(getattr(tok, "special_tokens_map", None) or {})
        user = [_user_message("x")]
        # a template that does not parse, raises or breaks a bound: one line now, not at the first answer
        prompt = self.render(user, add_generation_prompt=True)
        full = self.render(user + [assistant_message(_PROBE)])
        if not full.startswith(prompt) or _PROBE not in full[len(prompt):]:
            raise DegustaError("model: its chat template does not render the answer right after the "
                               "generation prompt; fine-tuning this template is not supported")
        completion = full[len(prompt):]
        at = completion.index(_PROBE)
        self.lead, tail = completion[:at], completion[at + len(_PROBE):]
        eos = getattr(generation_config, "eos_token_id", None) if generation_config is not None else None
        stops = [eos] if isinstance(eos, int) else list(eos or [])
        if tok.eos_token_id is not None:
            stops.append(tok.eos_token_id)
        tail_ids = tok(tail, add_special_tokens=False)["input_ids"]
        special = set(tok.all_special_ids)
        end = next((i for i in tail_ids if i in stops), None)
        if end is None:
            end = next((i for i in tail_ids if i in special), None)
        if end is None:
            raise DegustaError("model: its chat template closes the assistant turn without a special "
                               "end-of-turn token; generation could not learn to stop")
        self.end_id = end
        self.end_text = tok.decode([end], skip_special_tokens=False)
        self.stop_ids = list(dict.fromkeys([end, *stops]))
        self._prompt_probe = prompt
        self._followup: tuple[str, str] | None = None  # probed on first use (followup_text)
        bos = tok.bos_token_id
        # Templates normally hold the BOS; add it ourselves only if the tokenizer wants one and it is missing.
        self.add_bos = bool(bos is not None and tok("x")["input_ids"][:1] == [bos] and not prompt.startswith(
            tok.bos_token or "\0"))

    def render(self, messages: list[dict], add_generation_prompt: bool = False) -> str:
        """The processor's chat template applied to `messages` (as `processor.apply_chat_template(...,
        tokenize=False)` writes them), with bounds on its time and size (`vlm/chat_template.py`): a template that
        loops or grows without end is a one-line DegustaError within seconds."""
        return render_chat(self._template, messages, add_generation_prompt, self._special)

    def prompt_text(self, messages: list[dict]) -> str:
        text = self.render(messages, add_generation_prompt=True)
        return (self.tokenizer.bos_token + text) if self.add_bos else text

    def completion_text(self, answer: str) -> str:
        """The supervised text: template lead + answer + end-of-turn token."""
        return self.lead + answer + self.end_text

    def followup_text(self, question: str) -> str:
        """The unsupervised text between an answer's end-of-turn token and the next answer's lead: the rest
        of the template's assistant turn, a user turn asking `question` (text only), the generation prompt."""
        if self._followup is None:
            conversation = [_user_message("x"), assistant_message(_PROBE), _user_message(_QUESTION)]
            follow = self.render(conversation, add_generation_prompt=True)
            done = self._prompt_probe + self.completion_text(_PROBE)
            if not follow.startswith(done) or _QUESTION not in follow[len(done):]:
                raise DegustaError("model: its chat template does not render a further user turn after an answer "
                                   "the way it renders the first; follow-up questions are not supported")
            self._followup = tuple(follow[len(done):].split(_QUESTION, 1))  # (before, after) the question
        before, after = self._followup
        return before + question + after


def _user_message(text: str) -> dict:
    return {"role": "user", "content": [{"type": "text", "text": text}]}


def assistant_message(text: str) -> dict:
    return {"role": "assistant", "content": [{"type": "text", "text": text}]}


def encode_prompt(processor, fmt: ChatFormat, prompt):
    """Model inputs (1 row, tensors) for generating the answer to `prompt`."""
    messages, images = prompt_messages(prompt)
    return processor(text=[fmt.prompt_text(messages)], images=[images] if images else None,
                     add_special_tokens=False, return_tensors="pt")


def set_image_budget(processor, model_config, image_size: int | None, key: str = "model.image_size") -> None:
    """Fix the processor's per-image cost: one tile of `image_size` px (Idefics3) or image_size^2 px (Qwen)."""
    ip = processor.image_processor
    mtype = getattr(model_config, "model_type", "")
    if mtype == "idefics3":
        vc = model_config.vision_config
        size = image_size or ip.max_image_size["longest_edge"]
        unit = vc.patch_size * model_config.scale_factor
        if size % unit:
            raise DegustaError(f"{key}: {size} must be a multiple of patch_size x scale_factor = {unit}")
        ip.do_image_splitting = False
        ip.size = {"longest_edge": size}
        ip.max_image_size = {"longest_edge": size}
        processor.image_seq_len = (size // vc.patch_size) ** 2 // model_config.scale_factor ** 2
    elif mtype in ("qwen2_vl", "qwen2_5_vl"):
        if image_size is None:  # the saved budget, capped at 448 px (Qwen's default max_pixels -> OOM)
            current = int((ip.size or {}).get("longest_edge", 448 * 448) ** 0.5) // 28 * 28
            image_size = max(28, min(current, 448) // 28 * 28)
        size = image_size
        if size % 28:
            raise DegustaError(f"{key}: {size} must be a multiple of 28 for Qwen2-VL (patch 14 x merge 2)")
        # Square images of any size land on exactly size x size px: the +-14 px margins keep Qwen's
        # floor/ceil rounding (smart_resize) from falling one patch row short or over.
        lo, hi = (size - 14) ** 2 + 1, (size + 14) ** 2 - 1
        ip.size = {"shortest_edge": lo, "longest_edge": hi}
        for attr, value in (("min_pixels", lo), ("max_pixels", hi)):
            if hasattr(ip, attr):
                setattr(ip, attr, value)
    elif mtype == "fast_vlm":  # a CNN tower: image_size / output stride tokens per side, no crop
        stride = getattr(processor, "patch_size", None) or 32
        size = image_size or (getattr(ip, "size", None) or {}).get("height") or 256
        if size % stride:
            raise DegustaError(f"{key}: {size} must be a multiple of the vision tower's output stride {stride}")
        ip.size = {"height": size, "width": size}
        ip.crop_size = {"height": size, "width": size}
        ip.do_center_crop = False
    elif image_size:
        ip.size = {"height": image_size, "width": image_size}
    _check_context(processor, model_config, key)


def _check_context(processor, model_config, key: str) -> None:
    """One image may not cost more image tokens than the language model has positions (a budget the model cannot
    take: its first prompt would fail, or exhaust memory)."""
    side = image_tokens_per_side(processor, model_config)
    text = getattr(model_config, "text_config", None) or model_config
    positions = getattr(text, "max_position_embeddings", None)
    if side and isinstance(positions, int) and side * side > positions:
        raise DegustaError(f"{key}: this budget gives {side} x {side} = {side * side:,} image tokens an image, more "
                           f"than the model's {positions:,} positions (max_position_embeddings); lower {key}")


def tokens_per_image(processor, fmt: ChatFormat, image_token_id: int) -> int:
    """How many image tokens one image costs with this processor (measured, not assumed)."""
    messages = [{"role": "user", "content": [{"type": "image"}, {"type": "text", "text": "x"}]}]
    enc = processor(text=[fmt.prompt_text(messages)], images=[[Image.new("RGB", (448, 448), "white")]],
                    add_special_tokens=False)
    ids = enc["input_ids"][0]
    return int(sum(1 for i in ids if i == image_token_id))


def image_tokens_per_side(processor, model_config) -> int | None:
    """Image tokens along one side of a (square, one-tile) image with this budget; None if unknown."""
    ip = processor.image_processor
    mtype = getattr(model_config, "model_type", "")
    if mtype == "idefics3":
        if getattr(ip, "do_image_splitting", False):
            return None  # tiles: several token grids per image
        size = (getattr(ip, "max_image_size", None) or {}).get("longest_edge")
        unit = model_config.vision_config.patch_size * model_config.scale_factor
        return size // unit if size else None
    if mtype == "fast_vlm":
        size = (getattr(ip, "size", None) or {}).get("height")
        stride = getattr(processor, "patch_size", None)
        return size // stride if size and stride else None
    if mtype in ("qwen2_vl", "qwen2_5_vl"):
        vc = model_config.vision_config
        unit = getattr(vc, "patch_size", 14) * getattr(vc, "spatial_merge_size", 2)
        pixels = (getattr(ip, "size", None) or {}).get("longest_edge") or getattr(ip, "max_pixels", None)
        return int(pixels ** 0.5) // unit if pixels else None
    return None


def check_grid_resolution(processor, model_config, grid, key: str = "model.image_size",
                          render_size: int | None = None, image_size: tuple[int, int] | None = None):
    """Refuse an image budget whose image tokens are coarser than the grid's cells (one line naming `key`);
    with `render_size`, also say where the cells' borders fall among the image tokens.

    With fewer image tokens per side than grid cells per side, no image token covers a single cell, so
    the model cannot tell which cell an object is in: a grid method cannot be learned or answered.
    Where the token geometry is not known (another model type, an Idefics3 processor that splits images
    into tiles) the image tokens of one image are counted with the processor itself, and fewer tokens
    than the grid has cells is refused.

    Returns:
        With `render_size` (the size GMA images are drawn at) and a known token geometry, the
        `vlm.token_grid.GridAlignment` of a GMA image of `image_size` px (default: a square table's,
        `render_size` x `render_size`) with the renderer's label margins: each cell border's distance to
        the nearest token border, or that they line up. Otherwise None. Misalignment is reported, not refused.
    """
    n = image_tokens_per_side(processor, model_config)
    need = max(grid.rows, grid.cols)
    if n is None:
        count = _measured_image_tokens(processor, model_config)
        if count is not None and count < grid.rows * grid.cols:
            raise DegustaError(f"{key}: an image gives the model {count} image tokens, fewer than the "
                               f"{grid.rows}x{grid.cols} grid's {grid.rows * grid.cols} cells, so it cannot see "
                               f"which cell an object is in; raise {key} or use a coarser grid")
        return None
    if n < need:
        mtype, vc = getattr(model_config, "model_type", ""), model_config.vision_config
        unit = (vc.patch_size * model_config.scale_factor if mtype == "idefics3" else
                processor.patch_size if mtype == "fast_vlm" else
                getattr(vc, "patch_size", 14) * getattr(vc, "spatial_merge_size", 2))
        raise DegustaError(f"{key}: images give the model {n} x {n} image tokens, fewer than the {grid.rows}x{grid.cols} grid's "
                           f"{need} cells per side, so it cannot see which cell an object is in; use at least "
                           f"{need * unit} px per image (one token per {unit} px) or a coarser grid")
    if render_size is None:
        return None
    from degusta_learn.vlm.token_grid import cell_alignment, gma_margin, image_token_grid

    width, height = image_size or (render_size, render_size)
    tokens = image_token_grid(processor, model_config, width, height)
    return None if tokens is None else cell_alignment(grid, (width, height), gma_margin(render_size), tokens)


def _measured_image_tokens(processor, model_config) -> int | None:
    """Image tokens of one square image, counted with the processor; None where it cannot be counted."""
    token_id = getattr(model_config, "image_token_id", None)
    if token_id is None:
        token_id = getattr(model_config, "image_token_index", None)
    if token_id is None:
        return None
    try:
        return tokens_per_image(processor, ChatFormat(processor), token_id)
    except DegustaError:  # no usable chat template: the backend refuses the model itself
        return None
