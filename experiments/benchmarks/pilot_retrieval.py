"""Pilot: how fast does a from-scratch decoder learn to retrieve from a scene given as 64 oracle image tokens
(or as text)? Perception factored out: image token k is the sum of the embeddings of cell k and of the type,
id and direction of what covers it (as `finetune/pretrain/dense.OracleTokens`). Logs teacher-forced accuracy
per content kind every 25 steps (type, id, cell, first cell of an item "cell1", later cells "cellN", dir).
A research script (docs/tiny_base.md, points 8-15), not part of the toolkit: arguments are key=value.

args: steps, bs, q (questions per scene), lr, beta2, warm (warmup steps), total (cosine length),
  mode=oracle|text, task=describe|list|locate|mix, norepeat=1 (min(q, objects) questions), chat=1 (chat turns),
  init=default|mimetic, tie=0|1, classinit=1, prevhead=1 (the previous-token head), layers, heads, kv, hidden,
  inter, alpha, beta, ov (mimetic scales), threads, seed,
  load=RUN/init (a pipeline run's initial weights instead of build_base + the pilot's init; rc=1 / rm=1 / rp=1
  re-apply the pilot's class init / mimetic draw / previous-token head on top),
  attsup=W (attention supervision of head atthead in layer attlayer, default 1 and 2; items=1: list items
  too), final_eval=1 (8 fresh batches, eval mode, fp32), check=1 (print the previous-token head's mass).

Examples (docs/tiny_base.md, point 14; RUN = a pretraining run folder of configs/pretrain_tiny_vlm_cpu.yaml):
    python benchmarks/pilot_retrieval.py steps=450 tie=1 seed=0 beta2=0.98 warm=100 total=4000 norepeat=1 chat=1 \
        load=RUN/init                     # the pipeline's init: first cell 0.14 at step 450
    python benchmarks/pilot_retrieval.py ... load=RUN/init attsup=1.0   # supervised: 0.67 at step 450
    python benchmarks/pilot_retrieval.py steps=450 tie=1 seed=0 beta2=0.98 warm=100 total=4000 task=list \
        load=RUN/init attsup=1.0 items=1  # list items supervised too (items=0: without)
"""

import math
import os
import sys
import time

os.environ["HF_HUB_OFFLINE"] = "1"
import numpy as np
import torch
import torch.nn.functional as F

from degusta_learn.finetune.pretrain.base import BaseArchitecture, build_base
from degusta_learn.finetune.pretrain.scenes import random_scene
from degusta_learn.finetune.pretrain.tasks import PerceptionExamples
from degusta_learn.prompting import answer_items, format_answer
from degusta_learn.render.grid import DIRECTIONS, Grid
from degusta_learn.scene import default_catalog, default_tables
from degusta_learn.trainer import cpu_has_native_bf16

A = dict(a.split("=", 1) for a in sys.argv[1:])
g = lambda k, d: type(d)(A.get(k, d))  # noqa: E731
STEPS, B, Q, LR = g("steps", 200), g("bs", 8), g("q", 8), g("lr", 1.5e-3)
BF16 = cpu_has_native_bf16()  # autocast to bfloat16 only where it is native: emulated it is ~60x slower
MODE, INIT, TIE, TASK = g("mode", "oracle"), g("init", "default"), g("tie", 0), g("task", "describe")
torch.set_num_threads(g("threads", 2))
torch.manual_seed(g("seed", 0))
arch = BaseArchitecture(
    text_layers=g("layers", 4),
    text_heads=g("heads", 4),
    text_kv_heads=g("kv", 2),
    text_hidden=g("hidden", 256),
    text_intermediate=g("inter", 768),
)
if A.get("load"):  # bisect: the pipeline's own initial weights, none of the pilot's init on top
    from degusta_learn.vlm.load import load_vlm

    model, proc = load_vlm(A["load"], device="cpu", dtype="float32", key="run")
    model.train()
else:
    model, proc = build_base(arch, seed=g("seed", 0))
tok = proc.tokenizer
cat = default_catalog()
tables = {t.id: t for t in default_tables()}
grid = Grid(8, 8)
pe = PerceptionExamples(cat, tables, grid, 256, 0, 10)
enc = lambda s: tok.encode(s, add_special_tokens=False)  # noqa: E731
one = lambda s: enc(s)[0]  # noqa: E731
CELL = [one(c) for c in grid.cells]
TYPE = {t: one(t) for t in cat.types}
DIR = {d: one(d) for d in DIRECTIONS}
IDT = {i: one(str(i)) for i in cat.ids}
SEP = one(";")
E = model.get_input_embeddings()
lm = model.model.language_model
head = model.lm_head
if (not A.get("load") or g("rc", 0)) and g(
    "classinit", 0
):  # a shared direction per token class (types, ids, cells, directions) in E and lm_head
    cls = [list(TYPE.values()), list(IDT.values()), CELL, list(DIR.values())]
    scale = g("classinit_scale", 1.0)
    with torch.no_grad():
        for members in cls:
            for W in (E.weight, head.weight):
                W[members] += scale * 0.02 * math.sqrt(1.0) * torch.randn(1, W.shape[1]) * 1.0
