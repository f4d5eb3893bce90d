"""Image-to-video flow models v_theta(x_t, t | first frame, text), LoRA, and checkpoints (Sec. 3 "Setup", App. A.1).

The paper's base is LTX-2; on a laptop it is `ToyVideoFlow`, a ~1.1M-parameter (2+1)D convolutional U-Net over
the toy world's 16x16 videos (world.py), pretrained by `python train.py --stage pretrain` on captions in the style
of the detailed description D. Design notes (../shared/notes/toy-prototype.md says why the first ones matter):
convolutions, per-frame FiLM from (pooled text, flow time t, frame index) through a small MLP, x/y coordinate
channels, the first frame as input channels, a zero-initialised temporal conv in every block, a bottleneck
transformer block (self-attention over space-time tokens, cross-attention to the text tokens). The clean video x_1
is predicted by *dynamic neighbourhood advection* (DNA, Finn et al. 2016): each frame is the previous one with
every pixel a softmax-weighted mix of its 3x3 neighbours, plus a residual -- so a moved sprite keeps its exact
pixels. Measured on the toy: with a plain residual on the first frame, moving sprites came out as coloured blobs
(consistency 0.06 given the error-free D after the same 2000 steps); docs/base.md has the table.
With `evidence` (the shipped base: a 5x5 window) each of the 9 moves' logits also gets the log-likelihood of x_t
under that move, log N(x_t | t x_1, (1 - t)^2 I) summed over the window around the pixel -- the data term of the
Bayes posterior over moves, which a flow model needs to *commit* to one motion when the prompt leaves it open.
Without it the base blended the possible motions into smears whenever the prompt did not fix the motion (given only
T: consistency 0.125). A plain window also pools a moving sprite's evidence into a still neighbour and drags it
along; `evidence_by_colour` (on in the shipped base) pools a sprite pixel's evidence only over its own sprite
(`_pool_evidence`). `ground` (off in the shipped base) adds `Grounding`, a path from each word to a place in
the first frame; tried with goal-captioned pretraining, it did not help (docs/given-t.md). `relate` (off in the
shipped base) adds `Relate`, every pixel's offset to where the caption points; tried likewise, its heads did not
learn to point (docs/given-t.md, with the measurements).

Latent space of the toy model: the generated frames 1..F-1 as a tensor (B, T=F-1, 3, H, W) in [-1, 1]; frame 0
is the clean condition, not generated (as in image-to-video LTX-2, where first-frame tokens sit at t = 1 here).

The Executor is this model plus LoRA adapters (B = 0 at init, so it starts equal to the base); the Demonstrator is
the *same* weights with the adapters switched off (`adapters_disabled`) -- one copy in memory, as with LTX-2.
"""
from __future__ import annotations

import contextlib
import copy
import ctypes
import math
import os
import re
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F_

import flow
import world

# ----------------------------------------------------------------------------------------------------------------
# text: a word-level tokenizer and an order-aware encoder
# ----------------------------------------------------------------------------------------------------------------


class Tokenizer:
    """Words of world.VOCAB -> ids 1..V (0 is padding). Any other word is an error, named in the message."""

    def __init__(self, vocab: list[str], max_len: int = 16):
        self.vocab, self.max_len = list(vocab), max_len
        self.ids = {w: i + 1 for i, w in enumerate(self.vocab)}

    def words(self, text: str) -> list[str]:
        text = text.lower().strip()
        words = re.findall(r"\[|\]|:|[^\s\[\]:]+", text)
        for w in words:
            if w not in self.ids:
                raise ValueError(f"unknown word {w!r} in prompt {text!r} (the toy vocabulary has {len(self.vocab)} "
                                 f"words: {' '.join(self.vocab)})")
        if len(words) > self.max_len:
            raise ValueError(f"prompt {text!r} has {len(words)} words; at most {self.max_len}")
        return words

    def __call__(self, texts: list[str]) -> torch.Tensor:
        """list of B prompts -> (B, max_len) long, right-padded with 0."""
        out = torch.zeros(len(texts), self.max_len, dtype=torch.long)
        for i, t in enumerate(texts):
            ids = [self.ids[w] for w in self.words(t)]
            out[i, :len(ids)] = torch.tensor(ids, dtype=torch.long)
        return out


class Attention(nn.Module):
    """Multi-head attention with separate q/k/v/out projections (the Linear layers LoRA attaches to)."""

    def __init__(self, dim: int, heads: int, ctx_dim: int | None = None):
        super().__init__()
        self.heads = heads
        self.to_q = nn.Linear(dim, dim)
        self.to_k = nn.Linear(ctx_dim or dim, dim)
        self.to_v = nn.Linear(ctx_dim or dim, dim)
        self.to_out = nn.Linear(dim, dim)

    def forward(self, x, ctx=None, key_mask=None):
        ctx = x if ctx is None else ctx
        B, N, D = x.shape
        q, k, v = (z.reshape(B, -1, self.heads, D // self.heads).transpose(1, 2)  # (B, nh, N, hs)
                   for z in (self.to_q(x), self.to_k(ctx), self.to_v(ctx)))
        mask = None if key_mask is None else key_mask[:, None, None, :]  # (B, 1, 1, L): True = attend
        y = F_.scaled_dot_product_attention(q, k, v, attn_mask=mask)      # (B, nh, N, hs)
        return self.to_out(y.transpose(1, 2).reshape(B, N, D))


class TextEncoder(nn.Module):
    """Word embeddings + learned positions + pre-norm transformer layers: order-aware, so "[red square]: move to
    the blue circle" and "[blue circle]: move to the red square" get different encodings."""

    def __init__(self, vocab_size: int, dim: int, layers: int, heads: int, max_len: int):
        super().__init__()
        self.emb = nn.Embedding(vocab_size + 1, dim, padding_idx=0)
        self.pos = nn.Parameter(torch.randn(max_len, dim) * 0.02)
        self.blocks = nn.ModuleList(nn.ModuleList([nn.LayerNorm(dim), Attention(dim, heads), nn.LayerNorm(dim),
                                                   nn.Sequential(nn.Linear(dim, 2 * dim), nn.GELU(),
                                                                 nn.Linear(2 * dim, dim))]) for _ in range(layers))
        self.norm = nn.LayerNorm(dim)

    def forward(self, ids):
        """ids (B, L) -> tokens (B, L, dim), attend (B, L) the keys to attend to (the real words, and slot 0 so an
        empty caption has one), pooled (B, dim) the mean over the real words."""
        mask = ids > 0
        attend = mask.clone()
        attend[:, 0] = True  # an empty caption still has one key to attend to (its padding slot)
        h = self.emb(ids) + self.pos[: ids.shape[1]]
        for ln1, attn, ln2, mlp in self.blocks:
            h = h + attn(ln1(h), key_mask=attend)
            h = h + mlp(ln2(h))
        h = self.norm(h)
        return h, attend, word_mean(h, ids)


def word_mean(h: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """Mean of the token encodings h (B, L, dim) over the real words (ids > 0): (B, dim); 0 for an empty caption."""
    words = (ids > 0)[..., None]
    return (h * words).sum(1) / words.sum(1).clamp(min=1)


def point_into_frame(q: torch.Tensor, keys: torch.Tensor, coords: torch.Tensor):
    """Queries q (B, ..., feat) attend over the first frame's pixels, keys (B, feat, HW): softmax(q . k / sqrt(feat))
    -> the attention a (B, ..., HW) and the place it lands, its attention-weighted coordinates xy (B, ..., 2)."""
    a = torch.softmax(torch.einsum("b...f,bfp->b...p", q, keys) / math.sqrt(q.shape[-1]), dim=-1)
    return a, torch.einsum("b...p,cp->b...c", a, coords.flatten(1))


class Grounding(nn.Module):
    """Words point into the first frame. Each text token queries the first frame's pixels (keys: a small conv of
    the frame, so colour and shape), takes the attention-weighted pixel coordinates (x, y) per head and how peaked
    the attention is, adds an embedding of them to its encoding, and one more transformer layer lets the tokens
    combine their positions ("where is the agent, where is the target"). A real video DiT gets this from attention
    between text and image tokens; the toy's U-Net only meets the text at its 4x4 bottleneck and in a pooled FiLM
    vector, so without this it had no short path from "to the blue circle" to where the blue circle is. Measured
    with 25% goal-captioned pretraining: goal captions 0.360 with it, 0.375 without -- no help; off in the shipped
    base (docs/results.md, "Why the Executor does not learn T here")."""

    def __init__(self, dim: int, heads: int, feat: int = 16):
        super().__init__()
        self.heads, self.feat = heads, feat
        self.frame = nn.Sequential(nn.Conv2d(3, feat, 3, padding=1), nn.SiLU(), nn.Conv2d(feat, feat, 3, padding=1))
        self.q = nn.Linear(dim, heads * feat)
        self.where = nn.Sequential(nn.Linear(3 * heads, dim), nn.SiLU(), nn.Linear(dim, dim))
        self.ln1, self.attn, self.ln2 = nn.LayerNorm(dim), Attention(dim, heads), nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))
        self.norm = nn.LayerNorm(dim)

    def forward(self, tokens, attend, frame0, coords):
        """tokens (B, L, D), attend (B, L), frame0 (B, 3, H, W), coords (2, H, W) -> tokens (B, L, D)."""
        B, L, _ = tokens.shape
        keys = self.frame(frame0).flatten(2)                                              # (B, feat, HW)
        q = self.q(tokens).reshape(B, L, self.heads, self.feat)
        a, xy = point_into_frame(q, keys, coords)                                         # xy (B, L, heads, 2)
        peak = a.max(dim=-1).values[..., None]                                            # (B, L, heads, 1)
        h = tokens + self.where(torch.cat([xy, peak], -1).flatten(2))
        h = h + self.attn(self.ln1(h), key_mask=attend)
        return self.norm(h + self.mlp(self.ln2(h)))


class Relate(nn.Module):
    """Where the caption points in the first frame, as pixel channels. Each of `heads` queries, read from the
    pooled caption by a small MLP, attends over the first frame's pixels (keys: a small conv of the frame, so
    colour and shape) and lands at the attention-weighted coordinates q_h; every pixel p then gets q_h - p (in
    units of 4 px) and the attention map itself as input channels of the U-Net. Grounding gives the words a
    place; this gives every pixel its offset to that place, so "move towards the blue circle until beside it" is
    a rule a 3x3 conv can apply where the agent is, at every frame (the offset is read where the sprite is now).
    Returns (B, 3 * heads, H, W). Measured (docs/given-t.md, "A base with offsets to where the caption points"):
    pretrained with 25% goal captions, no head learned to point at the target or the agent (each within 1 px of
    the target in at most 8% of bench pairs), so the offsets are there and unused; off in the shipped base.
    train.py --point_weight supervises heads 0 and 1 in pretraining (docs/given-t.md, "Teaching the offset heads to
    point"), and cfg.relate_text gives Relate its own text encoder (docs/given-t.md, "Relate with its own text
    encoder")."""

    def __init__(self, dim: int, heads: int, feat: int = 16):
        super().__init__()
        self.heads, self.feat = heads, feat
        self.frame = nn.Sequential(nn.Conv2d(3, feat, 3, padding=1), nn.SiLU(), nn.Conv2d(feat, feat, 3, padding=1))
        self.q = nn.Sequential(nn.Linear(dim, dim), nn.SiLU(), nn.Linear(dim, heads * feat))

    def attend(self, pooled, frame0, coords):
        """Where each head looks: its attention over the pixels (B, heads, HW) and where it lands (B, heads, 2)."""
        q = self.q(pooled).reshape(len(pooled), self.heads, self.feat)
        return point_into_frame(q, self.frame(frame0).flatten(2), coords)

    def forward(self, pooled, frame0, coords):
        """pooled (B, dim) the caption, frame0 (B, 3, H, W), coords (2, H, W) -> (B, 3 * heads, H, W)."""
        B, _, H, W = frame0.shape
        a, xy = self.attend(pooled, frame0, coords)                                       # (B, heads, HW), (.., 2)
        rel = (xy[..., None, None] - coords[None, None]) * (H - 1) / 8                    # (B, heads, 2, H, W)
        return torch.cat([rel.flatten(1, 2), a.reshape(B, self.heads, H, W) * H * W / 9], 1)


