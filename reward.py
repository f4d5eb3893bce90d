"""Rule-based judges standing in for the VLM (Sec. 4.1 "Rewards", App. A.7 Figs. 15-17).

They read only the generated frames -- sprites are found by colour, never looked up in the simulator -- and answer
the three WorldTasks-Bench questions:

  judge_task        (Fig. 15) is the instructed task solved by the end?  Looks at the end state only. Like a VLM
                    asked about the outcome, it is satisfied if *some* blob of the agent's colour is where the task
                    wants it -- so a video that spawns a copy of the agent at the goal fools it. That is on purpose:
                    the separate consistency judge is what catches it, and that separation is what lets reward
                    hacking appear and be cured later (paper Fig. 8).
  judge_agent       (Fig. 16) did the addressed agent act, and only it? For "[first-person view]" the camera must
                    move: every sprite shifts by the same vector.
  judge_consistency (Fig. 17) physical consistency: no sprite appearing, vanishing (except across the border) or
                    duplicated, no teleport, no change of size or shape, a stable background.

Each returns a Judgment: a binary decision and a graded score in the role of log p(yes) - log p(no) (positive iff
yes, its size growing with the margin), or yes = score = None when no judgment can be made (a malformed video, or
an agent/target named by the task that the first frame does not show) -- counted as invalid, never a crash, as the
paper discards malformed VLM answers (App. A.4, Tab. 4).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import world
from world import COLOURS, FIRST_PERSON, H, SHAPE_OFFSET, W

SLACK = 0.35        # px of extra tolerance on the task rules for sub-pixel blur in generated frames
MAX_STEP = world.MAX_SPEED + 0.6  # px per frame (Chebyshev) above which a move is a teleport
MIN_BLOB = 3        # px: smaller specks of a colour are ignored as noise
SCORE_CLIP = 6.0    # graded scores live in [-6, 6], like a confident VLM's log-odds
# --judge of train.py and bench.py: these rules, a VLM from a local directory, a tiny random-weight Qwen3-VL for CPU
# checks, Qwen3-VL-8B at its real size with random weights for a GPU's seconds and memory (VLMJudge)
JUDGE_CHOICES = ("toy", "qwen-vl", "qwen-vl-tiny", "qwen-vl-random")


@dataclass
class Judgment:
    yes: bool | None
    score: float | None  # > 0 iff yes; None iff no judgment could be made
    why: str = ""


INVALID = Judgment(None, None, "no judgment possible")


def _graded(margin: float, why: str = "") -> Judgment:
    s = float(np.clip(2.0 * margin, -SCORE_CLIP, SCORE_CLIP))
    if s == 0.0:
        s = -1e-3  # the boundary counts as "no"
    return Judgment(s > 0, s, why)


@dataclass
class Reading:
    """What a judge sees in a video: the sprites of frame 0 and, per frame and colour, the blobs of that colour."""
    sprites: list          # list[world.Sprite] read from frame 0
    blobs: list            # blobs[f][colour] -> list[world.Blob], largest first, each >= MIN_BLOB px
    frames: np.ndarray     # (F, H, W, 3) float32 in [0, 255]

    def sprite(self, name: str):
        return next((s for s in self.sprites if s.name == name), None)

    def centres(self, name: str, f: int, all_blobs: bool = False) -> list[np.ndarray]:
        """Centres (x, y) of the blobs of `name`'s colour in frame f (the largest only unless all_blobs),
        corrected for the shape's centroid offset."""
        s = self.sprite(name)
        off = np.array(SHAPE_OFFSET[s.shape])
        bs = self.blobs[f][s.colour]
        return [np.array([b.cx, b.cy]) - off for b in (bs if all_blobs else bs[:1])]