if TIE:
    head.weight = E.weight
H = arch.text_hidden
if (not A.get("load") or g("rm", 0)) and INIT == "mimetic":
    alpha, beta = g("alpha", 0.06), g("beta", 0.06)
    nh, nkv = arch.text_heads, arch.text_kv_heads
    d = H // nh
    with torch.no_grad():
        for layer in lm.layers:
            at = layer.self_attn
            at.k_proj.weight.normal_(0, alpha)
            at.v_proj.weight.normal_(0, beta)
            for h in range(nh):
                gq = h // (nh // nkv)
                at.q_proj.weight[h * d : (h + 1) * d] = at.k_proj.weight[
                    gq * d : (gq + 1) * d
                ] + 0.02 * torch.randn(d, H)
                at.o_proj.weight[:, h * d : (h + 1) * d] = at.v_proj.weight[gq * d : (gq + 1) * d].T * (
                    g("ov", 0.25) / (beta * beta * d)
                )
if (not A.get("load") or g("rp", 0)) and g(
    "prevhead", 0
):  # layer 0, head 0: a positional previous-token head (q/k biases through RoPE)
    at = lm.layers[0].self_attn
    dh = H // arch.text_heads
    npair, c = g("pairs", 8), g("pc", 80.0)
    theta = lm.rotary_emb.inv_freq if hasattr(lm, "rotary_emb") else None
    inv = 10000 ** (-torch.arange(dh // 2, dtype=torch.float32) / (dh // 2))
    a = math.sqrt(c)
    with torch.no_grad():
        at.q_proj.weight[0:dh] = 0
        at.q_proj.bias[0:dh] = 0
        for i in range(npair):
            at.q_proj.bias[i] = a
            at.k_proj.weight[i] = 0
            at.k_proj.weight[i + dh // 2] = 0
            at.k_proj.bias[i] = a * math.cos(inv[i])
            at.k_proj.bias[i + dh // 2] = a * math.sin(inv[i])
            at.q_proj.weight[dh + i] = 0  # head 1 shares kv head 0: blind to the positional dims
            at.q_proj.weight[dh + i + dh // 2] = 0
            at.q_proj.bias[dh + i] = 0
            at.q_proj.bias[dh + i + dh // 2] = 0
if g("check", 0):
    lm.config._attn_implementation = "eager"
    ids = torch.randint(10, 1900, (1, 700))
    out = lm(input_ids=ids, output_attentions=True)
    a0 = out.attentions[0][0, 0]
    diag = torch.diagonal(a0, offset=-1)
    print(
        "head0 mass on t-1:",
        diag.mean().item(),
        diag.min().item(),
        "head1 on t-1:",
        torch.diagonal(out.attentions[0][0, 1], offset=-1).mean().item(),
    )
    sys.exit()
ATT = {}
if g("attsup", 0.0):
    from transformers.models.qwen2.modeling_qwen2 import apply_rotary_pos_emb

    _L, _H = g("attlayer", 1), g("atthead", 2)

    def _grab(mod, args, kwargs):
        ATT["h"] = kwargs["hidden_states"]
        ATT["pe"] = kwargs["position_embeddings"]

    lm.layers[_L].self_attn.register_forward_pre_hook(_grab, with_kwargs=True)
    _IDSET = set(IDT.values())
    _CELLDIR = set(CELL) | set(DIR.values())

    def att_loss(ids, labels, idx):
        at = lm.layers[_L].self_attn
        h = ATT["h"]
        cos, sin = ATT["pe"]
        dh = at.head_dim
        grp = _H // (arch.text_heads // arch.text_kv_heads)
        q = torch.nn.functional.linear(
            h, at.q_proj.weight[_H * dh : (_H + 1) * dh], at.q_proj.bias[_H * dh : (_H + 1) * dh]
        )
        k = torch.nn.functional.linear(
            h, at.k_proj.weight[grp * dh : (grp + 1) * dh], at.k_proj.bias[grp * dh : (grp + 1) * dh]
        )
        q, k = apply_rotary_pos_emb(q[:, None], k[:, None], cos, sin)
        q, k = q[:, 0], k[:, 0]
        Bn, T = ids.shape
        rows = idx.view(Bn, 64, -1)
        qs, bs, tg = [], [], []
        il = ids.tolist()
        ll = labels.tolist()
        _NAMED = _IDSET | set(TYPE.values())
        for b in range(Bn):
            last = None
            up = [None] * T
            nx = None
            for t in range(T - 1, -1, -1):
                if ll[b][t] in _IDSET:
                    nx = ll[b][t]
                up[t] = nx
            for t in range(T - 1):
                if il[b][t] in _IDSET and t >= 64:
                    last = il[b][t]
                if last is not None and ll[b][t + 1] in _CELLDIR:
                    qs.append(t)
                    bs.append(b)
                    tg.append((rows[b] == last).any(-1))
                elif g("items", 0) and ll[b][t + 1] in _NAMED and up[t + 1] is not None:
                    qs.append(t)
                    bs.append(b)
                    tg.append((rows[b] == up[t + 1]).any(-1))
        if not qs:
            return h.new_zeros(())
        bs_t, qs_t = torch.tensor(bs), torch.tensor(qs)
        sc = (q[bs_t, qs_t][:, None, :] * k[bs_t]).sum(-1).float() * at.scaling  # (n, T)
        causal = torch.arange(T)[None, :] <= qs_t[:, None]
        sc = sc.masked_fill(~causal, float("-inf"))
        tgt = torch.stack(tg)
        full = torch.zeros(len(qs), T, dtype=torch.bool)
        full[:, :64] = tgt
        return (torch.logsumexp(sc, -1) - torch.logsumexp(sc.masked_fill(~full, float("-inf")), -1)).mean()


cat_of = {}
for t in TYPE.values():
    cat_of[t] = "type"
for t in IDT.values():
    cat_of[t] = "id"
for t in CELL:
    cat_of[t] = "cell"
for t in DIR.values():
    cat_of[t] = "dir"
rng = np.random.default_rng(g("seed", 0))


def scene_tokens(scene):
    labels = pe.cell_labels(scene.placements)
    if MODE == "oracle":
        img = []
        for k in range(64):
            ids = [CELL[k]]
            for oid, dd in labels[k]:
                ids += [TYPE[cat[oid].type], IDT[oid], DIR[dd]]
            img.append(ids)
        return img, []
    seq = []  # text: per non-empty cell "cell type id dir ... ;"
    for k in range(64):
        if labels[k]:
            seq.append(CELL[k])
            for oid, dd in labels[k]:
                seq += [TYPE[cat[oid].type], IDT[oid], DIR[dd]]
            seq.append(SEP)
    return None, seq


def question(scene, p, first_q):
    o = cat[p.object]
    qt = enc(f"\nWhere is the {o.type} with object_reference_id {o.id}?\n")
    if g("chat", 0):
        qt = enc(
            f"\n<|im_start|>user\nWhere is the {o.type} with object_reference_id {o.id} in final_state_1.jpg?<|im_end|>\n<|im_start|>assistant\n"
        )
    at = enc(format_answer(answer_items([p], cat, "grid", grid), "grid")) + [
        tok.convert_tokens_to_ids("<|im_end|>")
    ]
    return qt, at


def list_question(scene):
    ps = sorted(scene.placements, key=lambda p: pe._first_cell(p))
    qt = enc("\nList every object row by row from the top left.\n")
    at = enc(format_answer(answer_items(ps, cat, "grid", grid), "grid")) + [
        tok.convert_tokens_to_ids("<|im_end|>")
    ]
    return qt, at


def example():
    scene = random_scene(rng, cat, tables)
    img, seq = scene_tokens(scene)
    lab = [-100] * len(seq)
    ps = list(scene.placements)
    task = TASK if TASK != "mix" else ("list" if rng.random() < 0.5 else "describe")
    if task == "locate":
        order = rng.permutation(len(ps))[:Q]
        asked = [ps[j] for j in order]
        names = ", ".join(f"the {cat[p.object].type} with object_reference_id {p.object}" for p in asked)
        qt = enc(f"\nWhere are {names}?\n")
        at = enc(format_answer(answer_items(asked, cat, "grid", grid), "grid")) + [
            tok.convert_tokens_to_ids("<|im_end|>")
        ]
        seq += qt + at
        lab += [-100] * len(qt) + at
    elif task == "list":
        qt, at = list_question(scene)
        seq += qt + at
        lab += [-100] * len(qt) + at
    else:
        order = rng.permutation(len(ps))
        for q in range(min(Q, len(ps)) if g("norepeat", 0) else Q):
            p = ps[order[q % len(ps)]]
            qt, at = question(scene, p, q == 0)
            seq += qt + at
            lab += [-100] * len(qt) + at
    return img, seq, lab


def batch():
    exs = [example() for _ in range(B)]
    n_img = 64 if MODE == "oracle" else 0
    T = n_img + max(len(s) for _, s, _ in exs)
    pad = tok.pad_token_id
    ids = torch.full((B, T), pad)
    labels = torch.full((B, T), -100)
    att = torch.zeros(B, T, dtype=torch.long)
    flat = []
    for b, (img, s, lb) in enumerate(exs):
        ids[b, n_img : n_img + len(s)] = torch.tensor(s)
        labels[b, n_img : n_img + len(s)] = torch.tensor(lb)
        att[b, : n_img + len(s)] = 1
        if img:
            flat += img
    idx = None
    if flat:
        L = max(len(r) for r in flat)
        idx = torch.tensor([r + [-1] * (L - len(r)) for r in flat])
    return ids, labels, att, idx, n_img


def embed(ids, idx):
    """Input embeddings with the 64 image positions replaced by their oracle sums (when there is an image)."""
    x = E(ids)
    if idx is None:
        return x
    m = (idx >= 0).float()
    vec = (E(idx.clamp(min=0)) * m[..., None]).sum(1).view(ids.shape[0], 64, -1)
    return torch.cat([vec.to(x.dtype), x[:, 64:]], 1)


opt = torch.optim.AdamW(model.parameters(), lr=LR, weight_decay=0.01, betas=(0.9, g("beta2", 0.98)))
WARM = g("warm", 50)
t0 = time.time()
stats = {}
hist = []
for step in range(1, STEPS + 1):
    ids, labels, att, idx, n_img = batch()
    cur = LR * min(1.0, step / WARM) * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * step / g("total", STEPS))))
    for gr in opt.param_groups:
        gr["lr"] = cur
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=BF16):
        h = lm(inputs_embeds=embed(ids, idx), attention_mask=att).last_hidden_state[:, :-1]
        tgt = labels[:, 1:]
        sel = tgt != -100
        logits = head(h[sel]).float()
    loss = F.cross_entropy(logits, tgt[sel])
    if g("attsup", 0.0) and step <= g("attsteps", 10**9):
        la = att_loss(ids, labels, idx)
        ATT.setdefault("log", []).append(la.item())
        loss = loss + g("attsup", 0.0) * la
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
    opt.step()
    opt.zero_grad()
    with torch.no_grad():
        t = tgt[sel].tolist()
        pr = logits.argmax(-1).tolist()
        prev = None
        for tv, pv in zip(t, pr):
            c = cat_of.get(tv)
            cs = [c] if c else []
            if c == "cell":
                cs.append("cell1" if prev != "cell" else "cellN")
            for c2 in cs:
                s = stats.setdefault(c2, [0, 0])
                s[0] += tv == pv
                s[1] += 1
            if c:
                prev = c
    hist.append(loss.item())
    if step % 25 == 0:
        acc = {k: v[0] / max(1, v[1]) for k, v in stats.items()}
        tot = sum(v[0] for v in stats.values()) / max(1, sum(v[1] for v in stats.values()))
        print(f"att {np.mean(ATT.pop('log', [0])):.3f} ", end="")
        print(
            f"step {step} t={time.time() - t0:.0f}s loss {np.mean(hist):.3f} content {tot:.3f} "
            + " ".join(
                f"{k} {acc[k]:.2f}" for k in ("type", "id", "cell", "cell1", "cellN", "dir") if k in acc
            ),
            flush=True,
        )
        stats, hist = {}, []

if g("final_eval", 0):  # fresh batches, eval mode, fp32, no update: is the running tally a fair measurement?
    model.eval()
    stats = {}
    with torch.no_grad():
        for _ in range(8):
            ids, labels, att, idx, n_img = batch()
            h = lm(inputs_embeds=embed(ids, idx), attention_mask=att).last_hidden_state[:, :-1]
            tgt = labels[:, 1:]
            sel = tgt != -100
            pr = head(h[sel]).argmax(-1).tolist()
            prev = None
            for tv, pv in zip(tgt[sel].tolist(), pr):
                c = cat_of.get(tv)
                if c == "cell":
                    k = "cell1" if prev != "cell" else "cellN"
                    s_ = stats.setdefault(k, [0, 0])
                    s_[0] += tv == pv
                    s_[1] += 1
                if c:
                    prev = c
    print(
        "final fresh eval fp32:",
        {k: round(a / n, 3) for k, (a, n) in stats.items()},
        {k: n for k, (a, n) in stats.items()},
    )