# ----------------------------------------------------------------------------------------------------------------
# the (2+1)D U-Net
# ----------------------------------------------------------------------------------------------------------------


class ResBlock(nn.Module):
    """Spatial 3x3 convs with FiLM from the per-frame embedding, then a zero-initialised temporal conv (k = 3)."""

    def __init__(self, c_in: int, c_out: int, emb_dim: int):
        super().__init__()
        self.n1, self.c1 = nn.GroupNorm(8, c_in), nn.Conv2d(c_in, c_out, 3, padding=1)
        self.film = nn.Linear(emb_dim, 2 * c_out)
        self.n2, self.c2 = nn.GroupNorm(8, c_out), nn.Conv2d(c_out, c_out, 3, padding=1)
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()
        self.nt, self.ct = nn.GroupNorm(8, c_out), nn.Conv1d(c_out, c_out, 3, padding=1)
        nn.init.zeros_(self.ct.weight)
        nn.init.zeros_(self.ct.bias)

    def forward(self, x, emb, T: int):
        # x: (B*T, C, h, w), emb: (B*T, E)
        h = self.c1(F_.silu(self.n1(x)))
        scale, shift = self.film(emb)[..., None, None].chunk(2, dim=1)
        h = self.c2(F_.silu(self.n2(h * (1 + scale) + shift)))
        x = self.skip(x) + h
        BT, C, hh, ww = x.shape
        z = F_.silu(self.nt(x)).reshape(BT // T, T, C, hh * ww).permute(0, 3, 2, 1).reshape(-1, C, T)  # (B*hw, C, T)
        z = self.ct(z).reshape(BT // T, hh * ww, C, T).permute(0, 3, 2, 1).reshape(BT, C, hh, ww)
        return x + z


class BottleneckAttention(nn.Module):
    """At the 4x4 bottleneck: self-attention over all T*16 space-time tokens, cross-attention to text tokens."""

    def __init__(self, dim: int, text_dim: int, heads: int):
        super().__init__()
        self.n1, self.attn = nn.LayerNorm(dim), Attention(dim, heads)
        self.n2, self.cross = nn.LayerNorm(dim), Attention(dim, heads, ctx_dim=text_dim)
        self.n3, self.mlp = nn.LayerNorm(dim), nn.Sequential(nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))

    def forward(self, x, text, text_mask, T: int):
        BT, C, hh, ww = x.shape
        h = x.reshape(BT // T, T, C, hh * ww).permute(0, 1, 3, 2).reshape(BT // T, T * hh * ww, C)  # (B, T*hw, C)
        h = h + self.attn(self.n1(h))
        h = h + self.cross(self.n2(h), text, text_mask)
        h = h + self.mlp(self.n3(h))
        return h.reshape(BT // T, T, hh * ww, C).permute(0, 1, 3, 2).reshape(BT, C, hh, ww)


@dataclass
class ToyConfig:
    width: int = 32          # channels at 16x16; 2x at 8x8, 3x at 4x4
    text_dim: int = 64
    text_layers: int = 2
    heads: int = 4
    emb_dim: int = 128
    max_words: int = 16
    frames: int = world.F - 1  # generated frames T
    size: int = world.H
    min_one_minus_t: float = 0.05  # v = (x1_hat - x_t) / max(1 - t, this): keeps the velocity finite at t -> 1
    dna: bool = True         # predict x1_hat by advecting the first frame frame-by-frame (3x3 dynamic filters) + a residual
    evidence: int = 0        # > 0: add to each DNA filter's logits the log-likelihood of x_t under each of its 9
                             # moves, summed over this many pixels square around the pixel (0: off)
    evidence_by_colour: bool = False  # pool a sprite pixel's evidence only over its own sprite (its colour)
    evidence_lead: bool = False  # with evidence_by_colour: a sprite's move evidence also counts the pixels it moves
                                 # onto, and a background pixel follows the sprite beside it (_lead_evidence)
    ground: bool = False     # text tokens point into the first frame (Grounding) before the U-Net reads them
    relate: bool = False     # every pixel gets its offset to where the caption points in the first frame (Relate)
    relate_text: bool = False  # with relate: Relate reads the caption through its own text encoder, not the U-Net's

    def __post_init__(self):
        if self.width < 8 or self.width % 8:
            raise ValueError(f"width must be a positive multiple of 8 (the U-Net's GroupNorms have 8 groups), "
                             f"got {self.width}")
        if self.evidence < 0 or self.evidence % 2 == 0 and self.evidence:
            raise ValueError(f"evidence must be 0 (off) or an odd window size (a window centred on the pixel), "
                             f"got {self.evidence}")


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal features of 1000 t: (B,) -> (B, dim)."""
    freqs = torch.exp(-math.log(10000) * torch.arange(dim // 2, device=t.device) / (dim // 2))
    a = 1000 * t[:, None] * freqs[None]
    return torch.cat([a.sin(), a.cos()], dim=1)


class ToyVideoFlow(nn.Module):
    """v_theta(x_t, t | c), c = (first frame, text). x_t: (B, T, 3, H, W); t: (B,); returns v: (B, T, 3, H, W)."""

    backend = "toy"

    def __init__(self, cfg: ToyConfig = ToyConfig()):
        super().__init__()
        self.cfg = cfg
        c1, c2, c3, E = cfg.width, 2 * cfg.width, 3 * cfg.width, cfg.emb_dim
        self.tokenizer = Tokenizer(world.VOCAB, cfg.max_words)
        self.text = TextEncoder(len(world.VOCAB), cfg.text_dim, cfg.text_layers, cfg.heads, cfg.max_words)
        self.t_mlp = nn.Sequential(nn.Linear(E, E), nn.SiLU(), nn.Linear(E, E))
        self.text_proj = nn.Linear(cfg.text_dim, E)
        if cfg.ground:
            self.ground = Grounding(cfg.text_dim, cfg.heads)
        self.frame_emb = nn.Parameter(torch.randn(cfg.frames, E) * 0.02)
        # per-frame embedding: where a sprite is at frame f depends on f times what the text says (min(f, k) v),
        # so (text, t, frame) meet in a two-layer MLP rather than a sum
        self.emb_out = nn.Sequential(nn.SiLU(), nn.Linear(2 * E, E), nn.SiLU(), nn.Linear(E, E))
        if cfg.relate:
            self.relate = Relate(cfg.text_dim, cfg.heads)
        if cfg.relate and cfg.relate_text:
            # a second encoder of the same shape, so that teaching Relate to point (train.pointing_loss) can shape
            # how it reads the caption without moving the encodings the U-Net reads D through
            self.relate_text = TextEncoder(len(world.VOCAB), cfg.text_dim, cfg.text_layers, cfg.heads, cfg.max_words)
        # input: x_t, the first frame, (x, y) coordinates [, Relate's offsets and attention maps]
        self.inp = nn.Conv2d(3 + 3 + 2 + 3 * cfg.heads * cfg.relate, c1, 3, padding=1)
        self.d1, self.down1 = ResBlock(c1, c1, E), nn.Conv2d(c1, c1, 3, stride=2, padding=1)
        self.d2, self.down2 = ResBlock(c1, c2, E), nn.Conv2d(c2, c2, 3, stride=2, padding=1)
        self.m1, self.mid_attn, self.m2 = ResBlock(c2, c3, E), BottleneckAttention(c3, cfg.text_dim, cfg.heads), ResBlock(c3, c3, E)
        self.u2, self.u1 = ResBlock(c3 + c2, c2, E), ResBlock(c2 + c1, c1, E)
        # output per frame: a residual (3 channels) and, with cfg.dna, logits of a 3x3 dynamic neighbourhood
        # filter (9 channels); zero-initialised, with the filter's centre tap favoured, so that x1_hat starts as
        # the first frame repeated: a still video
        self.out_norm, self.out = nn.GroupNorm(8, c1), nn.Conv2d(c1, 3 + 9 * cfg.dna, 3, padding=1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        if cfg.evidence:
            self.evidence_gain = nn.Parameter(torch.ones(()))
        self.register_buffer("centre_tap", 6.0 * (torch.arange(9) == 4).float().reshape(1, 1, 9, 1, 1),
                             persistent=False)
        s = torch.linspace(-1, 1, cfg.size)
        self.register_buffer("coords", torch.stack(torch.meshgrid(s, s, indexing="xy")), persistent=False)  # (2, H, W)

    # -- the interface every backend provides -------------------------------------------------------------------
    def condition(self, frame0: np.ndarray | torch.Tensor, texts: list[str]) -> dict:
        """c = (first frame (B, H, W, 3) uint8, prompts) -> what forward() consumes. Raises on unknown words."""
        f0 = torch.as_tensor(np.asarray(frame0)).float().div(127.5).sub(1).permute(0, 3, 1, 2)  # (B, 3, H, W)
        return {"frame0": f0.to(self.coords.device), "ids": self.tokenizer(texts).to(self.coords.device)}

    def check_prompts(self, texts: list[str]) -> None:
        """ValueError naming a prompt condition() would refuse: an unknown word, or more than max_words."""
        self.tokenizer(texts)

    def latent_shape(self) -> tuple:
        return (self.cfg.frames, 3, self.cfg.size, self.cfg.size)

    def relate_attention(self, c: dict, detach_text: bool = False):
        """With cfg.relate: where Relate's heads look in the first frame under c, (attention (B, heads, HW), place
        (B, heads, 2) in [-1, 1] coordinates) -- what train.pointing_loss supervises (with no gradient into the
        U-Net's encoding of the caption if detach_text) and bench.pointing reads."""
        pooled = None if self.cfg.relate_text else self._read(c)[2]   # the U-Net's encoding only where Relate reads it
        return self.relate.attend(self._relate_query(c, pooled, detach_text), c["frame0"], self.coords)

    def _relate_query(self, c: dict, pooled: torch.Tensor | None, detach_text: bool = False) -> torch.Tensor:
        """The caption as Relate reads it (B, dim): its own encoder's mean with cfg.relate_text, else the U-Net's
        pooled encoding (detached if detach_text)."""
        if self.cfg.relate_text:
            return self.relate_text(c["ids"])[2]
        return pooled.detach() if detach_text else pooled

    def _read(self, c: dict):
        """The caption's token encodings (B, L, dim), which to attend to (B, L), and their mean (B, dim)."""
        tokens, mask, pooled = self.text(c["ids"])
        if self.cfg.ground:
            tokens = self.ground(tokens, mask, c["frame0"], self.coords)
            pooled = word_mean(tokens, c["ids"])
        return tokens, mask, pooled

    @staticmethod
    def encode_video(video: np.ndarray) -> torch.Tensor:
        """uint8 (B, F, H, W, 3) -> x_1 (B, T, 3, H, W) in [-1, 1]: the generated frames 1..F-1."""
        return torch.as_tensor(np.asarray(video)[:, 1:]).float().div(127.5).sub(1).permute(0, 1, 4, 2, 3)

    @staticmethod
    def decode(x_1: torch.Tensor, frame0: np.ndarray) -> np.ndarray:
        """x_1 (B, T, 3, H, W) -> uint8 video (B, F, H, W, 3) with the given first frame prepended."""
        gen = ((x_1.detach().float().clamp(-1, 1) + 1) * 127.5).round().byte().permute(0, 1, 3, 4, 2).cpu().numpy()
        return np.concatenate([np.asarray(frame0)[:, None], gen], axis=1)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, c: dict) -> torch.Tensor:
        B, T, C, H, W = x_t.shape
        tokens, mask, pooled = self._read(c)
        e = self.t_mlp(timestep_embedding(t, self.cfg.emb_dim)) + self.text_proj(pooled)      # (B, E)
        emb = self.emb_out(torch.cat([e[:, None].expand(B, T, -1), self.frame_emb[None, :T].expand(B, T, -1)],
                                     dim=-1)).reshape(B * T, -1)                               # (B*T, E)
        f0 = c["frame0"][:, None].expand(B, T, C, H, W)
        h = [x_t, f0, self.coords.expand(B, T, 2, H, W)]
        if self.cfg.relate:
            r = self.relate(self._relate_query(c, pooled), c["frame0"], self.coords)
            h.append(r[:, None].expand(B, T, *r.shape[1:]))
        h = torch.cat(h, dim=2).reshape(B * T, -1, H, W)
        h1 = self.d1(self.inp(h), emb, T)                                   # (B*T, c1, 16, 16)
        h2 = self.d2(self.down1(h1), emb, T)                                # (B*T, c2, 8, 8)
        h3 = self.m1(self.down2(h2), emb, T)                                # (B*T, c3, 4, 4)
        h3 = self.m2(self.mid_attn(h3, tokens, mask, T), emb, T)
        u = self.u2(torch.cat([F_.interpolate(h3, scale_factor=2.0), h2], 1), emb, T)   # (B*T, c2, 8, 8)
        u = self.u1(torch.cat([F_.interpolate(u, scale_factor=2.0), h1], 1), emb, T)    # (B*T, c1, 16, 16)
        out = self.out(F_.silu(self.out_norm(u))).reshape(B, T, -1, H, W)  # (B, T, 3 [+ 9], H, W)
        if self.cfg.dna:
            # dynamic neighbourhood advection (DNA, Finn et al. 2016): frame f is frame f-1 with every pixel a
            # softmax-weighted mix of its 3x3 neighbourhood (the world moves at most 1 px per frame), so moved
            # sprites keep their exact pixels; what enters the view is background (zero after subtracting it)
            bg = c["frame0"].flatten(2).median(dim=2).values[:, :, None, None]                      # (B, 3, 1, 1)
            logits = out[:, :, 3:] + self.centre_tap                                                 # (B, T, 9, H, W)
            prev, frames = c["frame0"] - bg, []
            ev = self.cfg.evidence
            if ev:
                tb = t.reshape(B, 1, 1, 1, 1)
                xe = x_t - tb * bg[:, None]                             # = t (x_1 - bg) + (1 - t) x_0
                inv_var = 1 / (1 - t.reshape(B, 1, 1, 1)).clamp(min=self.cfg.min_one_minus_t) ** 2
            for f in range(T):
                nb = neighbours(prev, 3)                                    # the 3x3 neighbours of every pixel
                lf = logits[:, f]
                if ev:
                    # log N(x_t | t x_1, (1 - t)^2) of each of the 9 candidate moves, up to a constant, summed
                    # over the ev x ev window around the pixel: the Bayes posterior's data term for "which move"
                    ll = (tb * xe[:, f, :, None] * nb - 0.5 * tb ** 2 * nb ** 2).sum(1) * inv_var   # (B, 9, H, W)
                    lf = lf + self.evidence_gain * self._pool_evidence(ll, prev)
                prev = (nb * torch.softmax(lf, dim=1)[:, None]).sum(2)        # (B, 3, H, W)
                frames.append(prev)
            x1_hat = torch.stack(frames, 1) + bg[:, None] + out[:, :, :3]
        else:
            x1_hat = f0 + out[:, :, :3]
        one_minus_t = (1 - t).clamp(min=self.cfg.min_one_minus_t).reshape(B, 1, 1, 1, 1)
        return (x1_hat - x_t) / one_minus_t  # velocity of the straight path through x_t that ends at x1_hat

    def _pool_evidence(self, ll: torch.Tensor, prev: torch.Tensor) -> torch.Tensor:
        """Pool the per-pixel move log-likelihoods ll (B, 9, H, W) over the ev x ev window around each pixel.

        Plain (cfg.evidence_by_colour off): sum over the whole window. Measured on the previous base given the
        error-free D: 26 of its 49 failures were a correct agent move with a nearby still sprite dragged 1-4 px the
        same way, because the still sprite's pixels pooled the moving one's evidence.
        By colour: a sprite pixel p pools only the window pixels q of its own colour in the previous frame, weight
        exp(-|prev_q - prev_p|^2 / 0.25) (~1 for the same colour, < 0.01 for any other: world.COLOURS are > 150/255
        apart), and a background pixel (prev_p ~ 0 after subtracting the background) keeps its own evidence only:
        the pixels of one rigid sprite decide together, and a still neighbour never pools a moving sprite's
        evidence. (Tried and dropped: also pooling over the footprint after the move, with the evidence detached --
        consistency given T fell to 0.14; docs/base.md.)"""
        ev = self.cfg.evidence
        if not self.cfg.evidence_by_colour:
            return F_.avg_pool2d(ll, ev, 1, ev // 2, divisor_override=1)
        B, C, H, W = prev.shape
        win = neighbours(prev, ev)
        same = torch.exp(-((win - prev[:, :, None]) ** 2).sum(1) / 0.25)                     # (B, ev^2, H, W)
        is_bg = torch.exp(-(prev ** 2).sum(1, keepdim=True) / 0.25)                            # (B, 1, H, W)
        w = (1 - is_bg) * same
        w[:, ev * ev // 2] = 1                                   # the window's centre tap: the pixel itself
        if self.cfg.evidence_lead:
            return self._lead_evidence(ll, same, is_bg)
        lw = neighbours(ll, ev)
        return (lw * w[:, None]).sum(2)

    def _lead_evidence(self, ll: torch.Tensor, same: torch.Tensor, is_bg: torch.Tensor) -> torch.Tensor:
        """cfg.evidence_lead: the evidence for a rigid sprite move, and background pixels that follow it.

        Under move m (pixel p takes its colour from p + off_m) a sprite lands on its footprint shifted by -off_m.
        The log-likelihood of that hypothesis is the sum of ll[m] over the landing footprint (a background
        pixel's ll is 0: the background is subtracted): the sprite's own pixels, pooled by colour as above, plus
        the background pixels it moves onto, its leading edge. E_s(m) sums both. Without the leading edge (by
        colour alone) a leading-edge pixel decided on its own noisy evidence, and given T sprites grew (docs/base.md).
        A background pixel p then takes its neighbouring sprite's colour by move m with that sprite's own
        probability of m: logit E_s(m), E_s read at the sprite pixels among p's sources; the moves that leave p
        background share the sprite's remaining mass (their colour is the same, so how they share it does not
        matter). Marginalised so, p turns sprite exactly as often as the sprite moves onto it."""
        B, _, H, W = ll.shape
        ev, k = self.cfg.evidence, torch.arange(9, device=ll.device)

        lead = neighbours(ll * is_bg, 3)[:, k, 8 - k]     # channel m: ll[m] of the pixel q - off_m, if background
        win = neighbours(ll + lead, ev)
        E = (win * ((1 - is_bg) * same)[:, None]).sum(2)     # at a sprite pixel: its sprite's E_s (B, 9, H, W)
        src = neighbours(1 - is_bg, 3)[:, 0]              # (B, 9, H, W): is the source of move m a sprite pixel
        E_s = (neighbours(E, 3) * src[:, None]).sum(2) / src.sum(1, keepdim=True).clamp(min=1e-3)  # the sprite's E_s at p
        rest = (torch.logsumexp(E_s + torch.log((1 - src).clamp(min=1e-6)), 1, keepdim=True)
                - torch.log((1 - src).sum(1, keepdim=True).clamp(min=1e-6)))
        return (1 - is_bg) * E + is_bg * (src * E_s + (1 - src) * rest)


class _Neighbours(torch.autograd.Function):
    """F.unfold's values from shifted slices (fast), and its own backward, F.fold (col2im), so that gradients are
    summed in unfold's order and training is bit for bit what it was with unfold."""

    @staticmethod
    def forward(ctx, x, k):
        B, C, H, W = x.shape
        ctx.k, ctx.hw = k, (H, W)
        xp = F_.pad(x, (k // 2,) * 4)
        return torch.stack([xp[:, :, i:i + H, j:j + W] for i in range(k) for j in range(k)], dim=2)

    @staticmethod
    def backward(ctx, grad):
        B, C, kk, H, W = grad.shape
        return F_.fold(grad.reshape(B, C * kk, H * W), ctx.hw, ctx.k, padding=ctx.k // 2), None


def neighbours(x: torch.Tensor, k: int) -> torch.Tensor:
    """The k x k neighbourhood of every pixel, zero outside the image: (B, C, H, W) -> (B, C, k * k, H, W), tap
    i * k + j holding x at (h + i - k // 2, w + j - k // 2). The values of F.unfold(x, k, padding=k // 2) reshaped,
    made of shifted slices of the padded image: on a 2-core CPU about 3x faster than unfold's im2col, which was 12%
    of a toy forward (the DNA head calls it 3-5 times a frame)."""
    return _Neighbours.apply(x, k)


def moving_pixel_weight(x_1: torch.Tensor, frame0: torch.Tensor, weight: float) -> torch.Tensor:
    """Toy pixel-space latents only: `weight` on the pixels of x_1 (B, T, 3, H, W) that differ from the first frame
    (B, 3, H, W), 1 elsewhere -> (B, T, 1, H, W). Pretraining weighs moving pixels so (train.video_loss); the
    still background is ~99% of the dimensions and would otherwise outweigh the sprite that moves."""
    moving = (x_1 - frame0[:, None]).abs().sum(2, keepdim=True) > 0.05                    # (B, T, 1, H, W)
    return 1 + (weight - 1) * moving.float()


def distinct_condition(model, frame0, texts: list[str]) -> tuple[dict, torch.Tensor]:
    """model.condition over the distinct (first frame, prompt) rows only -> (c, index): c has one row per distinct
    row, in order of first appearance, and row i of the batch is row index[i] of c (`condition_rows`). Alg. 1
    repeats every (image, T, D) group_size times; a real backend's text encoder and VAE then see each once (4
    prompts a step instead of 96 at 4 x 24), and the text encoder's stacked hidden states are held for those
    only. Every value of c must be a tensor with the batch first (all three backends)."""
    frame0 = np.asarray(frame0)
    slot: dict = {}                          # (frame bytes, prompt) -> its row of c, in order of first appearance
    index = [slot.setdefault((f.tobytes(), t), len(slot)) for f, t in zip(frame0, texts)]
    rows = [index.index(j) for j in range(len(slot))]     # the first batch row of each
    return model.condition(frame0[rows], [texts[r] for r in rows]), torch.tensor(index, dtype=torch.long)


def condition_rows(c: dict, index: torch.Tensor) -> dict:
    """The rows `index` of a condition c (every value a tensor with the batch first), as condition() returns them."""
    return {k: v[index.to(v.device)] for k, v in c.items()}


@torch.no_grad()
def seeded_noise(model, n: int, seed: int) -> torch.Tensor:
    """The bench's x_0 ~ N(0, I), (n, *latent_shape): item i's noise depends only on `seed` and i."""
    return torch.randn(n, *model.latent_shape(), generator=torch.Generator().manual_seed(seed))


@torch.no_grad()
def generate(model, frame0: np.ndarray, texts: list[str], steps: int = 10, seed: int = 0, batch: int = 200,
             guidance: float = 1.0):
    """Sample one video per (first frame, prompt), tau ~ p(tau | I, text) of Eq. 1, with the Euler ODE sampler
    (Eq. 2) from seeded noise x_0, `batch` videos a pass (a progress line after each when there are several).
    `guidance` w != 1 samples with classifier-free guidance against the empty caption (flow.guided_field).
    Returns uint8 (B, F, H, W, 3). The noise depends only on `seed` and the item's index, not on `batch`."""
    x_0 = seeded_noise(model, len(texts), seed)
    out, start = [], time.time()
    for i in range(0, len(texts), batch):
        frames, prompts = frame0[i:i + batch], texts[i:i + batch]
        c = model.condition(frames, prompts)
        c_u = model.condition(frames, [""] * len(prompts)) if guidance != 1 else None   # the empty caption
        dev = next(model.parameters()).device
        field = flow.guided_field(lambda x, t: model(x, t, c), lambda x, t: model(x, t, c_u), guidance)
        x_1 = flow.sample_ode(field, x_0[i:i + batch].to(dev), steps)
        out.append(model.decode(x_1, frames))
        done = min(i + batch, len(texts))
        if batch < len(texts):
            spent = time.time() - start
            eta = spent / done * (len(texts) - done)
            print(f"  sampled {done}/{len(texts)} videos, {spent:.0f} s, ETA {eta:.0f} s", flush=True)
    return np.concatenate(out)


# ----------------------------------------------------------------------------------------------------------------
# LoRA: W x + (alpha / r) B A x, B = 0 at init; the Demonstrator is the base with adapters off
# ----------------------------------------------------------------------------------------------------------------


class LoRA(nn.Module):
    """A low-rank update of one layer's weight, W' = W + (alpha / r) B A, with A: (r, fan_in) random and
    B: (out, r) zeros, so the layer equals the base at init. For nn.Linear, y = W x + b + (alpha / r) B (A x); for
    nn.Conv1d / nn.Conv2d (add_lora's convs), B A is reshaped to the kernel (out, in, k...) -- LoCon's form (a k x k
    down-projection to r channels, a 1 x 1 up-projection), merged the same way. For nn.Embedding (add_lora's
    embeddings; the table E is (V, d), so A: (r, d), B: (V, r)), word w's row is E[w] + (alpha / r) B[w] A: each word
    gets an r-dim code B[w] (zeros at init) in a learned basis A (unit normal at init, not 1 / sqrt(d): the rows it
    moves have norm about sqrt(d)), as loralib's and peft's embedding LoRA; the padding row stays zero."""

    def __init__(self, base: nn.Module, rank: int, alpha: float):
        super().__init__()
        self.base, self.scale, self.enabled = base, alpha / rank, True
        fan_in = base.weight[0].numel()
        root = 1.0 if isinstance(base, nn.Embedding) else math.sqrt(fan_in)   # an embedding's basis: unit normal
        dev = base.weight.device                   # drawn on the CPU generator: the same A on every device
        self.lora_A = nn.Parameter((torch.randn(rank, fan_in) / root).to(dev))
        self.lora_B = nn.Parameter(torch.zeros(base.weight.shape[0], rank, device=dev))

    def delta(self) -> torch.Tensor:
        return self.scale * (self.lora_B @ self.lora_A).view_as(self.base.weight)

    def forward(self, x):
        if not self.enabled:
            return self.base(x)
        if isinstance(self.base, nn.Linear):
            return self.base(x) + self.scale * (x @ self.lora_A.T) @ self.lora_B.T
        if isinstance(self.base, nn.Embedding):
            return self.base(x) + self.scale * F_.embedding(x, self.lora_B, self.base.padding_idx) @ self.lora_A
        return self.base._conv_forward(x, self.base.weight + self.delta(), self.base.bias)


def add_lora(model: nn.Module, rank: int = 8, alpha: float = 16.0, target: str = r".*",
             convs: bool = False, embeddings: bool = False) -> list[str]:
    """Wrap every nn.Linear whose qualified name matches `target` in a LoRA; with convs, every nn.Conv1d/nn.Conv2d
    too (the toy U-Net does most of its work in convolutions, where LTX-2's transformer does it in the Linear
    layers that Table 3's LoRA covers); with embeddings, the toy text encoder's word table too (the words its
    captions never used are still random vectors, where LTX-2's Gemma has read every word). Freeze everything
    else. Returns the wrapped names. (Table 3 uses rank 64 / alpha 128 on LTX-2's video attention.)"""
    if hasattr(model, "add_lora"):          # a backend with its own LoRA (LTX-2: peft through diffusers)
        if convs or embeddings:
            raise ValueError("LoRA on convolutions or embeddings is for the toy; a real backend's LoRA follows Table 3")
        return model.add_lora(rank, alpha) if target == r".*" else model.add_lora(rank, alpha, target)
    kinds = (nn.Linear,) + ((nn.Conv1d, nn.Conv2d) if convs else ()) + ((nn.Embedding,) if embeddings else ())
    names = [n for n, m in model.named_modules() if isinstance(m, kinds) and re.fullmatch(target, n)]
    if not names:
        raise ValueError(f"LoRA target {target!r} matches no {' or '.join(k.__name__ for k in kinds)} layer")
    for p in model.parameters():
        p.requires_grad_(False)
    for n in names:
        parent_name, _, child = n.rpartition(".")
        parent = model.get_submodule(parent_name) if parent_name else model
        setattr(parent, child, LoRA(getattr(parent, child), rank, alpha))
    return names


def lora_parameters(model: nn.Module) -> list[nn.Parameter]:
    return [p for n, p in model.named_parameters() if "lora_" in n]


def merge_lora(model: nn.Module) -> nn.Module:
    """A copy of `model` with every LoRA folded into its base weight, W' = W + (alpha / r) B A, as plain layers:
    the same network as the base, so the Executor samples at exactly the base's cost. Adapters that are switched
    off are dropped, not merged."""
    out = copy.deepcopy(model)
    for n, m in list(out.named_modules()):
        if isinstance(m, LoRA):
            if m.enabled:
                m.base.weight.data += m.delta().detach()
            parent_name, _, child = n.rpartition(".")
            setattr(out.get_submodule(parent_name) if parent_name else out, child, m.base)
    return out


def copy_for_adapter(model: nn.Module) -> nn.Module:
    """A second network for another LoRA (Alg. 2's Demonstrator phi, train.py --alternate), made from the base
    before any adapter is added. It owns its modules and shares every tensor of `model` (weights and buffers;
    deepcopy's memo says they are "already copied"), so the LoRA added to it later is its own while the frozen base
    is held once (a copy of LTX-2-19b's transformer would add about 38 GB in bf16). Only adapters train, so the
    shared base stays the base."""
    if lora_parameters(model):
        raise ValueError("copy_for_adapter copies the base: call it before adding adapters, which it would share")
    shared = {id(t): t for t in (*model.parameters(), *model.buffers())}
    return copy.deepcopy(model, shared)


@contextlib.contextmanager
def adapters_disabled(model: nn.Module):
    """Inside this block the model is the Demonstrator: the same base weights with every adapter switched off."""
    layers = [m for m in model.modules() if isinstance(m, LoRA)]
    peft = [m for m in model.modules() if getattr(m, "_hf_peft_config_loaded", False)]   # diffusers + peft
    before = [m.enabled for m in layers]
    for m in layers:
        m.enabled = False
    for m in peft:
        m.disable_adapters()
    try:
        yield model
    finally:
        for m, e in zip(layers, before):
            m.enabled = e
        for m in peft:
            m.enable_adapters()


# ----------------------------------------------------------------------------------------------------------------
# backends and checkpoints
# ----------------------------------------------------------------------------------------------------------------

BACKENDS = {"toy": lambda **kw: ToyVideoFlow(ToyConfig(**kw))}
SHIPPED_BASE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "checkpoints", "base.pt")


def use_cpu(threads: int) -> bool:
    """torch's CPU threads, and glibc's malloc told to keep the memory it frees for the next allocation.

    By default glibc hands freed blocks of a few MB back to the OS, so the next forward's activations land on fresh
    pages and pay a page fault for every 4 KiB of them. On the toy that was most of a forward's time outside the
    convolutions: measured on a 2-core AMD EPYC, 32 videos, the shipped base, median of 15, a forward took 0.25-0.28 s
    without this and 0.18-0.19 s with it, and a 200-video bench evaluation 19.5-22.9 s against 11.6-11.8 s. The
    arithmetic is untouched: the same videos come out, bit for bit. Settings (mallopt(3)): mmap threshold 32 MiB
    (its maximum), trim threshold 1 GiB, top pad 64 MiB. Returns whether they were applied (False off glibc, where
    only the threads are set)."""
    torch.set_num_threads(threads)
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
    return all(libc.mallopt(k, v) == 1 for k, v in ((M_MMAP_THRESHOLD, 32 << 20), (M_TRIM_THRESHOLD, 1 << 30),
                                                    (M_TOP_PAD, 64 << 20)))


def make_model(backend: str = "toy", **config) -> nn.Module:
    """Return a freshly initialised model of the named backend. (LTX-2 is built from its weights or configs
    instead: LTX2Video.from_pretrained / LTX2Video.tiny.)"""
    if backend not in BACKENDS:
        raise ValueError(f"unknown model backend {backend!r}; available: {', '.join(BACKENDS)}")
    return BACKENDS[backend](**config)


def save_checkpoint(model: nn.Module, path: str, meta: dict | None = None) -> None:
    """Write {backend, config, state_dict, meta} atomically (temp file + rename): a crash never leaves half a file."""
    state = {"backend": model.backend, "config": asdict(model.cfg),
             "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}, "meta": meta or {}}
    atomic_save(state, path)


def make_parent(path: str) -> None:
    """Create the folders a file is to be written into (atomic_save; bench.py's pictures)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)


def atomic_save(obj, path: str) -> None:
    """torch.save to a temp file, then rename over `path`: a crash or a kill never leaves half a file, and on
    failure the previous file is untouched and no temp file is left."""
    make_parent(path)
    tmp = f"{path}.tmp{os.getpid()}"
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def save_lora(model: nn.Module, path: str, meta: dict | None = None) -> None:
    """Write only the LoRA weights (and meta), atomically: what a real backend's Executor adds to its base."""
    atomic_save({"lora": {k: v.detach().cpu() for k, v in model.state_dict().items() if "lora_" in k},
                 "meta": meta or {}}, path)


def load_error(e: Exception) -> str:
    """One line on why a file would not load. torch.load(weights_only=True)'s refusal opens with advice to load the
    file as an arbitrary pickle instead; a file we did not write must not be loaded that way, so keep only the cause.
    An empty or cut-off file raises an EOFError with no message."""
    text = str(e)
    if "WeightsUnpickler error:" in text:
        cause = text.split("WeightsUnpickler error:", 1)[1].strip().splitlines()[0]
        text = f"not a file of tensors that torch.save wrote ({cause})"
    if isinstance(e, EOFError) and not text.strip():
        text = "the file is empty or cut short"
    return f"{type(e).__name__}: {(text.splitlines() or [''])[0][:200]}"


def load_lora(model: nn.Module, path: str, add: bool = False) -> dict:
    """Load save_lora's weights into a model that already has the same adapters -- or, with add=True, first give it
    adapters of the rank and alpha the file's run used (train.py's meta) -- a clear error otherwise."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        if add:
            run = state.get("meta", {}).get("args", {})
            add_lora(model, run.get("lora_rank", 8), run.get("lora_alpha", 16.0))
        missing = set(state["lora"]) - set(model.state_dict())
        if missing:
            raise KeyError(f"{len(missing)} LoRA weights have no place in this model, e.g. {sorted(missing)[0]}")
        model.load_state_dict(state["lora"], strict=False)
    except FileNotFoundError:
        raise FileNotFoundError(f"LoRA file {path!r} does not exist") from None
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"LoRA file {path!r} is corrupt or does not match this model: {load_error(e)}") from None
    return state.get("meta", {})


def load_checkpoint(path: str | None = None) -> tuple[nn.Module, dict]:
    """Load a model saved by save_checkpoint (default: the shipped base). Raises a one-line error for a missing,
    corrupt or mismatched file."""
    path = path or SHIPPED_BASE
    if not os.path.isfile(path):
        raise FileNotFoundError(f"checkpoint {path!r} is a directory, not a checkpoint file" if os.path.isdir(path) else
                                f"checkpoint {path!r} does not exist"
                                + (" (rebuild it with: python train.py --stage pretrain)" if path == SHIPPED_BASE else ""))
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        run_state = isinstance(state, dict) and "step" in state and "lora" in state    # train.save_state's file
        if not run_state:
            model = make_model(state["backend"], **state["config"])
            model.load_state_dict(state["state_dict"])
    except Exception as e:  # noqa: BLE001 -- any failure here means the file is not a usable checkpoint
        raise ValueError(f"checkpoint {path!r} is corrupt or does not match this code: {load_error(e)}") from None
    if run_state:
        raise ValueError(f"checkpoint {path!r} is a run's state for train.py --resume, not a model: the run's "
                         f"Executor is the executor_*.pt beside it")
    return model, state.get("meta", {})


# ----------------------------------------------------------------------------------------------------------------
# LTX-2 through diffusers (optional: pip install -r requirements-real.txt), behind the same interface
# ----------------------------------------------------------------------------------------------------------------

def _require(*packages: str) -> None:
    """A clear error naming what is missing, instead of an ImportError deep inside a backend."""
    import importlib.util
    missing = [p for p in packages if importlib.util.find_spec(p) is None]
    if missing:
        raise ImportError(f"the real-model path needs {', '.join(missing)}: pip install -c <(echo torch==2.13.0) "
                          f"-r requirements-real.txt")


def word_tokenizer(words: list[str], specials=("<pad>", "<eos>", "<bos>", "<unk>"), punctuation: bool = False,
                   **named):
    """A word-level tokenizer over `words`, ids in the order `specials` then the other words sorted, built
    in-process (nothing can be downloaded): the text path of the tiny and random real models (Gemma's specials by
    default) and of the VLM judge's (reward.VLMJudge). punctuation: split punctuation off words too, not only at
    spaces. `named`: the special tokens by role (pad_token=..., ...; default: those of `specials` among <pad>,
    <eos>, <bos>, <unk>)."""
    from tokenizers import Tokenizer as HFTokenizer
    from tokenizers import models as tok_models
    from tokenizers import pre_tokenizers
    from transformers import PreTrainedTokenizerFast
    vocab = {w: i for i, w in enumerate(list(specials) + sorted(set(words) - set(specials)))}
    tok = HFTokenizer(tok_models.WordLevel(vocab, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace() if punctuation else pre_tokenizers.WhitespaceSplit()
    named = named or {f"{s[1:-1]}_token": s for s in specials if s in ("<pad>", "<eos>", "<bos>", "<unk>")}
    return PreTrainedTokenizerFast(tokenizer_object=tok, **named)


@contextlib.contextmanager
def built_on(device, dtype):
    """Modules made inside this block are made directly on `device` in `dtype` (a real size's weights never pass
    through float32 on the CPU); the default dtype is restored after it."""
    default = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        with torch.device(device):
            yield
    finally:
        torch.set_default_dtype(default)


def _check_pipeline_dir(path: str, name: str, parts: tuple[str, ...]) -> None:
    """A clear error before any loading when `path` is not a local diffusers directory of `name` holding the
    component folders `parts` (a wrong folder, e.g. the transformer's own, otherwise fails deep in diffusers)."""
    if not os.path.isdir(path):
        raise FileNotFoundError(f"{name} weights not found at {path!r} (a local diffusers directory is needed; "
                                f"nothing is downloaded)")
    missing = [part for part in parts if not os.path.isdir(os.path.join(path, part))]
    if missing:
        raise FileNotFoundError(f"{path!r} is not a diffusers {name} directory: it has no "
                                f"{'folders' if len(missing) > 1 else 'folder'} {', '.join(missing)} (give the "
                                f"folder that holds model_index.json and the components)")


def _load_part(kind, path: str, subfolder: str, dtype, device):
    """One component of a local diffusers directory, in `dtype`, moved to `device` as it is loaded (so a backend's
    __init__, which probes its VAE, runs there)."""
    return kind.from_pretrained(path, subfolder=subfolder, torch_dtype=dtype).to(device)


def _image_batch(frame0, height: int, width: int) -> torch.Tensor:
    """First frames (B, H, W, 3) uint8 -> (B, 3, height, width) in [-1, 1], bilinear: a real backend's VAE input."""
    img = torch.as_tensor(np.asarray(frame0)).float().div(127.5).sub(1).permute(0, 3, 1, 2)
    return F_.interpolate(img, size=(height, width), mode="bilinear", align_corners=False)


def _video_batch(video, frames: int, height: int, width: int) -> torch.Tensor:
    """Videos (B, F, H, W, 3) uint8 -> (B, 3, F, height, width) in [-1, 1], each frame as _image_batch: a real
    backend's VAE input. A video of another frame count than the model's `frames` is a ValueError."""
    v = np.asarray(video)
    if v.ndim != 5 or v.shape[1] != frames or v.shape[-1] != 3:
        raise ValueError(f"videos of shape {v.shape}: this model takes (B, {frames}, H, W, 3), its {frames} frames")
    B, F = v.shape[:2]
    return _image_batch(v.reshape(B * F, *v.shape[2:]), height, width).reshape(B, F, 3, height, width).transpose(1, 2)


@contextlib.contextmanager
def resolution(model, height: int, width: int):
    """Inside this block a real backend conditions, samples and decodes at height x width, then at its own size
    again: Table 3 trains LTX-2 at 384 x 576 and evaluates it at 512 x 768 (train.py --eval_height, --eval_width;
    bench.py --height, --width). The latent grid scales with the pixels, so both must be multiples of the VAE's
    spatial compression, the model's size over its latent grid's; the frame count is unchanged."""
    if getattr(model, "backend", "toy") == "toy":
        raise ValueError("a resolution other than the training one is for a real model: the toy's U-Net is 16 x 16")
    C, F_lat, h, w = model._latent
    sh, sw = model.height // h, model.width // w
    if height < sh or width < sw or height % sh or width % sw:
        raise ValueError(f"{height} x {width} is not a multiple of {sh} x {sw}, the pixels of one latent cell of "
                         f"this VAE")
    old = model.height, model.width, model._latent
    model.height, model.width, model._latent = height, width, (C, F_lat, height // sh, width // sw)
    try:
        yield model
    finally:
        model.height, model.width, model._latent = old


def _with_first_frame(video: torch.Tensor, frame0) -> np.ndarray:
    """A real backend's decoded video (B, 3, F, H, W) in [-1, 1] -> uint8 (B, F, H, W, 3) whose frame 0 is the given
    observation (nearest-resized to H x W), as in the toy's decode: frame 0 is the condition, not generated."""
    video = ((video.clamp(-1, 1) + 1) * 127.5).round().byte().permute(0, 2, 3, 4, 1).cpu().numpy()
    f0 = torch.as_tensor(np.asarray(frame0)).permute(0, 3, 1, 2).float()
    video[:, 0] = F_.interpolate(f0, size=video.shape[2:4], mode="nearest").permute(0, 2, 3, 1).round().byte().numpy()
    return video


def _weights(module: nn.Module) -> list[torch.Tensor]:
    """A module's parameters and buffers, each once (a tied weight appears under two names)."""
    return list({id(t): t for t in [*module.parameters(), *module.buffers()]}.values())


def offload(module: nn.Module) -> None:
    """Keep a frozen module's weights in CPU memory, pinned when there is a GPU (faster to copy from); `visiting`
    brings them to the GPU for one call. For a real model's text encoder (train.py and bench.py --offload_text): it
    runs twice a step (c_E and c_D), and its weights are a third of LTX-2's (Gemma-3-12B: 21.9 GiB of 62.0). Both
    backends' condition() encode inside `visiting`, so nothing else changes."""
    pin = torch.cuda.is_available()
    for t in _weights(module):
        t.data = t.data.cpu().pin_memory() if pin else t.data.cpu()


@contextlib.contextmanager
def visiting(module: nn.Module, device):
    """Inside this block the module's weights are copies on `device`; after it they are their CPU originals again.
    The weights are frozen, so nothing is copied back: the copies are simply dropped (their memory returns to the
    allocator for the next step's activations). Weights already on `device` (not offloaded) are not copied: then
    the block changes nothing."""
    tensors = _weights(module)
    homes = [t.data for t in tensors]
    for t in tensors:
        t.data = t.data.to(device, non_blocking=True)
    try:
        yield module
    finally:
        for t, home in zip(tensors, homes):
            t.data = home


LTX2_VIDEO_ATTENTION = r".*transformer_blocks\.\d+\.attn[12]\.(to_q|to_k|to_v|to_out\.0)"  # Table 3: video attention only


def _peft_lora(transformer, rank: int, alpha: float, target: str) -> list[str]:
    """A real backend's LoRA through peft (diffusers' add_adapter) on the modules matching `target`, B = 0 at init;
    everything else frozen. The adapter weights are kept in float32 even when the base is bfloat16 (as diffusers'
    training scripts do): a bf16 weight near 0.016 moves in steps of 1.2e-4, about one Adam step at Table 3's
    learning rate 2e-4, so updates would be rounded away. peft casts activations to the adapter's dtype and back.
    Returns the adapter parameters' names."""
    from peft import LoraConfig
    transformer.requires_grad_(False)
    transformer.add_adapter(LoraConfig(r=rank, lora_alpha=alpha, target_modules=target, init_lora_weights=True))
    for p in transformer.parameters():
        if p.requires_grad:
            p.data = p.data.float()
    return [n for n, _ in transformer.named_parameters() if "lora_" in n]


class LTX2Video(nn.Module):
    """LTX-2 image-to-video (diffusers' LTX2VideoTransformer3DModel + its video VAE + Gemma3 text encoder and
    LTX-2's text connectors) as v_theta(x_t, t | c) in this repository's convention.

    State: x (B, C, F_lat - 1, h, w), the VAE latents of the frames after the first. The first latent frame is the
    encoded first frame, a clean condition: its tokens enter the transformer with timestep 0 (how diffusers' LTX-2
    image-to-video pipeline conditions). Time: our t (0 noise, 1 data) is diffusers' sigma = 1 - t, scaled by the
    transformer's timestep_scale_multiplier; LTX-2 predicts d x / d sigma = noise - data, so v_ours = -output.
    This is the only place the other convention appears. The transformer requires an audio stream: a video-only
    caller feeds one zero audio token. The text encoder and the VAE are frozen and run without gradients."""

    backend = "ltx2"
    PARTS = ("transformer", "vae", "text_encoder", "tokenizer", "connectors")    # the pipeline folder's components

    def __init__(self, transformer, vae, text_encoder, tokenizer, connectors, frames: int, height: int, width: int,
                 fps: float = 24.0, max_sequence_length: int = 1024):
        super().__init__()
        self.transformer, self.vae, self.text_encoder, self.connectors = transformer, vae, text_encoder, connectors
        self.tokenizer = tokenizer
        self.frames, self.height, self.width, self.fps, self.max_len = frames, height, width, fps, max_sequence_length
        for m in (vae, text_encoder, connectors):
            m.requires_grad_(False).eval()
        with torch.no_grad():   # the latent grid, read off the VAE itself (its compression ratios vary by config)
            zeros = torch.zeros(1, 3, frames, height, width, device=vae.device, dtype=vae.dtype)
            z = vae.encode(zeros).latent_dist.mode()
        self._latent = tuple(z.shape[1:])          # (C, F_lat, h, w)

    # -- construction ------------------------------------------------------------------------------------------
    @classmethod
    def from_pretrained(cls, path: str, frames: int = 121, height: int = 384, width: int = 576, dtype=torch.bfloat16,
                        max_sequence_length: int = 1024, device="cpu"):
        """Load the components from a local diffusers LTX-2 directory (e.g. a snapshot of Lightricks/LTX-2);
        Table 3's training resolution and frame count are the defaults, and diffusers' LTX-2 pipelines' prompt
        length (1024 tokens: a step-by-step description D is long). Each component goes to `device` as it is
        loaded, so the latent-grid probe of __init__ runs there."""
        _require("diffusers", "transformers", "peft")
        _check_pipeline_dir(path, "LTX-2", cls.PARTS)
        from diffusers import AutoencoderKLLTX2Video, LTX2VideoTransformer3DModel
        from diffusers.pipelines.ltx2 import LTX2TextConnectors
        from transformers import AutoModelForCausalLM, AutoTokenizer
        def load(kind, sub):
            return _load_part(kind, path, sub, dtype, device)
        return cls(load(LTX2VideoTransformer3DModel, "transformer"), load(AutoencoderKLLTX2Video, "vae"),
                   load(AutoModelForCausalLM, "text_encoder"),
                   AutoTokenizer.from_pretrained(path, subfolder="tokenizer"),
                   load(LTX2TextConnectors, "connectors"), frames, height, width,
                   max_sequence_length=max_sequence_length)

    @classmethod
    def tiny(cls, words: list[str], frames: int = 5, height: int = 32, width: int = 32, seed: int = 0,
             dtype=torch.float32):
        """A random-weight LTX-2 of the real classes, small enough for CPU tests (configs after diffusers' own
        tests; a word-level tokenizer built in-process over `words`, since nothing can be downloaded). `dtype`:
        the components' dtype (bfloat16 is how from_pretrained loads the real one). Its VAE halves time both ways,
        so it makes videos of `frames` frames, as LTX-2's (8x) makes 121; with those tests' encoder, which halves
        space only, it made 9 of 5 (found at stop 118)."""
        _require("diffusers", "transformers", "tokenizers")
        from diffusers import AutoencoderKLLTX2Video, LTX2VideoTransformer3DModel
        from diffusers.pipelines.ltx2 import LTX2TextConnectors
        from transformers import Gemma3ForCausalLM, Gemma3TextConfig
        tokenizer = word_tokenizer(words)
        torch.manual_seed(seed)
        text = Gemma3ForCausalLM(Gemma3TextConfig(vocab_size=len(tokenizer), hidden_size=32, intermediate_size=64,
                                                  num_hidden_layers=2, num_attention_heads=2, num_key_value_heads=1,
                                                  head_dim=16, max_position_embeddings=64, sliding_window=16))
        connectors = LTX2TextConnectors(
            caption_channels=32, text_proj_in_factor=3, video_connector_num_attention_heads=4,
            video_connector_attention_head_dim=8, video_connector_num_layers=1,
            video_connector_num_learnable_registers=None, audio_connector_num_attention_heads=4,
            audio_connector_attention_head_dim=8, audio_connector_num_layers=1,
            audio_connector_num_learnable_registers=None, connector_rope_base_seq_len=32, rope_theta=10000.0,
            rope_double_precision=False, causal_temporal_positioning=False, rope_type="split")
        transformer = LTX2VideoTransformer3DModel(
            in_channels=4, out_channels=4, patch_size=1, patch_size_t=1, num_attention_heads=2, attention_head_dim=8,
            cross_attention_dim=16, audio_in_channels=4, audio_out_channels=4, audio_num_attention_heads=2,
            audio_attention_head_dim=4, audio_cross_attention_dim=8, num_layers=2, qk_norm="rms_norm_across_heads",
            caption_channels=32, rope_double_precision=False, rope_type="split")
        vae = AutoencoderKLLTX2Video(
            in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(8,), decoder_block_out_channels=(8,),
            layers_per_block=(1,), decoder_layers_per_block=(1, 1), spatio_temporal_scaling=(True,),
            decoder_spatio_temporal_scaling=(True,), decoder_inject_noise=(False, False),
            downsample_type=("spatiotemporal",), upsample_residual=(False,), upsample_factor=(1,),
            timestep_conditioning=False, patch_size=1, patch_size_t=1, encoder_causal=True, decoder_causal=False)
        return cls(transformer.to(dtype), vae.to(dtype), text.to(dtype), tokenizer, connectors.to(dtype), frames,
                   height, width, max_sequence_length=16)

    @classmethod
    def random(cls, words: list[str], frames: int = 121, height: int = 384, width: int = 576, device="cuda",
               dtype=torch.bfloat16, seed: int = 0):
        """LTX-2 at its real size with random weights (train.py --model ltx2-random): what a step costs in seconds
        and memory on a GPU, without the weights, which cannot be downloaded here. Nothing it generates means
        anything. The sizes: diffusers' LTX2VideoTransformer3DModel, LTX2TextConnectors and AutoencoderKLLTX2Video
        at their default configs, which are LTX-2-19B's (48 layers of 32 x 128 heads, caption width 3840; the
        transformer has 18.9B parameters with its audio stream, the connectors 1.4B, the VAE 1.2B; the VAE
        compresses 32x in space and 8x in time, as its conversion script states); the text encoder is Gemma-3-12B's
        text model (48 layers of width 3840, 16 query and 8 key-value heads of 256, MLP 15360, vocabulary 262208;
        11.8B parameters), whose 49 hidden states the connectors read. The tokenizer is word-level over `words`
        (Gemma's cannot be downloaded), so token counts differ from Gemma's; prompts are padded to 1024 all the
        same. Built directly on `device` in `dtype` (no float32 copy on the CPU)."""
        _require("diffusers", "transformers", "tokenizers")
        from diffusers import AutoencoderKLLTX2Video, LTX2VideoTransformer3DModel
        from diffusers.pipelines.ltx2 import LTX2TextConnectors
        from transformers import Gemma3ForCausalLM, Gemma3TextConfig
        tokenizer = word_tokenizer(words)
        torch.manual_seed(seed)
        with built_on(device, dtype):
            text = Gemma3ForCausalLM(Gemma3TextConfig(
                vocab_size=262208, hidden_size=3840, intermediate_size=15360, num_hidden_layers=48,
                num_attention_heads=16, num_key_value_heads=8, head_dim=256, query_pre_attn_scalar=256,
                sliding_window=1024, max_position_embeddings=131072))
            connectors = LTX2TextConnectors()                 # reads Gemma's 48 + 1 hidden states
            transformer = LTX2VideoTransformer3DModel()
            vae = AutoencoderKLLTX2Video(spatial_compression_ratio=32, temporal_compression_ratio=8)
        return cls(transformer, vae, text, tokenizer, connectors, frames, height, width)

    # -- LoRA (peft through diffusers' add_adapter) ---------------------------------------------------------------
    def add_lora(self, rank: int, alpha: float, target: str = LTX2_VIDEO_ATTENTION) -> list[str]:
        """Table 3: LoRA on the video attention projections only; B = 0 at init (the Executor starts as the base)."""
        return _peft_lora(self.transformer, rank, alpha, target)

    # -- the interface every backend provides -------------------------------------------------------------------
    def latent_shape(self) -> tuple:
        C, F_lat, h, w = self._latent
        return (C, F_lat - 1, h, w)

    def _normalise(self, z: torch.Tensor, inverse: bool = False) -> torch.Tensor:
        m = self.vae.latents_mean.view(1, -1, 1, 1, 1).to(z)
        s = self.vae.latents_std.view(1, -1, 1, 1, 1).to(z)
        k = self.vae.config.scaling_factor
        return z * s / k + m if inverse else (z - m) * k / s

    @torch.no_grad()
    def condition(self, frame0, texts: list[str]) -> dict:
        """c = (first frame (B, H, W, 3) uint8, prompts) -> {image latent (B, C, 1, h, w), the connectors' video and
        audio text embeddings, their mask}. The text path mirrors diffusers' LTX-2 pipeline: Gemma hidden states of
        every layer, stacked, left-padded, through the text connectors. A prompt longer than max_sequence_length
        is an error (check_prompts), not cut: a D cut short would be another D. Only the hidden states are read, so
        the language-model head runs on one position (logits_to_keep=1), not on all 1024: at Gemma-3-12B's
        vocabulary of 262208 that head is 2 TFLOPs and a 0.5 GB logit tensor per prompt, for nothing."""
        self.check_prompts(texts)
        dev = next(self.transformer.parameters()).device
        self.tokenizer.padding_side = "left"
        ids = self.tokenizer([t.strip() for t in texts], padding="max_length", max_length=self.max_len,
                             truncation=True, add_special_tokens=True, return_tensors="pt").to(dev)
        with visiting(self.text_encoder, dev):   # offloaded (train.py --offload_text): a copy on dev
            hs = self.text_encoder(input_ids=ids.input_ids, attention_mask=ids.attention_mask,
                                   output_hidden_states=True, logits_to_keep=1).hidden_states
        emb = torch.stack(hs, dim=-1).flatten(2, 3)
        video, audio, mask = self.connectors(emb.to(self.connectors.dtype), ids.attention_mask, padding_side="left")
        return {"image_latent": self._image_latent(frame0), "text": video, "audio_text": audio, "mask": mask}

    def check_prompts(self, texts: list[str]) -> None:
        """ValueError naming the first prompt longer than the text path takes (max_sequence_length tokens); one
        batched tokenizer call, as condition() makes its own."""
        ids = self.tokenizer([t.strip() for t in texts], add_special_tokens=True).input_ids
        for t, n in zip(texts, map(len, ids)):
            if n > self.max_len:
                raise ValueError(f"prompt {t[:60]!r}... has {n} tokens; LTX-2's text path takes at most "
                                 f"{self.max_len} (max_sequence_length)")

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, c: dict) -> torch.Tensor:
        B = x_t.shape[0]
        z = torch.cat([c["image_latent"].to(x_t), x_t], dim=2)                         # (B, C, F_lat, h, w)
        _, C, F, h, w = z.shape
        tokens = z.permute(0, 2, 3, 4, 1).reshape(B, F * h * w, C)                     # patch size 1
        sigma = (1 - t).float() * self.transformer.config.timestep_scale_multiplier    # diffusers' convention
        per_token = sigma[:, None].expand(B, F * h * w).clone()
        per_token[:, :h * w] = 0                                                       # the clean first frame
        dtype = next(self.transformer.parameters()).dtype
        out = self.transformer(
            hidden_states=tokens.to(dtype), audio_hidden_states=torch.zeros(B, 1, self.transformer.config.audio_in_channels,
                                                                            device=x_t.device, dtype=dtype),
            encoder_hidden_states=c["text"].to(dtype), audio_encoder_hidden_states=c["audio_text"].to(dtype),
            timestep=per_token, audio_timestep=sigma, sigma=sigma, encoder_attention_mask=c["mask"],
            audio_encoder_attention_mask=c["mask"], num_frames=F, height=h, width=w, fps=self.fps,
            audio_num_frames=1, return_dict=False)[0]
        v_sigma = out.float().reshape(B, F, h, w, C).permute(0, 4, 1, 2, 3)[:, :, 1:]   # drop the first frame
        return -v_sigma                                                                 # d x / d t = -d x / d sigma

    @torch.no_grad()
    def encode_video(self, video) -> torch.Tensor:
        """Videos (B, F, H, W, 3) uint8 of the model's F frames -> x_1 (B, C, F_lat - 1, h, w): the normalised VAE
        latents of the frames after the first, the state sampling ends in and decode reads (the causal VAE's first
        latent frame is the first frame's, c's image latent). The +SFT baseline's data (train.py --sft_dataset)."""
        dev = next(self.transformer.parameters()).device
        img = _video_batch(video, self.frames, self.height, self.width).to(dev, self.vae.dtype)
        return self._normalise(self.vae.encode(img).latent_dist.mode().float())[:, :, 1:]

    @torch.no_grad()
    def decode(self, x_1: torch.Tensor, frame0) -> np.ndarray:
        """Latents of the generated frames -> uint8 video (B, F, H, W, 3), decoded together with the first frame."""
        z = self._normalise(torch.cat([self._image_latent(frame0), x_1.float()], dim=2), inverse=True)
        video = self.vae.decode(z.to(self.vae.dtype), return_dict=False)[0].float()     # (B, 3, F', H, W)
        return _with_first_frame(video, frame0)

    @torch.no_grad()
    def _image_latent(self, frame0) -> torch.Tensor:
        """First frames (B, H, W, 3) uint8 -> normalised VAE latents (B, C, 1, h, w) at the model's resolution."""
        dev = next(self.transformer.parameters()).device
        img = _image_batch(frame0, self.height, self.width)
        return self._normalise(self.vae.encode(img[:, :, None].to(dev, self.vae.dtype)).latent_dist.mode().float())


# ----------------------------------------------------------------------------------------------------------------
# HunyuanVideo-1.5 image-to-video through diffusers (the paper's second base, Table 1 / Table 3), same interface
# ----------------------------------------------------------------------------------------------------------------

# Table 3: LoRA on the video stream's attention only (the joint blocks' text stream, add_*_proj, stays frozen)
HY15_VIDEO_ATTENTION = r".*transformer_blocks\.\d+\.attn\.(to_q|to_k|to_v|to_out\.0)"


class HunyuanVideo15(nn.Module):
    """HunyuanVideo-1.5 image-to-video (diffusers' HunyuanVideo15Transformer3DModel + its VAE, the Qwen2.5-VL text
    encoder, ByT5 for quoted text, SigLIP for the first frame; its PIL image processor, since the default one needs
    torchvision) as v_theta(x_t, t | c) in this repository's convention.

    State: x (B, C, F_lat, h, w), the VAE latents of *all* latent frames. Unlike LTX-2, HunyuanVideo-1.5 denoises the
    first latent frame too; the first frame conditions it three ways, as in diffusers' image-to-video pipeline: its
    VAE latent as extra input channels at latent frame 0 (zeros elsewhere), a mask channel (1 at frame 0), and SigLIP
    tokens of the image beside the text tokens. Time: our t (0 noise, 1 data) is the scheduler's sigma = 1 - t,
    passed as timestep 1000 sigma; the transformer predicts d x / d sigma = noise - data, so v_ours = -output. This is
    the only place the other convention appears. Text: the pipeline's own encoders (Qwen2.5-VL hidden states three
    layers from the top, after its chat template with the system prompt cropped off; ByT5 zeros unless the prompt
    quotes text). The encoders and the VAE are frozen and run without gradients. The VAE runs one video at a time:
    its mid-block attention mask does not broadcast over a batch (diffusers 0.42: a batch of 2 raises)."""

    backend = "hunyuan15"
    PARTS = ("transformer", "vae", "text_encoder", "tokenizer", "text_encoder_2", "tokenizer_2", "image_encoder",
             "feature_extractor")                                             # the pipeline folder's components

    def __init__(self, transformer, vae, text_encoder, tokenizer, text_encoder_2, tokenizer_2, image_encoder,
                 feature_extractor, frames: int, height: int, width: int, max_sequence_length: int = 1000,
                 crop_start: int = 108, byt5_max_length: int = 256):
        super().__init__()
        self.transformer, self.vae = transformer, vae
        self.text_encoder, self.text_encoder_2 = text_encoder, text_encoder_2
        self.image_encoder, self.feature_extractor = image_encoder, feature_extractor
        self.tokenizer, self.tokenizer_2 = tokenizer, tokenizer_2
        self.frames, self.height, self.width = frames, height, width
        self.max_len, self.crop_start, self.byt5_max_len = max_sequence_length, crop_start, byt5_max_length
        for m in (vae, text_encoder, text_encoder_2, image_encoder):
            m.requires_grad_(False).eval()
        # the VAE in 256-px tiles, as the pipeline's own example sets it (pipe.vae.enable_tiling()): at 121 frames of
        # 480 x 848 one 128-channel activation of its outer blocks is 12.6 GB in bf16. Below 256 px nothing changes.
        vae.enable_tiling()
        with torch.no_grad():   # the latent grid, read off the VAE itself
            zeros = torch.zeros(1, 3, frames, height, width, device=vae.device, dtype=vae.dtype)
            z = vae.encode(zeros).latent_dist.mode()
        self._latent = tuple(z.shape[1:])          # (C, F_lat, h, w)

    # -- construction ------------------------------------------------------------------------------------------
    @classmethod
    def from_pretrained(cls, path: str, frames: int = 121, height: int = 480, width: int = 848, dtype=torch.bfloat16,
                        device="cpu", **text):
        """Load the components from a local diffusers HunyuanVideo-1.5 image-to-video directory (e.g. a snapshot of
        hunyuanvideo-community/HunyuanVideo-1.5-Diffusers-480p_i2v); Table 3's training resolution and frame count
        are the defaults. `text`: __init__'s text settings (max_sequence_length, crop_start, byt5_max_length; by
        default the pipeline's). Each component goes to `device` as it is loaded, so the latent-grid probe runs
        there."""
        _require("diffusers", "transformers", "peft")
        _check_pipeline_dir(path, "HunyuanVideo-1.5", cls.PARTS)
        from diffusers import AutoencoderKLHunyuanVideo15, HunyuanVideo15Transformer3DModel
        from transformers import (AutoTokenizer, ByT5Tokenizer, Qwen2_5_VLTextModel, SiglipImageProcessorPil,
                                  SiglipVisionModel, T5EncoderModel)
        def load(kind, sub):
            return _load_part(kind, path, sub, dtype, device)
        return cls(load(HunyuanVideo15Transformer3DModel, "transformer"), load(AutoencoderKLHunyuanVideo15, "vae"),
                   load(Qwen2_5_VLTextModel, "text_encoder"),
                   AutoTokenizer.from_pretrained(path, subfolder="tokenizer"),
                   load(T5EncoderModel, "text_encoder_2"), ByT5Tokenizer.from_pretrained(path, subfolder="tokenizer_2"),
                   load(SiglipVisionModel, "image_encoder"),
                   SiglipImageProcessorPil.from_pretrained(path, subfolder="feature_extractor"), frames, height, width,
                   **text)

    @staticmethod
    def _word_tokenizer(words: list[str]):
        """models.word_tokenizer with a chat template that keeps only the user turn, so nothing is cropped
        (Qwen2.5-VL's own tokenizer cannot be downloaded here)."""
        tokenizer = word_tokenizer(words, specials=("<pad>", "<eos>", "<unk>"))
        tokenizer.chat_template = ("{% for m in messages %}{% if m['role'] == 'user' %}{{ m['content'] }}{% endif %}"
                                   "{% endfor %}")
        return tokenizer

    @classmethod
    def tiny(cls, words: list[str], frames: int = 5, height: int = 32, width: int = 32, seed: int = 0,
             dtype=torch.float32):
        """A random-weight HunyuanVideo-1.5 of the real classes, small enough for CPU tests (sizes after diffusers'
        own tests; the word-level tokenizer above).
        `dtype`: the components' dtype (bfloat16 is how from_pretrained loads the real one)."""
        _require("diffusers", "transformers", "tokenizers")
        from diffusers import AutoencoderKLHunyuanVideo15, HunyuanVideo15Transformer3DModel
        from transformers import (ByT5Tokenizer, Qwen2_5_VLTextConfig, Qwen2_5_VLTextModel, SiglipImageProcessorPil,
                                  SiglipVisionConfig, SiglipVisionModel, T5Config, T5EncoderModel)
        tokenizer = cls._word_tokenizer(words)
        torch.manual_seed(seed)
        text = Qwen2_5_VLTextModel(Qwen2_5_VLTextConfig(
            vocab_size=len(tokenizer.get_vocab()), hidden_size=16, intermediate_size=16, num_hidden_layers=3,
            num_attention_heads=2, num_key_value_heads=2, rope_theta=1e6,
            rope_scaling={"mrope_section": [1, 1, 2], "rope_type": "default", "type": "default"}))
        byt5 = T5EncoderModel(T5Config(vocab_size=384, d_model=32, d_kv=8, d_ff=32, num_layers=1, num_heads=2))
        siglip = SiglipVisionModel(SiglipVisionConfig(hidden_size=12, intermediate_size=16, num_hidden_layers=1,
                                                      num_attention_heads=2, image_size=32, patch_size=8))
        transformer = HunyuanVideo15Transformer3DModel(
            in_channels=4 + 4 + 1, out_channels=4, num_attention_heads=2, attention_head_dim=8, num_layers=2,
            num_refiner_layers=1, mlp_ratio=2.0, patch_size=1, patch_size_t=1, text_embed_dim=16, text_embed_2_dim=32,
            image_embed_dim=12, rope_axes_dim=(2, 2, 4), target_size=32, task_type="i2v")
        vae = AutoencoderKLHunyuanVideo15(
            in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(16, 16), layers_per_block=1,
            spatial_compression_ratio=4, temporal_compression_ratio=2, downsample_match_channel=False,
            upsample_match_channel=False)
        return cls(transformer.to(dtype), vae.to(dtype), text.to(dtype), tokenizer, byt5.to(dtype), ByT5Tokenizer(),
                   siglip.to(dtype),
                   SiglipImageProcessorPil(size={"height": 32, "width": 32}), frames, height, width,
                   max_sequence_length=16, crop_start=0, byt5_max_length=16)

    @classmethod
    def random(cls, words: list[str], frames: int = 121, height: int = 480, width: int = 848, device="cuda",
               dtype=torch.bfloat16, seed: int = 0):
        """HunyuanVideo-1.5 (480p image-to-video) at its real size with random weights (--model hunyuan15-random):
        what Table 3's second column costs in seconds and memory on a GPU, without the weights. Nothing it generates
        means anything. The sizes: diffusers' HunyuanVideo15Transformer3DModel and AutoencoderKLHunyuanVideo15 at
        their default configs, which are the 480p model's (54 double-stream layers of 16 x 128 heads, 8.33B
        parameters; the VAE 16x in space, 4x in time, 32 channels, 1.26B); the text encoders the widths the
        transformer reads: Qwen2.5-VL-7B's text model (28 layers of width 3584, 28 query and 4 key-value heads, MLP
        18944, vocabulary 152064; 7.07B) and ByT5-small's encoder (12 layers of width 1472, 0.22B); the image
        encoder SigLIP-so400m at 384 px (27 layers of width 1152; 0.43B). At 121 frames of 480 x 848 the state is
        31 latent frames of 30 x 53 (the first frame's latent rides along as channels): 49,290 video tokens a
        forward. The tokenizer is word-level
        (_word_tokenizer), so prompts are fewer tokens than under Qwen's; they are padded to 1000 all the same.
        Built directly on `device` in `dtype`."""
        _require("diffusers", "transformers", "tokenizers")
        from diffusers import AutoencoderKLHunyuanVideo15, HunyuanVideo15Transformer3DModel
        from transformers import (ByT5Tokenizer, Qwen2_5_VLTextConfig, Qwen2_5_VLTextModel, SiglipImageProcessorPil,
                                  SiglipVisionConfig, SiglipVisionModel, T5Config, T5EncoderModel)
        tokenizer = cls._word_tokenizer(words)
        torch.manual_seed(seed)
        with built_on(device, dtype):
            text = Qwen2_5_VLTextModel(Qwen2_5_VLTextConfig(
                vocab_size=152064, hidden_size=3584, intermediate_size=18944, num_hidden_layers=28,
                num_attention_heads=28, num_key_value_heads=4, rope_theta=1e6, max_position_embeddings=128000,
                rope_scaling={"mrope_section": [16, 24, 24], "rope_type": "default", "type": "default"}))
            byt5 = T5EncoderModel(T5Config(vocab_size=384, d_model=1472, d_kv=64, d_ff=3584, num_layers=12,
                                           num_heads=6, feed_forward_proj="gated-gelu"))
            siglip = SiglipVisionModel(SiglipVisionConfig(hidden_size=1152, intermediate_size=4304,
                                                          num_hidden_layers=27, num_attention_heads=16,
                                                          image_size=384, patch_size=14))
            transformer = HunyuanVideo15Transformer3DModel()
            vae = AutoencoderKLHunyuanVideo15()
        return cls(transformer, vae, text, tokenizer, byt5, ByT5Tokenizer(), siglip,
                   SiglipImageProcessorPil(size={"height": 384, "width": 384}), frames, height, width,
                   max_sequence_length=1000, crop_start=0, byt5_max_length=256)

    # -- LoRA (peft through diffusers' add_adapter) ---------------------------------------------------------------
    def add_lora(self, rank: int, alpha: float, target: str = HY15_VIDEO_ATTENTION) -> list[str]:
        """Table 3: LoRA rank 64 / alpha 128; here on the video stream's attention projections (the joint blocks'
        to_q/k/v/out; the text stream's add_*_proj stay frozen), B = 0 at init."""
        return _peft_lora(self.transformer, rank, alpha, target)

    # -- the interface every backend provides -------------------------------------------------------------------
    def latent_shape(self) -> tuple:
        return self._latent

    @torch.no_grad()
    def condition(self, frame0, texts: list[str]) -> dict:
        """c = (first frame (B, H, W, 3) uint8, prompts) -> {first-frame VAE latent (B, C, 1, h, w), SigLIP tokens,
        Qwen2.5-VL and ByT5 embeddings with their masks}, through the pipeline's own encoding functions."""
        from diffusers.pipelines.hunyuan_video1_5.pipeline_hunyuan_video1_5_image2video import \
            HunyuanVideo15ImageToVideoPipeline as Pipe
        from PIL import Image
        self.check_prompts(texts)
        dev = next(self.transformer.parameters()).device
        texts = [t.strip() for t in texts]
        with visiting(self.text_encoder, dev):   # offloaded (train.py --offload_text): a copy on dev
            emb, mask = Pipe._get_mllm_prompt_embeds(self.text_encoder, self.tokenizer, texts, dev,
                                                     tokenizer_max_length=self.max_len, crop_start=self.crop_start)
        emb2, mask2 = Pipe._get_byt5_prompt_embeds(self.tokenizer_2, self.text_encoder_2, texts, dev,
                                                   tokenizer_max_length=self.byt5_max_len)
        images = [Image.fromarray(f).resize((self.width, self.height), Image.BILINEAR) for f in np.asarray(frame0)]
        pix = self.feature_extractor.preprocess(images=images, do_resize=True, return_tensors="pt")
        siglip = self.image_encoder(pixel_values=pix.pixel_values.to(dev, self.image_encoder.dtype)).last_hidden_state
        return {"image_latent": self._image_latent(frame0), "image_embeds": siglip, "text": emb, "mask": mask,
                "text_2": emb2, "mask_2": mask2}

    def check_prompts(self, texts: list[str]) -> None:
        """ValueError naming the first prompt longer than the text path takes: the pipeline's encoding pads the
        chat-formatted prompt to max_sequence_length + crop_start tokens and cuts what is longer, silently (a D cut
        short would be another D). One batched call of the same chat template, uncut."""
        import inspect

        from diffusers.pipelines.hunyuan_video1_5.pipeline_hunyuan_video1_5_image2video import \
            HunyuanVideo15ImageToVideoPipeline as Pipe
        from diffusers.pipelines.hunyuan_video1_5.pipeline_hunyuan_video1_5_image2video import format_text_input
        system = inspect.signature(Pipe._get_mllm_prompt_embeds).parameters["system_message"].default
        ids = self.tokenizer.apply_chat_template(format_text_input([t.strip() for t in texts], system),
                                                 add_generation_prompt=True, tokenize=True, return_dict=True).input_ids
        for t, n in zip(texts, map(len, ids)):
            if n > self.max_len + self.crop_start:
                raise ValueError(f"prompt {t[:60]!r}... has {n - self.crop_start} tokens; HunyuanVideo-1.5's text "
                                 f"path takes at most {self.max_len} (max_sequence_length)")

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, c: dict) -> torch.Tensor:
        B, C, F, h, w = x_t.shape
        cond = torch.zeros_like(x_t)
        cond[:, :, :1] = c["image_latent"].to(x_t)                         # the first frame's latent at frame 0
        mask = torch.zeros(B, 1, F, h, w, dtype=x_t.dtype, device=x_t.device)
        mask[:, :, 0] = 1
        dtype = next(self.transformer.parameters()).dtype
        sigma = (1 - t).float()                                            # the scheduler's convention
        out = self.transformer(
            hidden_states=torch.cat([x_t, cond, mask], dim=1).to(dtype), timestep=(1000 * sigma).to(dtype),
            encoder_hidden_states=c["text"].to(dtype), encoder_attention_mask=c["mask"],
            encoder_hidden_states_2=c["text_2"].to(dtype), encoder_attention_mask_2=c["mask_2"],
            image_embeds=c["image_embeds"].to(dtype), return_dict=False)[0]
        return -out.float()                                                # d x / d t = -d x / d sigma

    @torch.no_grad()
    def encode_video(self, video) -> torch.Tensor:
        """Videos (B, F, H, W, 3) uint8 of the model's F frames -> x_1 (B, C, F_lat, h, w): the scaled VAE latents of
        all latent frames, which this model denoises (frame 0's too), one video at a time as decode runs. The +SFT
        baseline's data (train.py --sft_dataset)."""
        dev = next(self.transformer.parameters()).device
        img = _video_batch(video, self.frames, self.height, self.width).to(dev, self.vae.dtype)
        z = torch.cat([self.vae.encode(img[i:i + 1]).latent_dist.mode() for i in range(len(img))]).float()
        return z * self.vae.config.scaling_factor

    @torch.no_grad()
    def decode(self, x_1: torch.Tensor, frame0) -> np.ndarray:
        """Latents of all frames -> uint8 video (B, F, H, W, 3); frame 0 is replaced by the given observation."""
        z = (x_1.float() / self.vae.config.scaling_factor).to(self.vae.dtype)
        video = torch.cat([self.vae.decode(z[i:i + 1], return_dict=False)[0] for i in range(len(z))]).float()
        return _with_first_frame(video, frame0)                               # (B, 3, F', H, W) in, uint8 out

    @torch.no_grad()
    def _image_latent(self, frame0) -> torch.Tensor:
        """First frames (B, H, W, 3) uint8 -> scaled VAE latents (B, C, 1, h, w) at the model's resolution."""
        dev = next(self.transformer.parameters()).device
        img = _image_batch(frame0, self.height, self.width)
        img = img[:, :, None].to(dev, self.vae.dtype)
        z = torch.cat([self.vae.encode(img[i:i + 1]).latent_dist.mode() for i in range(len(img))]).float()
        return z * self.vae.config.scaling_factor


REAL_MODELS = {"ltx2": LTX2Video, "hunyuan15": HunyuanVideo15}   # --model of train.py and bench.py: the paper's bases
# --model of train.py and bench.py: the toy, the two bases, their tiny random-weight models, both at size (random)
MODEL_CHOICES = ("toy", *REAL_MODELS, *(f"{m}-tiny" for m in REAL_MODELS), *(f"{m}-random" for m in REAL_MODELS))


# what --model / --judge builds at a real size: a GPU is needed
AT_REAL_SIZE = {"ltx2-random": "LTX-2 at its real size (about 67 GB of bf16 weights with its text encoder)",
                "hunyuan15-random": "HunyuanVideo-1.5 at its real size (about 35 GB of bf16 weights with its encoders)",
                "qwen-vl-random": "Qwen3-VL-8B at its real size (17.5 GB of bf16 weights)"}


def cannot_run_here(model: str, judge: str = "toy") -> str | None:
    """Why this machine cannot run --model `model` with --judge `judge` (the one line train.py and bench.py exit
    with), or None."""
    if torch.cuda.is_available():
        return None
    for flag, name in (("--model", model), ("--judge", judge)):
        if name in AT_REAL_SIZE:
            return f"{flag} {name} builds {AT_REAL_SIZE[name]}: it needs a CUDA GPU, and there is none here"
    return None