def read_video(video) -> Reading | None:
    """(F, H, W, 3) uint8 or float in [0, 255] -> Reading, or None if the array is malformed. A video at an integer
    multiple of the world's 16x16 (the toy world through a real backend, e.g. LTX-2 at 32x32) is read block-averaged.
    A Reading passes through, so judge_all reads a video once for its three judges."""
    if isinstance(video, Reading):
        return video
    v = np.asarray(video)
    if v.ndim == 4 and v.shape[3] == 3 and v.shape[1:3] != (H, W) and v.shape[1] % H == 0 and v.shape[2] % W == 0:
        # the toy world rendered at a multiple of its size (a real backend's resolution): block-average it down
        v = v.astype(np.float32).reshape(v.shape[0], H, v.shape[1] // H, W, v.shape[2] // W, 3).mean((2, 4))
    if v.ndim != 4 or v.shape[1:] != (H, W, 3) or v.shape[0] < 2 or not np.isfinite(v).all():
        return None
    v = np.clip(v.astype(np.float32), 0, 255)
    masks = world.colour_masks(v)
    bl = [{c: [b for b in world.blobs(masks[c][f]) if b.size >= MIN_BLOB] for c in COLOURS} for f in range(len(v))]
    return Reading(world.read_sprites(v[0].astype(np.uint8)), bl, v)


def _task_of(task_text: str, r: Reading):
    task = world.parse_task(task_text)  # a malformed prompt is the caller's bug: it raises ValueError
    needed = ([task.agent] if task.agent != FIRST_PERSON else []) + ([task.target] if task.kind != "edge" else [])
    return task if all(r.sprite(n) is not None for n in needed) else None


def judge_task(video, task_text: str) -> Judgment:
    """Fig. 15: is the task solved by the final frame? margin = max over blobs of the agent's (and target's) colour
    of world.task_margin(...) + SLACK; yes iff margin > 0. The agent not visible at the end is a clear no."""
    r = read_video(video)
    task = _task_of(task_text, r) if r is not None else None
    if task is None:
        return INVALID
    last = len(r.frames) - 1
    agents = [None] if task.kind == "centre" else r.centres(task.agent, last, all_blobs=True)
    targets = [None] if task.kind == "edge" else r.centres(task.target, last, all_blobs=True)
    if not agents or not targets:
        return _graded(-SCORE_CLIP, "agent or target not visible in the final frame")
    margin = max(world.task_margin(task.kind, task.target, a, t) for a in agents for t in targets)
    return _graded(margin + SLACK)


def _clipped(b, size0: int) -> bool:
    """A blob cut by the border of the view: touching it and smaller than the whole sprite."""
    return b.touches_border and b.size < 0.8 * size0


def _track(r: Reading, name: str) -> list:
    """Per frame the centre of `name`'s largest blob, or None where it is missing or cut by the border."""
    c = r.sprite(name).colour
    size0 = r.blobs[0][c][0].size
    return [r.centres(name, f)[0] if r.blobs[f][c] and not _clipped(r.blobs[f][c][0], size0) else None
            for f in range(len(r.frames))]


def _max_disp(track: list) -> float:
    return max([float(np.abs(p - track[0]).max()) for p in track[1:] if p is not None], default=0.0)


def judge_agent(video, task_text: str) -> Judgment:
    """Fig. 16: did the addressed agent act, and no one else?
    Sprite agent: d_agent = max_f |c_agent(f) - c_agent(0)|_inf must be >= 1 and every other sprite's d <= 1:
      margin = min(d_agent - 0.75, 1.25 - max_other d).
    First-person view: the camera moves, so all sprites shift together: with s_f the mean displacement over visible
      sprites, margin = min(max_f |s_f|_inf - 0.75, 1.25 - max_f max pairwise |disp_i - disp_j|_inf)."""
    r = read_video(video)
    task = _task_of(task_text, r) if r is not None else None
    if task is None:
        return INVALID
    tracks = {s.name: _track(r, s.name) for s in r.sprites}
    if task.agent != FIRST_PERSON:
        others = [_max_disp(t) for n, t in tracks.items() if n != task.agent]
        return _graded(min(_max_disp(tracks[task.agent]) - 0.75, 1.25 - max(others, default=0.0)))
    shift, spread = 0.0, 0.0
    for f in range(1, len(r.frames)):
        d = [t[f] - t[0] for t in tracks.values() if t[0] is not None and t[f] is not None]
        if not d:
            continue
        d = np.stack(d)
        shift = max(shift, float(np.abs(d.mean(0)).max()))
        spread = max(spread, float(np.abs(d[:, None] - d[None]).max()))
    return _graded(min(shift - 0.75, 1.25 - spread))


def judge_task_reward(video, task_text: str) -> Judgment:
    """Fig. 10, the *training* task reward: yes only if "the target agent performs the required action" (criterion 1,
    judge_agent's rule: it moved and no other sprite did) and "the action is fully completed by the final frame"
    (criterion 2, judge_task's end state). Criterion 3, realism, is left to the separate consistency reward (Sec. 4.1).
    Graded score = min(task score, agent score): positive iff both are yes, as an AND of two log-odds-like margins.
    train.py's --task_reward attributed; the bench keeps Fig. 15's end-state question (judge_task)."""
    r = read_video(video)
    if r is None:
        return INVALID
    jt, ja = judge_task(r, task_text), judge_agent(r, task_text)
    if jt.score is None or ja.score is None:
        return INVALID
    return Judgment(bool(jt.yes and ja.yes), min(jt.score, ja.score), jt.why or ja.why)


CONSISTENCY_FAULTS = ("appears", "duplicate", "vanishes", "reshaped", "teleports", "smear")  # judge_consistency's kinds


def judge_consistency(video, task_text: str | None = None) -> Judgment:
    """Fig. 17: physically consistent? Counts violations (each kind once per sprite), yes iff none:
      appears   -- a blob of a colour that frame 0 does not have
      duplicate -- a second blob of a sprite's colour
      vanishes  -- a sprite missing in a frame although it was last seen more than 1 px from the border
      reshaped  -- a sprite (away from the border) whose pixel count leaves [0.6, 1.6] x its frame-0 count
      teleports -- a centre moving more than MAX_STEP px between consecutive frames
      smear     -- more than 4 pixels in a frame that are neither background nor a palette colour
    score = 3 - 3 * n_violations (so one violation is a confident no). `task_text` is unused: the judgment is
    about the video alone."""
    r = read_video(video)
    if r is None or not r.sprites:
        return INVALID
    seen = {s.colour: s for s in r.sprites}
    size0 = {c: r.blobs[0][c][0].size for c in seen}
    bg = np.median(r.frames[0].reshape(-1, 3), axis=0)
    palette = np.array(list(COLOURS.values()), np.float32)
    bad = set()
    last = {c: r.blobs[0][c][0] for c in seen}  # last blob seen of each sprite
    for f in range(1, len(r.frames)):
        for c in COLOURS:
            bs = r.blobs[f][c]
            if c not in seen:
                if bs:
                    bad.add(("appears", c))
                continue
            if len(bs) > 1:
                bad.add(("duplicate", c))
            prev = r.blobs[f - 1][c]
            if not bs:
                x0, y0, x1, y1 = last[c].box  # leaving the view is fine for a sprite last seen at its border
                if min(x0, y0) > 1 and max(x1, y1) < W - 2:
                    bad.add(("vanishes", c))
                continue
            last[c] = bs[0]
            if not bs[0].touches_border and not 0.6 <= bs[0].size / size0[c] <= 1.6:
                bad.add(("reshaped", c))
            if prev and not _clipped(prev[0], size0[c]) and not _clipped(bs[0], size0[c]):
                if max(abs(bs[0].cx - prev[0].cx), abs(bs[0].cy - prev[0].cy)) > MAX_STEP:
                    bad.add(("teleports", c))
        px = r.frames[f].reshape(-1, 3)
        off_bg = np.abs(px - bg).max(-1) > 40
        off_palette = np.linalg.norm(px[:, None] - palette[None], axis=-1).min(-1) >= world.COLOUR_TOL
        if (off_bg & off_palette).sum() > 4:
            bad.add(("smear", ""))
    why = ", ".join(f"{k} {c}".strip() for k, c in sorted(bad))
    return Judgment(not bad, 3.0 - 3.0 * len(bad), why)


JUDGES = {"task": judge_task, "agent": judge_agent, "consistency": judge_consistency}


def judge_all(video, task_text: str) -> dict[str, Judgment]:
    """All three WorldTasks-Bench judgments of one video (App. A.7)."""
    r = read_video(video)
    return {k: (j(r, task_text) if r is not None else INVALID) for k, j in JUDGES.items()}


# ----------------------------------------------------------------------------------------------------------------
# a real VLM judge (optional: pip install -r requirements-real.txt): Qwen3-VL / Qwen3.5 through transformers
# ----------------------------------------------------------------------------------------------------------------

# The paper's prompts (App. A.2.2 Figs. 10-11 for training rewards, App. A.7 Figs. 15-17 for the bench), verbatim.
TASK_REWARD_PROMPT = (
    "Instruction: {instruction} Target agent: {agent_name} You are given generated video frames in correct temporal "
    "order (frames 0..N-1). You are judging whether a target agent in this temporally ordered video successfully "
    "completes an instruction. If the prompt refers to first-person view, camera perspective, or first-person "
    "perspective, interpret that as referring to the camera movement and viewpoint. Analyze the video carefully and "
    "reason strictly from visible evidence. Do not assume intent. Do not infer unseen events. Do not guess. "
    "Evaluation Criteria 1. Correct Agent Attribution The required action must be performed by the target agent. If "
    "another agent performs the action, the task is NOT successful. 2. Action Progress and Completion The target agent "
    "must clearly complete the instructed action. The instruction must be fully satisfied by the final frame (or "
    "earlier with a stable and persistent completed state). For first-person camera view: no other agent should be "
    "performing the action. 3. Realism and Physical Consistency The outcome must be grounded in objects present in "
    "earlier frames. If video quality is too poor to determine completion reliably, the task is NOT successful. "
    "Decision Rule Answer Yes only if all of the following are true: The target agent performs the required action "
    "The action is fully completed by the final frame The action is physically realistic and consistent If any "
    "condition fails, answer No. Output Format Return exactly one word: Yes or No. Do not include any explanation or "
    "additional text.")
CONSISTENCY_REWARD_PROMPT = (
    "You are given generated video frames in correct temporal order (frames 0..N-1). You are judging whether this "
    "temporally ordered video is successful in terms of visual quality and temporal consistency. Analyze the video "
    "carefully and reason strictly from visible evidence. Do not infer hidden causes. Do not guess missing frames. Do "
    "not speculate beyond what is visible. Evaluation Criteria 1. Visual Quality Frames should be clear, coherent, and "
    "stable. Severe blur, flicker, distortions, broken rendering, or major artifacts mean the video is NOT successful. "
    "2. Temporal Consistency Motion and state changes should be smooth and physically coherent over time. No "
    "teleportation, popping, identity instability, discontinuous motion, or implausible changes. 3. Reliability of "
    "Evidence Judge only from visible evidence in the frames. If frames are too unclear to assess reliably, the video "
    "is NOT successful. 4. Consistency with Initial Frame The video must remain consistent in style and quality with "
    "the first frame. Decision Rule Answer Yes only if all of the following are true: Visual quality is acceptable "
    "overall without severe artifacts Temporal consistency is acceptable without severe continuity failures Frames "
    "are clear enough for reliable judgment If any condition fails, answer No. Output Format Return exactly one word: "
    "Yes or No. Do not include any explanation or additional text.")
BENCH_TASK_PROMPT = (
    "Instruction: {eval_prompt} You are a strict video benchmark judge. Decide whether the video successfully solves "
    "the instructed task by the end. Decision Rule Return 1 only if the requested action is clearly completed. Return "
    "0 if the task is incomplete, incorrect, ambiguous, only partially done, or a different action occurs. Output "
    "Format Reply with only 0 or 1.")
BENCH_AGENT_PROMPT = (
    "Full instruction: {eval_prompt} Expected acting agent: {agent_name} Expected task for that agent: "
    "{agent_task_text} You are a strict video benchmark judge. Decide whether the correct agent is the one performing "
    "the instructed action. Decision Rule Return 1 only if the expected agent clearly performs the task. Return 0 if "
    "another agent performs it, the acting agent is unclear, or the expected agent is absent or incorrect. Output "
    "Format Reply with only 0 or 1.")
BENCH_CONSISTENCY_PROMPT = (
    "You are a strict video benchmark judge. Decide whether the video shows physically realistic execution. Decision "
    "Rule Return 1 only if motion, contact, timing, object interactions, and scene dynamics are physically plausible "
    "and temporally coherent. Return 0 if there is teleportation, impossible motion, severe temporal inconsistency, "
    "broken dynamics, identity drift, or obvious non-physical behavior. Output Format Reply with only 0 or 1.")


def judgment_from_logits(logits: np.ndarray, yes_id: int, no_id: int) -> Judgment:
    """Sec. 4.1 "Rewards": R(x) = log p_VLM('yes' | x) - log p_VLM('no' | x) from the next-token logits. The
    greedy answer must be one of the two tokens; anything else is a malformed answer: no judgment (App. A.4)."""
    logits = np.asarray(logits, np.float64)
    if not np.isfinite(logits).all():
        return Judgment(None, None, "non-finite logits")
    if int(logits.argmax()) not in (yes_id, no_id):
        return Judgment(None, None, "malformed answer")
    logp = logits - (logits.max() + np.log(np.exp(logits - logits.max()).sum()))
    score = float(logp[yes_id] - logp[no_id])
    return Judgment(score > 0, score, "VLM")


def video_frames(video, n: int) -> list:
    """n evenly spaced frames of a video (F, H, W, 3), the first and the last among them, as PIL images: what the
    VLM judge and PickScore see of it."""
    from PIL import Image
    v = np.asarray(video)
    idx = np.linspace(0, len(v) - 1, min(n, len(v))).round().astype(int)
    return [Image.fromarray(np.clip(v[i], 0, 255).astype(np.uint8)) for i in idx]


class VLMJudge:
    """A Qwen3-VL / Qwen3.5 judge through transformers, batched, with the paper's prompts. Frames go in as images
    (Qwen2VLImageProcessorPil: transformers' Qwen3VLProcessor needs torchvision, which this CPU machine cannot
    load), each as <|vision_start|><|image_pad|>...<|vision_end|>, in one user turn before the prompt; the answer is
    read off the logits of the first assistant token. Same method names and Judgment results as the toy judges."""

    def __init__(self, model, tokenizer, image_processor, frames: int = 8, batch: int = 8, device=None):
        self.model, self.tokenizer, self.image_processor = model.eval(), tokenizer, image_processor
        self.frames, self.batch = frames, batch
        self.device = model.device if device is None else device   # where it runs; its weights may live elsewhere
        vocab = tokenizer.get_vocab()
        for tok in ("<|im_start|>", "<|im_end|>", "<|vision_start|>", "<|vision_end|>", "<|image_pad|>",
                    "Yes", "No", "0", "1"):
            if tok not in vocab:
                raise ValueError(f"VLM tokenizer has no single token {tok!r}")
        self.ids = {k: vocab[k] for k in ("Yes", "No", "0", "1", "<|image_pad|>")}

    @classmethod
    def from_pretrained(cls, path: str, dtype=None, **settings):
        """A judge from a local transformers directory of the VLM; `settings`: __init__'s frames and batch."""
        import os

        import models
        models._require("transformers")

        from transformers import AutoModelForImageTextToText, AutoTokenizer, Qwen2VLImageProcessorPil
        if not os.path.isdir(path):
            raise FileNotFoundError(f"VLM weights not found at {path!r} (a local directory is needed; nothing is "
                                    f"downloaded)")
        if not os.path.isfile(os.path.join(path, "config.json")):
            raise FileNotFoundError(f"{path!r} is not a transformers model directory: it has no config.json")
        return cls(AutoModelForImageTextToText.from_pretrained(path, dtype=dtype or "auto"),
                   AutoTokenizer.from_pretrained(path), Qwen2VLImageProcessorPil.from_pretrained(path),
                   **settings)

    @staticmethod
    def _word_tokenizer(words: list[str]):
        """models.word_tokenizer over the prompts' words and `words`, with Qwen's special tokens and "Yes" / "No" /
        "0" / "1" as single tokens (Qwen's own cannot be downloaded here)."""
        import models
        models._require("transformers", "tokenizers")
        from tokenizers import pre_tokenizers
        specials = ["<pad>", "<unk>", "<|im_start|>", "<|im_end|>", "<|vision_start|>", "<|vision_end|>",
                    "<|image_pad|>", "<|video_pad|>"]
        taxonomy = [world.taxonomy_prompt("", key) for key in world.TAXONOMY_QUESTIONS]
        prompt_words = " ".join([TASK_REWARD_PROMPT, CONSISTENCY_REWARD_PROMPT, BENCH_TASK_PROMPT, BENCH_AGENT_PROMPT,
                                 BENCH_CONSISTENCY_PROMPT, *taxonomy, " ".join(words), "user assistant Yes No 0 1"])
        toks = {w for w, _ in pre_tokenizers.Whitespace().pre_tokenize_str(prompt_words)} | {"\n"}
        return models.word_tokenizer(sorted(toks), specials, punctuation=True, pad_token="<pad>", unk_token="<unk>",
                                     additional_special_tokens=specials[2:])

    @staticmethod
    def _special_ids(tokenizer) -> dict:
        vocab = tokenizer.get_vocab()
        return dict(image_token_id=vocab["<|image_pad|>"], video_token_id=vocab["<|video_pad|>"],
                    vision_start_token_id=vocab["<|vision_start|>"], vision_end_token_id=vocab["<|vision_end|>"])

    @classmethod
    def tiny(cls, words: list[str], seed: int = 0):
        """A random-weight Qwen3-VL of the real classes for CPU tests (text hidden 32, 2 layers; vision depth 2)."""
        import torch
        from transformers import Qwen2VLImageProcessorPil, Qwen3VLConfig, Qwen3VLForConditionalGeneration
        tokenizer = cls._word_tokenizer(words)
        torch.manual_seed(seed)
        cfg = Qwen3VLConfig(
            text_config=dict(vocab_size=len(tokenizer.get_vocab()), hidden_size=32, intermediate_size=64,
                             num_hidden_layers=2, num_attention_heads=2, num_key_value_heads=1, head_dim=16,
                             max_position_embeddings=4096,
                             rope_parameters={"rope_type": "default", "rope_theta": 10000.0, "mrope_section": [2, 1, 1],
                                              "mrope_interleaved": True}),
            vision_config=dict(depth=2, hidden_size=32, intermediate_size=64, num_heads=2, patch_size=16,
                               out_hidden_size=32, spatial_merge_size=2, temporal_patch_size=2,
                               num_position_embeddings=64, deepstack_visual_indexes=[1]),
            **cls._special_ids(tokenizer))
        proc = Qwen2VLImageProcessorPil(patch_size=16, temporal_patch_size=2, merge_size=2, min_pixels=32 * 32,
                                        max_pixels=64 * 64)
        return cls(Qwen3VLForConditionalGeneration(cfg), tokenizer, proc, frames=4, batch=4)

    @classmethod
    def random(cls, words: list[str], device="cuda", dtype=None, seed: int = 0):
        """Qwen3-VL-8B-Instruct at its real size with random weights (--judge qwen-vl-random): what judging costs in
        seconds and memory on a GPU beside the video model (Table 3's reward model of the HunyuanVideo-1.5 setting),
        without the weights, which cannot be downloaded here. Its answers mean nothing: random weights answer with
        arbitrary tokens, which the run counts as malformed and skips. The sizes are Qwen3-VL-8B-Instruct's config:
        text 36 layers of width 4096 (32 query and 8 key-value heads of 128, MLP 12288, vocabulary 151936, untied
        output), vision 27 layers of width 1152 (16 heads, MLP 4304, 16-px patches merged 2 x 2, deep-stack from
        layers 8, 16, 24); 8.77B parameters. Its image processor's pixel limits are Qwen3-VL's (65,536 to
        16,777,216), so a 384 x 576 frame is 24 x 36 patches, 216 tokens. The tokenizer is word-level
        (_word_tokenizer), so prompts are fewer tokens than under Qwen's. Built directly on `device` in bf16."""
        import torch
        from transformers import Qwen2VLImageProcessorPil, Qwen3VLConfig, Qwen3VLForConditionalGeneration

        import models
        tokenizer = cls._word_tokenizer(words)
        torch.manual_seed(seed)
        cfg = Qwen3VLConfig(
            text_config=dict(vocab_size=151936, hidden_size=4096, intermediate_size=12288, num_hidden_layers=36,
                             num_attention_heads=32, num_key_value_heads=8, head_dim=128,
                             max_position_embeddings=262144, tie_word_embeddings=False,
                             rope_parameters={"rope_type": "default", "rope_theta": 5000000.0,
                                              "mrope_section": [24, 20, 20], "mrope_interleaved": True}),
            vision_config=dict(depth=27, hidden_size=1152, intermediate_size=4304, num_heads=16, patch_size=16,
                               out_hidden_size=4096, spatial_merge_size=2, temporal_patch_size=2,
                               num_position_embeddings=2304, deepstack_visual_indexes=[8, 16, 24]),
            tie_word_embeddings=False, **cls._special_ids(tokenizer))
        with models.built_on(device, dtype or torch.bfloat16):
            model = Qwen3VLForConditionalGeneration(cfg)
        proc = Qwen2VLImageProcessorPil(patch_size=16, temporal_patch_size=2, merge_size=2, min_pixels=65536,
                                        max_pixels=16777216)
        return cls(model, tokenizer, proc, device=device)

    def offload(self) -> None:
        """Keep the VLM's weights in CPU memory (pinned where there is a GPU) and copy them to self.device each
        time it judges a set of videos, once for all its batches (train.py / bench.py --offload_judge; models.offload): they are not on the GPU during the
        video model's update, where a step peaks."""
        import models
        models.offload(self.model)

    def _frames(self, video) -> list:
        return video_frames(video, self.frames)

    @staticmethod
    def _chat(image_tokens: list[int], prompt: str) -> str:
        """One user turn -- each frame as <|vision_start|> + its image-pad tokens + <|vision_end|>, then the prompt --
        and the opened assistant turn whose first token is the answer."""
        vision = "".join("<|vision_start|>" + "<|image_pad|>" * n + "<|vision_end|>" for n in image_tokens)
        return f"<|im_start|>user\n{vision}{prompt}<|im_end|>\n<|im_start|>assistant\n"

    def logits(self, videos, prompts: list[str]) -> np.ndarray:
        """Next-token logits (N, vocab) after `<|im_start|>assistant`, for each (video, prompt), left-padded batches;
        videos=None: the prompts alone, no image (choose). An offloaded judge (--offload_judge) visits its device once
        for all the batches of the call."""
        import torch

        import models
        out = []
        with torch.no_grad(), models.visiting(self.model, self.device):   # no copy unless offloaded
            dev = self.model.device          # the VLM's GPU when it has one (train.make_judge)
            for s in range(0, len(prompts), self.batch):
                ps = prompts[s:s + self.batch]
                frames = [[] for _ in ps] if videos is None else [self._frames(v) for v in videos[s:s + self.batch]]
                vision, per_image = {}, []      # without videos: no image tokens in any prompt
                if videos is not None:
                    img = self.image_processor(images=[f for fs in frames for f in fs], return_tensors="pt")
                    vision = dict(pixel_values=img["pixel_values"].to(dev, self.model.dtype),
                                  image_grid_thw=img["image_grid_thw"].to(dev))
                    per_image = (img["image_grid_thw"].prod(-1) // self.image_processor.merge_size ** 2).tolist()
                texts, k = [], 0
                for fs, p in zip(frames, ps):
                    texts.append(self._chat(per_image[k:k + len(fs)], p))
                    k += len(fs)
                self.tokenizer.padding_side = "left"
                enc = self.tokenizer(texts, return_tensors="pt", padding=True)
                mm = (enc.input_ids == self.ids["<|image_pad|>"]).long()         # 0 text, 1 image (transformers 5)
                o = self.model(input_ids=enc.input_ids.to(dev), attention_mask=enc.attention_mask.to(dev),
                               mm_token_type_ids=mm.to(dev), logits_to_keep=1, **vision)
                out.append(o.logits[:, -1].float().cpu().numpy())   # the next token's only: a video is 1000s of tokens
        return np.concatenate(out)

    def choose(self, prompts: list[str], n: int) -> list:
        """A text-only multiple-choice question (Sec. 4.1.2's prompt-only taxonomy, world.classify_tasks): the greedy
        first answer token to each prompt read as an option's number 1..n (n <= 9: one digit token each). Returns the
        option's index 0..n-1, or None where that token is no option's number or the logits are not finite (a
        malformed answer)."""
        if not 1 <= n <= 9:
            raise ValueError(f"choose: {n} options; it reads 1 to 9, one digit token each")
        vocab = self.tokenizer.get_vocab()
        digits = [vocab.get(str(k)) for k in range(1, n + 1)]
        if None in digits:
            raise ValueError(f"choose: the VLM's tokenizer has no single token for each number 1..{n}")
        out = []
        for lg in self.logits(None, prompts):
            top = int(lg.argmax()) if np.isfinite(lg).all() else None
            out.append(digits.index(top) if top in digits else None)
        return out

    def yes_no(self, images, prompt: str) -> list:
        """One yes/no question about each still image (the suitability filter, Fig. 12): True / False / None."""
        return [j.yes for j in self._judge([np.asarray(im)[None] for im in images], [prompt] * len(images),
                                           "Yes", "No")]

    def generate(self, images, prompt: str, max_new_tokens: int = 512) -> list[str]:
        """Greedy answers to a prompt about each still image (H, W, 3) -- the task-solution generator, Sec. 4.1.1 --
        or each video (F, H, W, 3), read as the judges read one (its frames in order; world.label_videos)."""
        import torch

        import models
        out = []
        for im in images:
            im = np.asarray(im)
            frames = self._frames(im if im.ndim == 4 else im[None])
            img = self.image_processor(images=frames, return_tensors="pt")
            per_image = (img["image_grid_thw"].prod(-1) // self.image_processor.merge_size ** 2).tolist()
            enc = self.tokenizer([self._chat(per_image, prompt)], return_tensors="pt")
            mm = (enc.input_ids == self.ids["<|image_pad|>"]).long()
            with torch.no_grad(), models.visiting(self.model, self.device):
                dev = self.model.device
                ids = self.model.generate(input_ids=enc.input_ids.to(dev), attention_mask=enc.attention_mask.to(dev),
                                          pixel_values=img["pixel_values"].to(dev, self.model.dtype),
                                          image_grid_thw=img["image_grid_thw"].to(dev), mm_token_type_ids=mm.to(dev),
                                          max_new_tokens=max_new_tokens, do_sample=False)
            out.append(self.tokenizer.decode(ids[0, enc.input_ids.shape[1]:], skip_special_tokens=True))
        return out

    def _judge(self, videos, prompts, yes: str, no: str) -> list[Judgment]:
        return [judgment_from_logits(lg, self.ids[yes], self.ids[no]) for lg in self.logits(videos, prompts)]

    # training rewards (Figs. 10, 11) and bench judgments (Figs. 15-17), batched over videos
    def task_reward(self, videos, tasks: list[str]) -> list[Judgment]:
        ps = [TASK_REWARD_PROMPT.format(instruction=t, agent_name=world.split_task(t)[0]) for t in tasks]
        return self._judge(videos, ps, "Yes", "No")

    def consistency_reward(self, videos) -> list[Judgment]:
        return self._judge(videos, [CONSISTENCY_REWARD_PROMPT] * len(videos), "Yes", "No")

    def bench(self, videos, tasks: list[str]) -> list[dict]:
        parts = [world.split_task(t) for t in tasks]
        task = self._judge(videos, [BENCH_TASK_PROMPT.format(eval_prompt=t) for t in tasks], "1", "0")
        agent = self._judge(videos, [BENCH_AGENT_PROMPT.format(eval_prompt=t, agent_name=a, agent_task_text=i)
                                     for t, (a, i) in zip(tasks, parts)], "1", "0")
        cons = self._judge(videos, [BENCH_CONSISTENCY_PROMPT] * len(videos), "1", "0")
        return [{"task": a, "agent": b, "consistency": c} for a, b, c in zip(task, agent, cons)]


class PickScore:
    """PickScore [35] (Kirstain et al. 2023): Table 3's third training reward of the LTX-2 setting ("multi
    (task/consistency/pick)", weight 0.225; train.py --pick) and Fig. 4's measure of generation quality. A CLIP model
    fine-tuned on human preferences scores an image x against a prompt p as

        s(x, p) = exp(logit_scale) cos(E_image(x), E_text(p)),

    as its authors' code does. A video's score is the mean over `frames` evenly spaced frames, against the task T the
    Executor was given: both ours, the paper says neither. Weights from local directories, nothing downloaded: the
    model (yuvalkirstain/PickScore_v1, a CLIP-H/14) and the processor it was trained with
    (laion/CLIP-ViT-H-14-laion2B-s32B-b79K). Images go through CLIPImageProcessorPil (CLIPProcessor needs
    torchvision, which this CPU machine cannot load)."""

    def __init__(self, model, tokenizer, image_processor, frames: int = 4, batch: int = 16, device=None):
        self.model, self.tokenizer, self.image_processor = model.eval(), tokenizer, image_processor
        self.frames, self.batch = frames, batch
        self.device = model.device if device is None else device

    @classmethod
    def from_pretrained(cls, path: str, processor_path: str = "", **settings):
        """The model from `path` and its tokenizer and image processor from `processor_path` (default: `path`)."""
        import os

        import models
        models._require("transformers")
        from transformers import AutoTokenizer, CLIPImageProcessorPil, CLIPModel
        proc = processor_path or path
        for what, p, file in (("model", path, "config.json"), ("processor", proc, "preprocessor_config.json")):
            if not os.path.isfile(os.path.join(p, file)):
                raise FileNotFoundError(f"PickScore {what} not found at {p!r}: no {file} (a local transformers "
                                        f"directory is needed; nothing is downloaded)")
        return cls(CLIPModel.from_pretrained(path), AutoTokenizer.from_pretrained(proc),
                   CLIPImageProcessorPil.from_pretrained(proc), **settings)

    @classmethod
    def tiny(cls, words: list[str], seed: int = 0):
        """A random-weight CLIPModel of the real class for CPU tests (width 16, one layer each side, 32-px images),
        with a word-level tokenizer that, like CLIP's, wraps the text in start and end tokens (the text embedding is
        read at the end token)."""
        import torch
        from tokenizers.processors import TemplateProcessing
        from transformers import CLIPConfig, CLIPImageProcessorPil, CLIPModel

        import models
        tok = models.word_tokenizer(words, ("<pad>", "<|startoftext|>", "<|endoftext|>", "<unk>"), punctuation=True,
                                    pad_token="<pad>", bos_token="<|startoftext|>", eos_token="<|endoftext|>",
                                    unk_token="<unk>")
        tok.backend_tokenizer.post_processor = TemplateProcessing(
            single="<|startoftext|> $A <|endoftext|>", special_tokens=[("<|startoftext|>", 1), ("<|endoftext|>", 2)])
        torch.manual_seed(seed)
        cfg = CLIPConfig(text_config=dict(vocab_size=len(tok.get_vocab()), hidden_size=16, intermediate_size=32,
                                          num_hidden_layers=1, num_attention_heads=2, max_position_embeddings=77,
                                          bos_token_id=1, eos_token_id=2, pad_token_id=0),
                         vision_config=dict(hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                                            num_attention_heads=2, image_size=32, patch_size=8),
                         projection_dim=8)
        proc = CLIPImageProcessorPil(size={"shortest_edge": 32}, crop_size={"height": 32, "width": 32})
        return cls(CLIPModel(cfg), tok, proc, frames=2, batch=4)

    def __call__(self, videos, prompts: list[str]) -> np.ndarray:
        """s(x, p) averaged over each video's frames: videos (N, F, H, W, 3) uint8, prompts N strings -> (N,)."""
        import torch

        import models
        out = []
        with torch.no_grad(), models.visiting(self.model, self.device):
            dev = self.model.device
            for s in range(0, len(prompts), self.batch):
                vids, ps = videos[s:s + self.batch], prompts[s:s + self.batch]
                frames = [f for v in vids for f in video_frames(v, self.frames)]
                pix = self.image_processor(images=frames, return_tensors="pt").pixel_values
                txt = self.tokenizer(ps, padding=True, truncation=True, max_length=77, return_tensors="pt")
                o = self.model(input_ids=txt.input_ids.to(dev), attention_mask=txt.attention_mask.to(dev),
                               pixel_values=pix.to(dev, self.model.dtype))
                img = o.image_embeds.float().view(len(ps), -1, o.image_embeds.shape[-1])    # unit vectors
                cos = (img * o.text_embeds.float()[:, None]).sum(-1).mean(1)
                out.append((self.model.logit_scale.exp().float() * cos).cpu().numpy())
        return np.concatenate(out) if out else np.zeros(0)
