"""Training entry point: one Args dataclass, one stage per function.

  pretrain -- build the toy base model (the stand-in for downloaded LTX-2 weights, Sec. 3 "Setup"): rectified-flow
              training (App. A.9, flow.flow_matching_loss) of ToyVideoFlow on world videos captioned like the
              detailed description D, with a share of vague captions ("red square moves") and empty captions, as
              real video models see. It never sees a short task T. Writes checkpoints/base.pt (EMA weights).
  distill  -- self-distillation of the Demonstrator (base, adapters off, c_D = (I, D)) into the Executor (base +
              LoRA, c_E = (I, T)), distill.py: --variant off (Eq. 3), on (Eq. 5 = the anchor of Eq. 11 on the
              Executor's own states), dmd (App. A.2.1); sft and paired are SFT baselines. Several variants,
              comma-separated, run one after another from the same base, plotted together (the paper's Fig. 4 left);
              a run of one variant resumes with --resume.
  rl       -- the whole method, Alg. 1 (the default stage): groups of Executor rollouts, the judges (reward.py),
              r_distill (Eq. 9), group-relative advantages of the Eq. 10 reward, L_RL (rl.py: awm | flow-grpo |
              grpo | nft) + beta_d L_anchor (Eq. 12). Alg. 2 with --alternate N. Runs under torchrun, resumes with
              --resume, stops cleanly on non-finite values. --model ltx2|hunyuan15 / --judge qwen-vl / --dataset
              for real models.

  python train.py --stage pretrain --seed 0          # rebuilds checkpoints/base.pt
  python train.py --toy                              # laptop preset: WMSD (Alg. 1) from the shipped base
  python train.py --stage distill --variant off,on,dmd --steps 100   # Fig. 4 left
  python train.py --stage distill --variant off,on --executor_prompt instruction   # the positive control (docs/results.md)
  python train.py --toy --executor_prompt oracle_instruction --steps 300   # the second control: c_E right, D not
  python train.py --stage distill --variant off,on --executor_prompt goal --init B.pt  # third: T as a goal caption
  torchrun --nproc_per_node 2 train.py --toy --threads 1             # the same run on 2 processes
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import hashlib
import importlib.util
import json
import os
import random
import sys
import time
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import torch
import torch.distributed as dist
from PIL import Image

import bench
import distill
import flow
import models
import reward
import rl
import world

REAL_MODELS = models.REAL_MODELS   # --model: the paper's two bases


@dataclass
class Args:
    stage: str = "rl"
    """which stage to run: pretrain | distill | rl (the whole method, Alg. 1)"""
    toy: bool = False
    """the laptop preset: the toy world and model on CPU (the values below are already the toy's)"""
    seed: int = 0
    """one seed for python, numpy and torch; a rerun with the same seed gives the same numbers on CPU"""
    threads: int = 2
    """torch CPU threads"""
    out: str = ""
    """where the trained checkpoint goes (default: checkpoints/base.pt for pretrain, <run_dir>/executor_<variant>.pt
    for distill, <run_dir>/executor_<trainer>.pt for rl); one file, so one --variant"""
    run_dir: str = "runs"
    """metrics (JSON lines), plots and GIFs go here"""
    # ---- pretrain ----
    pretrain_steps: int = 2500
    """pretraining optimizer steps (2500 for the shipped base; its predecessors had 2000, docs/base.md)"""
    pretrain_batch: int = 32
    """pretraining videos per step"""
    pretrain_lr: float = 1e-3
    """pretraining AdamW learning rate (linear warm-up over 100 steps, cosine decay to 10%)"""
    weight_decay: float = 0.0
    """pretraining AdamW weight decay"""
    ema: float = 0.995
    """EMA decay of the weights that are saved"""
    motion_weight: float = 10.0
    """loss weight on pixels that differ from the first frame (moving sprites, pans); others weigh 1. Motion is
    1-3% of the pixels and is otherwise learned last (../shared/notes/toy-prototype.md)"""
    p_vague: float = 0.15
    """share of captions that name the mover but not the motion"""
    p_empty: float = 0.10
    """share of empty captions"""
    p_goal: float = 0.0
    """share of goal-directed clips with goal captions ("red square moves to the blue circle"); 0.25 was tried
    and broke D-following (docs/base.md), so it is off"""
    p_task_words: float = 0.0
    """share of pretraining captions said in T's words: top/bottom for up/down, first-person view for the camera
    (world.in_task_words). 0 in the shipped base, which never reads 16 of T's 29 words (docs/given-t.md, "Task by
    kind")"""
    log_every: int = 50
    """steps between progress lines"""
    width: int = 32
    """U-Net channels at full resolution"""
    evidence: int = 5
    """toy base: add the log-likelihood of x_t under each DNA move, summed over this window, to the filter logits
    (models.ToyConfig; 0 = off)"""
    evidence_by_colour: bool = True
    """toy base: pool a sprite pixel's evidence only over its own sprite (same colour), a background pixel's not at
    all, instead of the whole window (models.ToyVideoFlow._pool_evidence); --no-evidence_by_colour: plain window"""
    evidence_lead: bool = True
    """toy base, with --evidence_by_colour: a sprite's move evidence also counts the background pixels it moves onto,
    and those pixels follow the sprite with its own probability of the move (models.ToyVideoFlow._lead_evidence);
    without it, given T the sprites grew (docs/base.md); --no-evidence_lead: the previous base"""
    ground: bool = False
    """toy base: text tokens point into the first frame before the U-Net reads them (models.Grounding); tried with
    --p_goal 0.25, it did not help (docs/given-t.md), so it is off"""
    relate: bool = False
    """toy base: every pixel gets its offset to where the caption points in the first frame (models.Relate); tried
    with --p_goal 0.25, its heads did not learn to point (docs/given-t.md), so it is off"""
    relate_text: bool = False
    """toy base with --relate: Relate reads the caption through its own text encoder, so --point_weight trains that
    encoder and leaves the U-Net's alone (models.ToyConfig.relate_text). Measured (docs/given-t.md, "Relate with its own
    text encoder"): the base still follows D and its heads find the agent and target given T in about 40% of
    pairs, but the Executor given T learns no better from it"""
    point_weight: float = 0.0
    """toy base with --relate: weight of pointing_loss in pretraining, which teaches Relate's head 0 to look at the
    mover the caption names and head 1 at the sprite a goal caption names as target, else the mover (0 = off: the
    heads learn only from the video loss, and did not learn to point, docs/given-t.md)"""
    point_goal_only: bool = False
    """toy base with --point_weight: supervise head 1 only where a goal caption names a target, not at the mover
    otherwise (docs/given-t.md's form (a): with the shared text encoder it broke D-following; with --relate_text,
    base (f), the heads point given T 0.69 / 0.65 and it follows D, but given T it solves 0.315 and WMSD gains
    nothing)"""
    # ---- distill (and later RL) ----
    init: str = ""
    """base checkpoint the Executor starts from (default: the shipped checkpoints/base.pt)"""
    variant: str = "on"
    """objective(s), comma-separated: off (Eq. 3) | on (Eqs. 5/11) | dmd (App. A.2.1) | sft (the +SFT baseline,
    Sec. 4.4) | paired (SFT on the simulator's correct videos of the training tasks, labelled T: the paired
    task-execution supervision the paper avoids needing -- a reference, not WMSD)"""
    executor_prompt: str = "task"
    """the Executor's text: task (T, the paper's c_E) | instruction (the toy VLM's D rewritten in the task's
    "[agent]: instruction" form, world.instruction_form: D's information in a form the base never saw -- a positive
    control for the objectives, docs/results.md; distill variants off, on, dmd and paired (its videos labelled with
    it), and the rl stage; the judges still judge T) |
    oracle_instruction (the error-free D in that form: docs/results.md's second control, where c_E carries the right
    motion and the Demonstrator's D is still wrong at the toy VLM's error rate) | oracle_direction (the same without
    its duration, world.direction_form: "[red square]: move left 2 up 1" -- the partial control, docs/results.md: c_E
    carries part of the Demonstrator's decision) | goal (T's words, and no more, as
    the goal caption pretraining showed -- world.goal_caption: "red square moves to the blue circle"; the third
    control, docs/given-t.md: does the Executor fail given T for T's information or for its unseen form?)"""
    steps: int = 100
    """Executor (LoRA) optimizer steps per variant"""
    batch: int = 32
    """(image, T, D) triples per step (--variant sft: labelled videos)"""
    sft_dataset: str = ""
    """--variant sft on a real model (--model ltx2 / hunyuan15, -tiny, -random), Table 1's +SFT row: a JSONL file of
    labelled videos, one {"video": FILE, "task": T} a line. FILE (relative: to the JSONL file's folder) is a .npy
    array uint8 (F, H, W, 3) of the model's F frames, an mp4, mov, mkv, webm or avi file (through PyAV, in
    requirements-real.txt), or an animated GIF, PNG or WebP; its frames are resized to the model's size. The toy's
    SFT videos are the world's (world.sft_batch)"""
    lr: float = 1e-3
    """Adam learning rate of the LoRA weights (Table 3 uses 2e-4 on LTX-2; the toy's LoRA is tiny)"""
    lora_rank: int = 8
    """LoRA rank (Table 3: 64 on LTX-2)"""
    lora_alpha: float = 16.0
    """LoRA alpha (Table 3: 128 = 2 x rank)"""
    lora_convs: bool = False
    """LoRA on the toy U-Net's convolutions too, not only its Linear layers (models.add_lora; docs/given-t.md, "What the
    Executor can learn given T")"""
    lora_embeddings: bool = False
    """LoRA on the toy text encoder's word table too (models.add_lora): lets the Executor move the rows of the words
    that no pretraining caption used, still random vectors (docs/given-t.md, "Task by kind")"""
    executor_weights: str = "lora"
    """what of the Executor trains: lora (the paper's, Table 3: a LoRA on the base; the Demonstrator is the base, the
    same network with adapters off) | all (toy only: every weight of the base; the Demonstrator a frozen copy of it,
    docs/given-t.md, "Every weight of the Executor"). --lr is then every weight's (pretraining's peak is 1e-3)"""
    executor_init: str = ""
    """distill and rl stages, --executor_weights all: a saved Executor (a distill stage's
    <run_dir>/executor_<variant>.pt) whose weights the Executor starts from, while the Demonstrator stays the base
    (--init): Fig. 1's two stages, distillation and then RL; in the distill stage, more distillation from a distilled
    Executor (with a fresh optimizer: not the same run made longer). Step 0 of the curve scores that Executor"""
    sample_steps: int = 10
    """Euler steps of every rollout, in training and evaluation (--train_steps sets training's apart)"""
    train_steps: int = 0
    """Euler steps of the training rollouts (distill and rl stages); 0: --sample_steps, as in evaluation. Sec. 4.6:
    the paper trains with fewer steps than it evaluates with, for speed, and finds that the poorer training samples
    make reward hacking likelier (docs/results.md, "Fewer sampling steps in training")"""
    error_rate: float = 0.3
    """the toy VLM's share of wrong descriptions D (bench.DEFAULT_ERROR_RATE)"""
    train_pairs: int = 512
    """(image, T, D) training pairs drawn from the toy VLM, on scenes disjoint from the bench"""
    train_arrangements: int = 1
    """M > 1: the training pairs are --train_pairs / M tasks, each on M places of its scene's sprites (its own scene
    and M - 1 others where T is feasible, world.arrangements), D each place's error-free description (--error_rate
    0): T's words alone no longer tell the motion, the frame must (docs/given-t.md). 1: each task on one scene"""
    train_crowded: bool = False
    """train on scenes of 5 sprites (world.CROWDED_SPRITES) disjoint from the crowded bench's (bench.py --crowded),
    not on the bench's 2-4: the toy's Table 2, where SFT trains on the target domain's data and WMSD does not
    (docs/results.md); the training pairs, and the sft variant's plain videos. Evaluations stay on the bench unless
    --eval_crowded"""
    eval_crowded: bool = False
    """evaluate on the crowded bench (world.crowded_pairs, bench.py --crowded: 200 pairs on 5-sprite scenes) instead
    of the bench: every evaluation of the run, the base's and the Demonstrator's included, and the GIF's pairs.
    Beside --train_crowded, the curve of the toy's Table 2 target"""
    eval_every: int = 0
    """steps between bench evaluations; the last step is always evaluated (in the rl stage by the final evaluation,
    of the saved Executor). 0: the stage's default, 10 in distill (Fig. 4 left's curve) and 25 in rl, where at 10
    the 200-pair evaluations were a fifth of a 2-core toy run (README, "The laptop commands")"""
    eval_n: int = 200
    """bench pairs per evaluation"""
    eval_cache: str = ""
    """a folder where the base's own evaluations (given T; the Demonstrator given D) are kept and reused by later
    runs from the same base file with the same evaluation settings (the report's runs share one); empty: off"""
    keep_executors: bool = False
    """also save the Executor each evaluation before the last scores, beside the final one (--out) as its name with
    _step<N> (<run_dir>/executor_on_step250.pt), the run's settings and the step in its meta: a curve's points for
    bench.py (whose --trained_pairs reads them), and what an interrupted run keeps. Trains the same weights"""
    loss_power: float = 1.0
    """weight the velocity loss by (1 - t)^p. p = 0 is the plain loss, which for a model predicting the clean video
    puts weight 1/(1-t)^2 on its error near t = 1 and learns motion (decided at small t) slowly; p = 2 weights the
    clean-video error evenly and leaves the last, detail-making steps blurry; p = 1 sits between"""
    state_window: str = ""
    """"LO,HI": the Demonstrator's terms -- Eq. 3 (off), Eqs. 5/11 (on, and the rl stage's anchor) -- take their
    states only from the sampler's grid times LO <= t_k < HI (docs/given-t.md: where the motion is decided); empty: all t.
    r_distill (Eq. 9) still integrates over the whole trajectory"""
    distill_motion_weight: float = 1.0
    """Eq. 4's squared error in the Demonstrator's terms (Eqs. 3, 5, 9, 11) with the pixels the Demonstrator moves
    weighed this many times the others, as pretraining weighs moving pixels (--motion_weight); 1 = the paper's plain
    norm. Ours, toy model only (distill.squared_error; docs/results.md)"""
    off_judged: bool = False
    """--variant off: Eq. 3 on the Demonstrator rollouts the judges pass only (task judged against T, and consistency:
    judge_rollouts' solved), the rest of the batch dropped -- a step whose every rollout fails makes no update. Ours,
    not the paper's: a rejection filter against the toy VLM's wrong D's, which need no oracle (docs/given-t.md)"""
    off_pool: int = 0
    """--variant off: Eq. 3's Demonstrator trajectories rolled out once, before the first step, N of them from fresh
    noise for each training pair (with --off_judged judged then, the failures dropped), and each step's batch drawn
    from that pool instead of rolled out anew: for the fixed Demonstrator the same kind of states and targets, at a
    step's cost without the sampler's rollout. 0: a fresh rollout every step (the paper's). Ours (train.py's
    demonstrator_pool)"""
    model: str = "toy"
    """the video model: toy (ToyVideoFlow from --init) | ltx2 (LTX-2 from a local diffusers directory,
    --model_path; pip install -r requirements-real.txt) | hunyuan15 (HunyuanVideo-1.5 image-to-video, likewise) |
    ltx2-tiny, hunyuan15-tiny (random-weight models of the real classes, for checking the real path on a CPU) |
    ltx2-random, hunyuan15-random (the real sizes with random weights, on a GPU: a step's seconds and memory,
    nothing more)"""
    toy_gpu: bool = False
    """the toy model on the GPU (the rl stage; real models go to the GPU whenever there is one). Off by default: every
    toy number in the README was measured on CPUs, and floating-point sums differ between devices. For runs too big
    for a laptop, e.g. Table 3's 32 tasks x 24 rollouts a step"""
    model_path: str = ""
    """--model ltx2 / hunyuan15: a local diffusers directory of the model (transformer/, vae/, text_encoder/, ...)"""
    dataset: str = ""
    """a WorldTasks JSONL file (image, task, description per line; world.make_worldtasks writes one) to train on
    instead of the toy VLM's pairs"""
    eval_height: int = 0
    """a real model's bench evaluations at this height and --eval_width (Table 3's evaluation resolution: LTX-2 trains
    at 384 x 576 and is evaluated at 512 x 768; models.resolution); 0: the training size"""
    eval_width: int = 0
    """see --eval_height"""
    eval_dataset: str = ""
    """a WorldTasks JSONL file whose first --eval_n rows are the bench (the paper's WorldTasks-Bench: 200 held-out
    image-task pairs), judged with the bench prompts; empty: the toy bench. No row may also be in --dataset"""
    judge: str = "toy"
    """the judge of rewards and bench: toy (reward.py's rule-based judges) | qwen-vl (a Qwen3-VL / Qwen3.5 from
    --judge_path, the paper's prompts, log p(yes) - log p(no)) | qwen-vl-tiny (random-weight Qwen3-VL, for checks) |
    qwen-vl-random (Qwen3-VL-8B's real sizes, random weights, on a GPU: a judgment's seconds and memory)"""
    judge_path: str = ""
    """--judge qwen-vl: a local transformers directory of the VLM"""
    pick: str = "none"
    """PickScore (reward.PickScore), recorded in each evaluation (Fig. 4's quality measure) and, with --lambda_pick >
    0, Table 3's third reward of the LTX-2 setting ("multi (task/consistency/pick)"): none | pickscore (from
    --pick_path) | pickscore-tiny (random weights of the real class, for checks). With --lambda_pick 0 it only
    measures: the rollouts are not scored by it"""
    pick_path: str = ""
    """--pick pickscore: a local transformers directory of PickScore (yuvalkirstain/PickScore_v1), and of its tokenizer
    and image processor unless --pick_processor_path gives them"""
    pick_processor_path: str = ""
    """--pick pickscore: a local directory of PickScore's tokenizer and image processor
    (laion/CLIP-ViT-H-14-laion2B-s32B-b79K); empty: --pick_path"""
    lambda_pick: float = 0.0
    """Eq. 10 with Table 3's third reward: weight of PickScore (the LTX-2 column: 0.225); needs --pick. 0: with --pick,
    PickScore only measures, at each evaluation"""
    offload_judge: bool = False
    """a VLM judge: keep its weights in CPU memory and copy them to the GPU each time it judges a set of videos, so that they
    are not on the GPU during the update, where a step peaks (Qwen3-VL-8B: 16.3 GiB); the same judgments"""
    # ---- rl (Alg. 1: the whole method) ----
    trainer: str = "awm"
    """policy-gradient objective L_RL (rl.py): awm (the paper's main setting) | flow-grpo | grpo | nft"""
    group_size: int = 8
    """G: rollouts per (image, task) whose rewards are compared (paper: 24)"""
    tasks_per_step: int = 4
    """distinct (image, T, D) per step; rollouts per step = tasks_per_step x group_size"""
    micro_batch: int = 0
    """rl stage: the most rollouts (or bench videos) one forward or backward pass holds in each process; 0 = all of
    the process's at once. The update is the same: gradients are summed over micro-batches, each weighted by its
    share and drawing what the whole batch draws. For a real model whose step does not fit in memory at once"""
    grad_checkpoint: bool = False
    """real models: recompute the transformer's activations in the backward pass instead of keeping them (diffusers'
    gradient checkpointing): less memory for more compute, the same gradients"""
    offload_text: bool = False
    """real models: keep the text encoder in CPU memory and copy it to the GPU only to encode prompts (twice a
    step): less GPU memory (LTX-2's Gemma-3-12B is 21.9 GiB) for a copy each time, the same numbers"""
    sampler: str = "ode"
    """rollout sampler for awm / nft: ode | sde (flow-grpo and grpo always use the SDE: they need its log-probs)"""
    noise_level: float = 0.7
    """a in the SDE's sigma_t = a sqrt((1 - t) / t) (Flow-GRPO's 0.7)"""
    lambda_task: float = 1.0
    """Eq. 10: weight of the task judge's graded score"""
    task_reward: str = "end_state"
    """the toy judges' r_task: end_state (Fig. 15's question, is the task solved by the end: reward.judge_task; every
    README result unless it says otherwise) | attributed (Fig. 10's training prompt: solved by the end *and* by the
    addressed agent alone: reward.judge_task_reward). A VLM judge always asks Fig. 10's prompt"""
    lambda_distill: float = 1.0
    """Eq. 10: weight of r_distill (Eq. 9); 0 = no distillation reward"""
    distill_reward: str = "trajectory"
    """r_distill in the advantages: trajectory (Eq. 9, the main text's: one per rollout) | per_step (App. A.3: each
    transition of the sampler credited with Eq. 9's terms after it, distill.distill_reward_to_go, and advantages per
    step; for the per-transition trainers grpo and flow-grpo, and awm re-noising on the grid with exp_first)"""
    lambda_cons: float = 1.0
    """weight of the consistency judge's score (Sec. 4.1 "Rewards"); 0 = without it (paper Fig. 8)"""
    beta_d: float = 1.0
    """Eq. 12: weight of the Demonstrator anchor (Eq. 11); 0 = RL without the anchor. With every reward weight 0 the
    rl stage trains the anchor alone (train.anchor_only: Fig. 4 left's on-policy variant, on any --model)"""
    demonstrator: str = "base"
    """who gives v_theta'(x_t, t | c_D) in Eqs. 9 and 11: base (the fixed base, adapters off: the paper's main
    setting) | executor (the Executor's own current weights under c_D: App. A.3's shared weights, which the paper
    found unstable; on the toy every seed collapsed to a still video by iteration 220, given T sooner; docs/results.md)"""
    adv_agg: str = "gdpo"
    """advantage aggregation over the rewards: gdpo (Tab. 3) | sum"""
    adv_clip: float = 5.0
    """advantages are clipped to [-adv_clip, adv_clip] (0: not clipped); also nft's A_max (5 when 0)"""
    inner_epochs: int = 1
    """optimizer steps on each batch of rollouts (Tab. 3: 1)"""
    executor_ema: float = 0.0
    """Tab. 3's EMA of the Executor's trained weights: ema <- d ema + (1 - d) theta every --executor_ema_every
    steps, with decay d (the LTX-2 column: 0.96 every step; --executor_ema_schedule power warms it up). Evaluations,
    the GIF and the saved (and kept) Executor use the averaged weights; rollouts and updates the trained ones, as
    Flow-GRPO does. The rl stage, and the distill stage too (its every variant; the average starts where the Executor
    does). 0 = off (the toy's default, and every README result unless it says otherwise)"""
    executor_ema_every: int = 1
    """steps between updates of --executor_ema (Tab. 3: 1 for LTX-2, 4 for HunyuanVideo-1.5)"""
    executor_ema_schedule: str = "constant"
    """the decay of --executor_ema over its updates (Tab. 3: constant for LTX-2, power for HunyuanVideo-1.5):
    constant | power (a warm-up: see executor_ema_decay)"""
    clip_range: float = 0.2
    """PPO clip of the ratio (flow-grpo, awm); binds only when inner_epochs > 1"""
    kl_beta: float = 0.0
    """KL to the base under c_E (flow-grpo, awm); the anchor plays this part in WMSD"""
    awm_timesteps: int = 2
    """awm / nft: re-noising times per final sample"""
    awm_times: str = "uniform"
    """awm / nft: where those times lie: uniform (in [0, 0.98)) | grid (the sampler's own step times)"""
    awm_weighting: str = "ghuber"
    """awm time weighting: uniform | t | huber | ghuber (Tab. 3)"""
    ghuber_power: float = 0.5
    """power of the generalised Huber weighting"""
    awm_ratio: str = "exp_first"
    """awm ratio: exp_first (Tab. 3) | sum_first"""
    nft_beta: float = 1.0
    """DiffusionNFT's implicit-policy step"""
    alternate: int = 0
    """Alg. 2: every N-th iteration is a Demonstrator round (RL on a Demonstrator phi of its own, anchored to the
    base); 0 = the Demonstrator stays the fixed base (Alg. 1, the main WMSD setting)"""
    beta_phi: float = 1.0
    """Alg. 2: weight of the Demonstrator's anchor to the base, L_base"""
    save_every: int = 10
    """rl stage, and a distill run of one --variant: steps between resumable state checkpoints (<run_dir>/state.pt,
    atomic)"""
    resume: bool = False
    """continue the rl or one-variant distill run in --run_dir from its state.pt (same settings; --steps may grow)"""
    executor_update: str = "wmsd"
    """Executor rounds: wmsd (L_RL + beta_d L_anchor, Eq. 12) | off (off-policy distillation from the Demonstrator,
    Eq. 3; with --alternate, the paper's "off-policy distillation + RL on the teacher" setting)"""


# The stages that read each flag (any flag not named here is read by all three; --stage and --toy by none). parse_args
# refuses a flag set, to anything but its default, for a stage that does not read it: a flag silently ignored makes a
# run other than the one asked for (`--stage rl --width 64` would train the shipped width-32 base's LoRA).
# tests/test_train.py checks this table against the code each stage runs.
READ_BY = {
    **dict.fromkeys(("pretrain_steps", "pretrain_batch", "pretrain_lr", "weight_decay", "ema", "p_vague", "p_empty",
                     "p_goal", "p_task_words", "width", "evidence", "evidence_by_colour", "evidence_lead", "ground",
                     "relate", "relate_text", "point_weight", "point_goal_only"), ("pretrain",)),
    **dict.fromkeys(("motion_weight", "loss_power", "log_every"), ("pretrain", "distill")),  # distill: the SFT rows
    **dict.fromkeys(("variant", "batch", "sft_dataset", "off_judged", "off_pool"), ("distill",)),
    **dict.fromkeys(("init", "executor_prompt", "steps", "lr", "executor_weights", "lora_rank", "lora_alpha",
                     "lora_convs", "lora_embeddings", "sample_steps", "train_steps", "error_rate", "train_pairs",
                     "train_arrangements", "train_crowded", "eval_crowded", "eval_every", "eval_n", "eval_cache",
                     "keep_executors", "executor_init", "executor_ema", "executor_ema_every", "executor_ema_schedule",
                     "state_window", "distill_motion_weight",
                     "model", "eval_dataset", "judge", "judge_path", "micro_batch", "eval_height", "eval_width",
                     "model_path", "offload_judge", "grad_checkpoint", "offload_text"),
                    ("distill", "rl")),
    **dict.fromkeys(("toy_gpu", "dataset", "trainer", "group_size", "tasks_per_step", "sampler", "noise_level",
                     "lambda_task", "task_reward", "lambda_distill", "distill_reward", "lambda_cons", "beta_d",
                     "demonstrator", "adv_agg", "adv_clip", "inner_epochs",
                     "clip_range", "kl_beta", "awm_timesteps", "awm_times", "awm_weighting",
                     "ghuber_power", "awm_ratio", "nft_beta", "alternate", "beta_phi",
                     "executor_update", "pick", "pick_path", "pick_processor_path", "lambda_pick"),
                    ("rl",)),
    **dict.fromkeys(("save_every", "resume"), ("distill", "rl")),
    "stage": (), "toy": (),
}
# The rl stage's trainer flags and the trainers (rl.OBJECTIVES) that read them through rl_config; set for another
# --trainer they are refused as READ_BY's are (tests/test_train.py checks this against rl.py).
TRAINER_READS = {**dict.fromkeys(("clip_range", "kl_beta"), ("flow-grpo", "awm")),
                 **dict.fromkeys(("awm_timesteps", "awm_times"), ("awm", "nft")),
                 **dict.fromkeys(("awm_weighting", "awm_ratio", "ghuber_power"), ("awm",)),
                 "nft_beta": ("nft",)}


def reward_weights(args: Args) -> tuple:
    """The Eq. 10 weights (--lambda_*) an rl run reads: WMSD's Executor rounds weigh all three; Alg. 2's Demonstrator
    rounds weigh r_task and r_cons (beside off-policy Executor rounds, Fig. 5 (iii), they are all that is weighed);
    off-policy Executor rounds alone judge and weigh nothing. Either kind of round weighs PickScore too with --pick."""
    pick = ("lambda_pick",) if args.pick != "none" else ()      # Table 3's PickScore, where --pick gives one
    if args.executor_update == "wmsd":
        return "lambda_task", "lambda_distill", "lambda_cons", *pick
    return ("lambda_task", "lambda_cons", *pick) if args.alternate else ()


def anchor_only(args: Args) -> bool:
    """Eq. 12 with no reward weighed (every --lambda_* 0) and the anchor on (--beta_d > 0): the Executor's rounds
    train beta_d L_anchor (Eq. 11) alone, on its own states -- Fig. 4 left's on-policy variant without r_distill, what
    `--stage distill --variant on` trains on the toy, and the way to run it on a real model, whose distill stage runs
    the +SFT baseline alone. The judges still judge each rollout, for the log."""
    return (args.executor_update == "wmsd" and not args.alternate and args.beta_d > 0
            and args.lambda_task == args.lambda_cons == args.lambda_distill == args.lambda_pick == 0)


def unread_flags(args: Args) -> list:
    """The flags set (to anything but their default) that nothing in this run would read, each as (name, what
    reads it, what was chosen instead): a flag of another --stage (READ_BY) or --trainer (TRAINER_READS), or one
    that tunes a setting this run does not use. parse_args refuses them."""
    default, variants = Args(), set(args.variant.split(","))
    off = args.stage == "rl" and args.executor_update == "off"    # Fig. 5 (iii): the Executor rounds are Eq. 3 only
    judged = bool(reward_weights(args))     # without Alg. 2's Demonstrator rounds, off-policy rounds judge nothing
    sde = judged and (args.sampler == "sde" or args.trainer in rl.NEEDS_SDE)
    no_video_loss = args.stage == "distill" and not variants & {"sft", "paired"}    # the SFT variants have one
    no_rollouts = args.stage == "distill" and variants <= {"sft", "paired"}         # the others roll out
    candidates = [  # (flag, what reads it, what this run chose instead, whether that leaves the flag unread)
        *((name, "--stage " + " and ".join(stages), f"--stage {args.stage}", args.stage not in stages)
          for name, stages in READ_BY.items() if stages),
        *((name, "--trainer " + " and ".join(trainers), f"--trainer {args.trainer}", args.trainer not in trainers)
          for name, trainers in TRAINER_READS.items()),
        ("ghuber_power", "--awm_weighting ghuber", f"--awm_weighting {args.awm_weighting}",
         args.awm_weighting != "ghuber"),
        ("model_path", "--model ltx2 or hunyuan15 (real weights)", f"--model {args.model}",
         args.model not in REAL_MODELS),
        ("judge_path", "--judge qwen-vl (real weights)", f"--judge {args.judge}", args.judge != "qwen-vl"),
        *((name, "--executor_weights lora", "--executor_weights all", args.executor_weights == "all")
          for name in ("lora_rank", "lora_alpha", "lora_convs", "lora_embeddings")),
        *((name, "--pick pickscore (real weights)", f"--pick {args.pick}", args.pick != "pickscore")
          for name in ("pick_path", "pick_processor_path")),
        ("noise_level", "SDE rollouts (--sampler sde, or --trainer flow-grpo or grpo)", "ODE rollouts", not sde),
        ("beta_phi", "--alternate N (Alg. 2's Demonstrator rounds)", "--alternate 0", not args.alternate),
        ("executor_ema_every", "--executor_ema > 0", "no --executor_ema", not args.executor_ema),
        ("save_every", "the rl stage or a distill run of one --variant (its state.pt)", f"--variant {args.variant}",
         args.stage == "distill" and "," in args.variant),
        *((name, "--stage pretrain, or --variant sft or paired (their video loss)", f"--variant {args.variant}",
           no_video_loss) for name in ("motion_weight", "loss_power")),
        ("train_steps", "the rl stage and --variant off, on or dmd (their rollouts)", f"--variant {args.variant}",
         no_rollouts),
        *((name, "the toy's video loss (--model toy)", f"--model {args.model}", args.model != "toy")
          for name in ("motion_weight", "loss_power")),
        *((name, "--model toy (the toy VLM's pairs) in the distill stage", f"--model {args.model}",
           args.stage == "distill" and args.model != "toy")
          for name in ("train_pairs", "train_arrangements", "train_crowded")),
        *((name, "RL rounds (--executor_update wmsd, or --alternate N's Demonstrator rounds)",
           "--executor_update off without --alternate", not judged)
          for name in ("trainer", *TRAINER_READS, "sampler", "lambda_task", "lambda_cons", "task_reward", "adv_agg",
                       "adv_clip", "lambda_pick")),
        *((name, "--executor_update wmsd (Eq. 12's rounds)", "--executor_update off", off)
          for name in ("lambda_distill", "distill_reward", "beta_d", "inner_epochs")),
        ("task_reward", "--lambda_task > 0 (r_task's weight)", "--lambda_task 0", args.lambda_task == 0),
        *((name, "L_RL (a --lambda_* > 0)", "every --lambda_* 0 (the anchor alone)", anchor_only(args))
          for name in ("trainer", *TRAINER_READS, "adv_agg", "adv_clip"))]
    return [(name, readers, chosen) for name, readers, chosen, unread in candidates
            if unread and getattr(args, name) != getattr(default, name)]


def train_steps(args: Args) -> int:
    """Euler steps of a training rollout: --train_steps, or --sample_steps (evaluation's) when it is 0."""
    return args.train_steps or args.sample_steps


def state_window(args: Args) -> tuple | None:
    """--state_window "LO,HI" -> (LO, HI) with 0 <= LO < HI <= 1, or None when empty (all t)."""
    if not args.state_window:
        return None
    parts = args.state_window.split(",")
    try:
        lo, hi = (float(x) for x in parts)
    except ValueError:
        raise ValueError(f"expected two numbers LO,HI, got {args.state_window!r}") from None
    if not 0 <= lo < hi <= 1:
        raise ValueError(f"expected 0 <= LO < HI <= 1, got {args.state_window!r}")
    return lo, hi


def _draws_demonstrator_states(args: Args) -> bool:
    """Whether the run evaluates Eq. 3 or Eqs. 5/11 on sampled states: the distill stage's off/on variants, or the
    rl stage with the anchor on (--beta_d > 0) or the off-policy Executor update."""
    return ((args.stage == "distill" and bool({"off", "on"} & set(args.variant.split(","))))
            or (args.stage == "rl" and (args.beta_d > 0 or args.executor_update == "off")))


def parse_args(argv=None) -> Args:
    """Build the command line from the dataclass: every field is a --flag with its docstring as help."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    docs = _field_docs(Args)
    for f in dataclasses.fields(Args):
        if f.type in ("bool", bool):
            p.add_argument(f"--{f.name}", action=argparse.BooleanOptionalAction, default=f.default, help=docs.get(f.name))
        else:
            typ = {"int": int, "float": float, "str": str}[f.type if isinstance(f.type, str) else f.type.__name__]
            p.add_argument(f"--{f.name}", type=typ, default=f.default, help=docs.get(f.name),
                           choices=list(STAGES) if f.name == "stage" else None)
    args = Args(**vars(p.parse_args(argv)))
    for f in dataclasses.fields(Args):      # nan passes every range check below (each comparison is False)
        if f.type in ("float", float) and not np.isfinite(getattr(args, f.name)):
            p.error(f"--{f.name} must be a finite number, got {getattr(args, f.name)}")
    ignored = unread_flags(args)       # refused below, after the checks that say more
    if args.seed < 0:
        p.error(f"--seed must be >= 0 (numpy's generators take no negative seed), got {args.seed}")
    if args.eval_every == 0:
        args.eval_every = 25 if args.stage == "rl" else 10
    for name in ("steps", "batch", "log_every", "threads", "width", "pretrain_steps", "pretrain_batch", "lora_rank",
                 "sample_steps", "train_pairs", "train_arrangements", "eval_every", "eval_n", "tasks_per_step",
                 "inner_epochs", "awm_timesteps", "save_every", "executor_ema_every"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.train_steps < 0:
        p.error(f"--train_steps must be >= 1, or 0 for --sample_steps, got {args.train_steps}")
    variants = args.variant.split(",")
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        p.error(f"--variant: unknown {', '.join(map(repr, bad))}; choose from {', '.join(VARIANTS)}")
    twice = sorted({v for v in variants if variants.count(v) > 1})
    if twice:
        p.error(f"--variant: {', '.join(map(repr, twice))} given twice (a variant's run would overwrite its first "
                "checkpoint and curve)")
    if args.out and args.stage == "distill" and "," in args.variant:
        p.error("--out names one checkpoint: with several --variant each Executor goes to "
                "<run_dir>/executor_<variant>.pt")
    if args.group_size < 2:
        p.error(f"--group_size must be >= 2 (advantages compare rollouts within a group), got {args.group_size}")
    for name, allowed in (("trainer", TRAINERS), ("sampler", ("ode", "sde")), ("adv_agg", ("gdpo", "sum")),
                          ("awm_weighting", ("uniform", "t", "huber", "ghuber")),
                          ("awm_ratio", ("exp_first", "sum_first")), ("awm_times", ("uniform", "grid")),
                          ("executor_update", ("wmsd", "off")), ("executor_weights", ("lora", "all")),
                          ("distill_reward", ("trajectory", "per_step")), ("demonstrator", ("base", "executor")),
                          ("executor_ema_schedule", ("constant", "power")),
                          ("task_reward", TOY_TASK_REWARDS),
                          ("model", models.MODEL_CHOICES),
                          ("judge", reward.JUDGE_CHOICES), ("pick", PICK_CHOICES)):
        if getattr(args, name) not in allowed:
            p.error(f"--{name}: unknown {getattr(args, name)!r}; choose from {', '.join(allowed)}")
    for name in ("beta_d", "beta_phi", "lambda_task", "lambda_distill", "lambda_cons", "lambda_pick", "kl_beta",
                 "adv_clip", "clip_range", "alternate", "weight_decay", "loss_power", "noise_level"):
        if getattr(args, name) < 0:
            p.error(f"--{name} must be >= 0, got {getattr(args, name)}")
    for name in ("lr", "pretrain_lr", "lora_alpha", "ghuber_power", "nft_beta", "motion_weight",
                 "distill_motion_weight"):
        if getattr(args, name) <= 0:
            p.error(f"--{name} must be > 0, got {getattr(args, name)}")
    weighed = reward_weights(args)    # none: unread_flags refuses any weight set
    if weighed and sum(getattr(args, name) for name in weighed) == 0 and not anchor_only(args):
        p.error(f"at least one of {', '.join('--' + name for name in weighed)} must be > 0"
                + (" (Alg. 2's Demonstrator rounds weigh no r_distill)" if args.executor_update != "wmsd" else
                   "" if args.alternate else ", or --beta_d (the anchor alone, Eq. 11)"))
    if args.noise_level <= 0 and (args.sampler == "sde" or args.trainer in rl.NEEDS_SDE):
        p.error("--noise_level must be > 0 for SDE rollouts")
    if not 0 <= args.error_rate <= 1:
        p.error("--error_rate must lie in [0, 1]")
    if args.train_pairs % args.train_arrangements:
        p.error(f"--train_pairs {args.train_pairs} is not a whole number of tasks on --train_arrangements "
                f"{args.train_arrangements} places each")
    if args.train_arrangements > 1 and args.error_rate:
        p.error("--train_arrangements > 1 gives each place the error-free D of T's plan there: give --error_rate 0")
    if args.model in REAL_MODELS and not args.model_path:
        p.error(f"--model {args.model} needs --model_path (a local diffusers {REAL_MODELS[args.model].__name__} "
                f"directory; nothing is downloaded)")
    if models.cannot_run_here(args.model, args.judge):
        p.error(models.cannot_run_here(args.model, args.judge))
    if args.model != "toy" and (args.lora_convs or args.lora_embeddings):
        p.error("--lora_convs and --lora_embeddings are for the toy; a real backend's LoRA covers its video attention "
                "(Table 3)")
    if args.executor_weights == "all" and (args.model != "toy" or args.alternate or "dmd" in variants):
        p.error("--executor_weights all trains every weight of the toy beside a frozen copy, its Demonstrator: toy "
                "model only, and neither --alternate (Alg. 2's phi shares the base's weights) nor --variant dmd (its "
                "fake score and real score are the base's adapters)")
    if args.executor_init and args.executor_weights != "all":
        p.error("--executor_init starts every weight of the Executor from a saved one: it needs --executor_weights all "
                "(a saved LoRA Executor of the toy has its adapter folded into the base's weights)")
    if args.judge != "toy" and args.task_reward != "end_state":
        p.error("--task_reward picks among the toy judges; a VLM judge always asks Fig. 10's task prompt")
    if args.judge == "qwen-vl" and not args.judge_path:
        p.error("--judge qwen-vl needs --judge_path (a local directory of the VLM; nothing is downloaded)")
    if (args.eval_height > 0) != (args.eval_width > 0) or min(args.eval_height, args.eval_width) < 0:
        p.error(f"--eval_height and --eval_width go together, both > 0, got {args.eval_height} x {args.eval_width}")
    if args.eval_height and args.model == "toy":
        p.error("--eval_height and --eval_width are for a real model: the toy's U-Net is 16 x 16")
    if args.pick == "pickscore" and not args.pick_path:
        p.error("--pick pickscore needs --pick_path (a local directory of PickScore; nothing is downloaded)")
    if args.lambda_pick > 0 and args.pick == "none":
        p.error("--lambda_pick weighs PickScore: it needs --pick pickscore (or pickscore-tiny)")
    if (args.model != "toy" or args.judge != "toy") and args.stage == "distill" and (
            args.model == "toy" or args.variant != "sft" or not args.sft_dataset):
        p.error("in the distill stage a real model (and a VLM judge, beside one) runs the +SFT baseline alone: "
                "--variant sft --sft_dataset FILE; Fig. 4 left's variants run in the rl stage (README)")
    if args.sft_dataset and args.model == "toy":
        p.error("--sft_dataset holds a real model's SFT videos; the toy's are the world's (world.sft_batch)")
    if args.state_window:
        try:
            window = state_window(args)
        except ValueError as e:
            p.error(f"--state_window: {e}")
        S = train_steps(args)
        if not any(window[0] <= k / S < window[1] for k in range(S)):
            p.error(f"--state_window {args.state_window}: no grid time k/{S} lies in [LO, HI)")
        if not _draws_demonstrator_states(args):
            p.error("--state_window picks the states of Eq. 3 and Eqs. 5/11: it needs --stage distill with --variant "
                    "off or on, or --stage rl with the anchor on (--beta_d > 0) or --executor_update off")
    per_transition = args.trainer in rl.NEEDS_SDE or (args.trainer == "awm" and args.awm_times == "grid"
                                                      and args.awm_ratio == "exp_first")
    if args.distill_reward == "per_step" and (args.stage != "rl" or not per_transition or args.lambda_distill == 0):
        p.error(f"--distill_reward per_step gives each transition its own advantage: it needs --stage rl, "
                f"--lambda_distill > 0 and a trainer with a term per transition: {' or '.join(rl.NEEDS_SDE)}, or awm "
                f"with --awm_times grid and --awm_ratio exp_first")
    if args.demonstrator == "executor" and (args.stage != "rl" or args.alternate):
        p.error("--demonstrator executor is the rl stage's Alg. 1 with a moving Demonstrator; --alternate trains a "
                "Demonstrator of its own")
    if args.distill_motion_weight != 1 and args.model != "toy":
        p.error("--distill_motion_weight weighs pixels against the first frame: toy model only")
    if args.distill_motion_weight != 1 and not (_draws_demonstrator_states(args)
                                                or (args.stage == "rl" and args.lambda_distill > 0)):
        p.error("--distill_motion_weight weighs Eq. 4 in Eqs. 3, 5, 9, 11: it needs --stage distill with --variant "
                "off or on, or --stage rl with the anchor or r_distill on")
    if args.off_judged and (args.stage != "distill" or "off" not in args.variant.split(",")):
        p.error("--off_judged filters Eq. 3's Demonstrator rollouts: it needs --stage distill with --variant off")
    if args.off_pool < 0:
        p.error(f"--off_pool must be >= 0 (0: a fresh Demonstrator rollout every step), got {args.off_pool}")
    if args.off_pool and (args.stage != "distill" or "off" not in args.variant.split(",")):
        p.error("--off_pool pools Eq. 3's Demonstrator rollouts: it needs --stage distill with --variant off")
    if args.executor_prompt not in EXECUTOR_PROMPTS:
        p.error(f"--executor_prompt: unknown {args.executor_prompt!r}; choose from {', '.join(EXECUTOR_PROMPTS)}")
    control_stage = args.stage == "rl" or (args.stage == "distill"
                                           and set(args.variant.split(",")) <= {"off", "on", "dmd", "paired"})
    if args.executor_prompt != "task" and (not control_stage or args.model != "toy" or args.dataset):
        p.error(f"--executor_prompt {args.executor_prompt} is a toy control for the objectives: --stage rl, or "
                "--stage distill with --variant off, on, dmd or paired (sft trains on the tasks it derives); toy "
                "model and toy VLM pairs only")
    if args.train_crowded and (args.model != "toy" or args.dataset):
        p.error("--train_crowded draws the toy VLM's pairs on crowded toy scenes: toy model, no --dataset")
    if args.micro_batch < 0:
        p.error(f"--micro_batch must be >= 0 (0: no micro-batches), got {args.micro_batch}")
    if args.resume and args.stage == "pretrain":
        p.error("--resume continues an rl or distill run from its state.pt; the pretrain stage saves no state")
    if args.resume and args.stage == "distill" and "," in args.variant:
        p.error("--resume continues a distill run of one --variant; a run of several saves no state")
    if args.micro_batch and args.stage != "rl" and args.model == "toy":
        p.error("--micro_batch splits the rl stage's rollouts, updates and evaluations, or a real model's SFT videos: "
                "it needs --stage rl or --model other than toy")
    if args.grad_checkpoint and args.model == "toy":
        p.error("--grad_checkpoint is for a real model's transformer (--model ltx2 / hunyuan15 and their -tiny)")
    if args.offload_judge and args.judge == "toy":
        p.error("--offload_judge is for a VLM judge's weights (--judge qwen-vl / qwen-vl-tiny / qwen-vl-random)")
    if args.toy_gpu and (args.model != "toy" or args.stage != "rl"):
        p.error("--toy_gpu puts the toy model of the rl stage on the GPU (a real --model goes there by itself)")
    if args.toy_gpu and not torch.cuda.is_available():
        p.error("--toy_gpu: torch sees no GPU on this machine")
    if args.offload_text and args.model == "toy":
        p.error("--offload_text is for a real model's text encoder (--model ltx2 / hunyuan15 and their -tiny and "
                "-random stand-ins)")
    if args.eval_n > 200 and not args.eval_dataset:
        p.error("--eval_n must be at most 200 (the toy bench's size)")
    if args.eval_crowded and args.eval_dataset:
        p.error("--eval_crowded is a toy bench and --eval_dataset another: give one")
    if args.eval_dataset and args.stage != "rl" and args.model == "toy":
        p.error("--eval_dataset is the rl stage's bench, and a real model's +SFT run's: it needs --stage rl or --model "
                "other than toy")
    if min(args.p_vague, args.p_empty, args.p_goal) < 0 or args.p_vague + args.p_empty + args.p_goal > 1:
        p.error("--p_vague, --p_empty, --p_goal must be >= 0 and sum to at most 1")
    try:
        models.ToyConfig(width=args.width, evidence=args.evidence)
    except ValueError as e:
        p.error(f"--{e}")
    if not 0 <= args.p_task_words <= 1:
        p.error(f"--p_task_words must lie in [0, 1], got {args.p_task_words}")
    if not 0 <= args.ema < 1:
        p.error("--ema must lie in [0, 1)")
    if not 0 <= args.executor_ema < 1:
        p.error("--executor_ema must lie in [0, 1) (0: no EMA)")
    if args.executor_ema_schedule != "constant" and not args.executor_ema:
        p.error("--executor_ema_schedule sets the decay of --executor_ema: it needs --executor_ema > 0")
    if args.point_weight < 0 or (args.point_weight and not args.relate):
        p.error("--point_weight must be >= 0 and supervises Relate's heads: it needs --relate")
    if args.point_goal_only and not args.point_weight:
        p.error("--point_goal_only changes what --point_weight supervises: it needs --point_weight > 0")
    if args.relate_text and not args.relate:
        p.error("--relate_text gives Relate its own text encoder: it needs --relate")
    for name, directory in (("run_dir", True), ("eval_cache", True), ("out", False)):
        if getattr(args, name) and (bad := bench.output_path_error(getattr(args, name), f"--{name}", directory)):
            p.error(bad)
    for name, readers, chosen in ignored:
        flag = f"--no-{name}" if getattr(args, name) is False else f"--{name}"      # a default-on switch
        p.error(f"{flag} is read with {readers} only: {chosen} would ignore it")
    return args


def _field_docs(cls) -> dict:
    """The string literal under each dataclass field (its docstring)."""
    import ast
    import inspect
    tree = ast.parse(inspect.getsource(cls))
    body, docs = tree.body[0].body, {}
    for a, b in zip(body, body[1:]):
        if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant):
            docs[a.target.id] = b.value.value.replace("%", "%%")   # argparse formats help strings with %
    return docs


def seed_everything(seed: int, threads: int) -> np.random.Generator:
    random.seed(seed)
    torch.manual_seed(seed)
    models.use_cpu(threads)
    return np.random.default_rng(seed)


def _eta(start: float, done: int, total: int) -> str:
    el = time.time() - start
    return f"{el / 60:.1f} min, ETA {el / max(done, 1) * (total - done) / 60:.1f} min"


# ================================================================================================================
# stage: pretrain the base model
# ================================================================================================================

def video_loss(model, videos: np.ndarray, captions: list[str], args: Args) -> torch.Tensor:
    """The flow-matching loss (App. A.9) on captioned world videos, weighted (1 - t)^loss_power and x motion_weight
    on pixels that differ from the first frame: pretraining's loss, and the SFT baseline's (on a real model's latents
    unweighted). Draws x_0 and t from torch's global generator."""
    x_1 = model.encode_video(videos)                       # (B, T, 3, H, W) data; a real model's latents
    c = model.condition(videos[:, 0], captions)
    x_0 = torch.randn_like(x_1)                            # noise
    t = torch.rand(len(videos), device=x_1.device)         # t ~ U[0, 1]
    if model.backend != "toy":     # a real model (the +SFT baseline): every t and latent alike; the paper gives no
        return flow.flow_matching_loss(lambda x, tt: model(x, tt, c), x_0, x_1, t)    # SFT loss, so this is ours
    w = (1 - t).clamp(min=model.cfg.min_one_minus_t).reshape(-1, 1, 1, 1, 1) ** args.loss_power \
        * models.moving_pixel_weight(x_1, c["frame0"], args.motion_weight)
    return flow.flow_matching_loss(lambda x, tt: model(x, tt, c), x_0, x_1, t, weight=w)


def pointing_loss(model, frame0: np.ndarray, captions: list[str], places: np.ndarray,
                  goal_only: bool = False) -> torch.Tensor:
    """Toy base, --relate --point_weight: cross-entropy of Relate's head 0's attention over the first frame's pixels
    against the centre pixel of the mover the caption names, and of head 1's against the sprite the motion heads
    for: a goal caption's target, else the mover itself, so that head 1's offset is a direction only when the
    caption names a goal (places (B, 2, 2) from world.pretraining_batch, NaN where the caption names no sprite: no
    term). A real base learns where "the blue circle" is from web-scale captions; the toy's heads did not from the
    video loss alone, so pretraining says it outright. The U-Net's encoding of the caption is detached here: this
    loss trains Relate's query MLP and keys (and, with --relate_text, Relate's own text encoder), not the text
    encoder the U-Net reads D through. Measured (docs/given-t.md, "Teaching the offset heads to point"): with the gradient
    into the text encoder, and head 1 supervised on goal captions only, the heads pointed but D-following broke
    (error-free D 0.345). goal_only (--point_goal_only) is that form: no head-1 term where its place is the mover's."""
    a, _ = model.relate_attention(model.condition(frame0, captions), detach_text=True)  # (B, heads, HW)
    pl = torch.as_tensor(places).clone()
    if goal_only:  # a goal caption's target is another sprite, at another place than the mover
        pl[:, 1][(pl[:, 1] == pl[:, 0]).all(-1)] = float("nan")
    valid = ~pl.isnan().any(-1)                                                      # (B, 2)
    idx = (pl[..., 1].nan_to_num() * model.cfg.size + pl[..., 0].nan_to_num()).long()  # row-major pixel index
    logp = torch.log(a[:, :2].gather(-1, idx[..., None]).squeeze(-1).clamp(min=1e-12))  # (B, 2)
    return -(logp * valid).sum() / valid.sum().clamp(min=1)


def ema_step(ema, params, decay: float) -> None:
    """An exponential moving average of weights, in place: ema <- decay ema + (1 - decay) theta, tensor by tensor.
    The base's pretraining (with a warm-up in `decay`) and the Executor's --executor_ema (Tab. 3) use it."""
    with torch.no_grad():
        for e, p in zip(ema, params):
            e.lerp_(p, 1 - decay)


def executor_ema_decay(decay: float, schedule: str, done: int) -> float:
    """The decay of the Executor's EMA (Tab. 3) at an update after `done` earlier ones: `decay` itself under the
    constant schedule; under "power" a warm-up, min(decay, 1 - (1 + done)^(-2/3)) -- 0 at the first update (the
    average starts as the trained weights), 0.37 at the second, 0.9 from the 32nd. Table 3 names the schedule, not
    its formula: this is the power warm-up of diffusers' EMAModel (inv_gamma 1, power 2/3). Flow-Factory, a public
    trainer with Table 3's setting names, calls min(decay, (1 + s) / (10 + s)) at step s "power"; over the
    HunyuanVideo-1.5 column's six updates the two differ by at most 0.10 after the first (docs/given-t.md)."""
    return decay if schedule == "constant" else min(decay, 1 - (1 + done) ** (-2 / 3))


@contextlib.contextmanager
def weights_swapped(params: list, ema: list | None):
    """Inside the block `params` hold the averaged weights `ema` (an evaluation of the --executor_ema Executor);
    afterwards the trained weights are back, bit for bit. ema None: nothing changes."""
    if ema is None:
        yield
        return
    trained = [p.detach().clone() for p in params]
    with torch.no_grad():
        for p, e in zip(params, ema):
            p.copy_(e)
    try:
        yield
    finally:
        with torch.no_grad():
            for p, w in zip(params, trained):
                p.copy_(w)


def pretrain(args: Args) -> dict:
    rng = seed_everything(args.seed, args.threads)
    model = models.make_model("toy", width=args.width, evidence=args.evidence,
                              evidence_by_colour=args.evidence_by_colour,
                              evidence_lead=args.evidence_lead, ground=args.ground,
                              relate=args.relate, relate_text=args.relate_text)
    ema = copy.deepcopy(model).requires_grad_(False)
    opt = torch.optim.AdamW(model.parameters(), lr=args.pretrain_lr, weight_decay=args.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / 100) * (
        0.1 + 0.9 * 0.5 * (1 + np.cos(np.pi * min(s / args.pretrain_steps, 1.0)))))
    exclude = world.bench_scene_keys()  # the bench's scenes are never seen in training
    steps, out = args.pretrain_steps, args.out or models.SHIPPED_BASE
    print(f"pretraining {sum(p.numel() for p in model.parameters()) / 1e6:.2f}M parameters for {steps} steps")
    os.makedirs(args.run_dir, exist_ok=True)
    logf, start, run_loss, run_point = open(os.path.join(args.run_dir, "pretrain.jsonl"), "w"), time.time(), [], []
    for step in range(1, steps + 1):
        videos, captions, places = world.pretraining_batch(rng, args.pretrain_batch, args.p_vague, args.p_empty,
                                                           args.p_goal, exclude, places=True,
                                                           p_task_words=args.p_task_words)
        loss = video_loss(model, videos, captions, args)
        if args.point_weight:
            point = pointing_loss(model, videos[:, 0], captions, places, args.point_goal_only)
            run_point.append(point.item())
            loss = loss + args.point_weight * point
        opt.zero_grad(set_to_none=True)
        loss.backward()
        gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        # EMA with warm-up, so early weights do not linger in the average
        ema_step(ema.parameters(), model.parameters(), min(args.ema, step / (step + 10)))
        run_loss.append(loss.item())
        if step % args.log_every == 0 or step == steps:
            rec = {"step": step, "loss": float(np.mean(run_loss)), "grad_norm": float(gnorm),
                   "lr": sched.get_last_lr()[0], "seconds": time.time() - start}
            if run_point:
                rec["pointing_loss"] = float(np.mean(run_point))
            logf.write(json.dumps(rec) + "\n")
            logf.flush()
            shown = f"pointing {rec['pointing_loss']:.3f} | " if run_point else ""
            print(f"step {step:5d}/{steps} | loss {rec['loss']:.4f} | {shown}grad {rec['grad_norm']:.2f} | "
                  f"{_eta(start, step, steps)}", flush=True)
            run_loss, run_point = [], []
    minutes = (time.time() - start) / 60
    models.save_checkpoint(ema, out, {"stage": "pretrain", "args": dataclasses.asdict(args),
                                      "minutes": round(minutes, 2)})
    print(f"saved {out} after {minutes:.1f} min")
    return {"minutes": minutes}


# ================================================================================================================
# stage: self-distillation (Sec. 3, distill.py)
# ================================================================================================================

VARIANTS = ("off", "on", "dmd", "sft", "paired")
# Args.executor_prompt -> how the tables and plots name it; each is a bench.prompts_for condition of that name
EXECUTOR_PROMPTS = {k: bench.PROMPT_NAMES[k] for k in ("task", "instruction", "oracle_instruction", "oracle_direction",
                                                      "goal")}


def executor_given(prompt: str) -> str:
    """What the Executor is given under --executor_prompt, for a plot's title: "T", or a control's prompt."""
    return EXECUTOR_PROMPTS[prompt] + ("" if prompt == "task" else " (a control)")


def _batch(pairs: list, idx, executor_prompt: str = "task") -> tuple:
    """(first frames uint8 (B, H, W, 3), the Executor's prompts, the toy VLM's descriptions D) of the chosen pairs.
    The Executor's prompt is the task T, or a control's prompt (Args.executor_prompt)."""
    ps = [pairs[i] for i in idx]
    return np.stack([p.frame0 for p in ps]), bench.prompts_for(ps, executor_prompt), [p.d_vlm for p in ps]


# what each bench evaluation during training records: the three judges, their mean, and the share of still videos
EVAL_KEYS = ("task", "agent", "consistency", "avg", "still")


def eval_keys(res: dict) -> tuple:
    """EVAL_KEYS, and PickScore's mean where the evaluation has one (--pick: Fig. 4's quality measure)."""
    return (*EVAL_KEYS, "pick") if "pick" in res else EVAL_KEYS


def eval_line(res: dict) -> str:
    """One evaluation as a progress line."""
    return " ".join(f"{k} {res[k]:.3f}" for k in eval_keys(res))


def eval_pairs(args: Args) -> list:
    """The bench every evaluation of this run reads: --eval_dataset's rows (BENCH, which rl_stage sets), else the
    toy bench, or with --eval_crowded the crowded one."""
    if BENCH is not None:
        return BENCH
    return (world.crowded_pairs if args.eval_crowded else world.bench_pairs)(args.error_rate)


def bench_title(crowded: bool) -> str:
    """The toy bench a figure's scores come from, as its title names it."""
    return "WorldTasks-toy's crowded bench" if crowded else "WorldTasks-toy"


def evaluate_executor(model, args: Args, demonstrator: bool | str = False) -> dict:
    """Bench scores of the Executor given T (or its --executor_prompt) -- or, with demonstrator=True, of the
    Demonstrator (adapters off) given the toy VLM's D. Same noise seed (0) every time, so curves compare like with
    like."""
    ctx = models.adapters_disabled(model) if demonstrator is True else contextlib.nullcontext()
    size = (models.resolution(model, args.eval_height, args.eval_width) if args.eval_height else
            contextlib.nullcontext())      # Table 3's evaluation resolution
    with ctx, size:   # demonstrator="trained": Alg. 2's phi, its adapters on, given D
        res, videos, _ = bench.evaluate(model, "vlm" if demonstrator else args.executor_prompt, args.eval_n, seed=0,
                                        error_rate=args.error_rate, steps=args.sample_steps, judge=JUDGE,
                                        batch=args.micro_batch or 200, pairs=eval_pairs(args), pick=PICK)
    return res


def base_evaluation(model, args: Args, demonstrator: bool = False) -> dict:
    """evaluate_executor of the base itself (no adapters trained yet): given T, or the Demonstrator given the toy
    VLM's D. The bench is deterministic (noise seed 0), so with --eval_cache the result is computed once per
    (base file, settings) and read back by every later run -- the report's 33 runs would otherwise repeat it 66
    times."""
    if not args.eval_cache or args.model != "toy" or PICK is not None:
        return evaluate_executor(model, args, demonstrator)
    key = {"base": bench.file_digest(args.init or models.SHIPPED_BASE), "demonstrator": demonstrator,
           **({} if demonstrator or args.executor_prompt == "task" else {"executor_prompt": args.executor_prompt}),
           "eval_n": args.eval_n, "error_rate": args.error_rate, "sample_steps": args.sample_steps,
           "judge": args.judge, "judge_path": args.judge_path,
           **({"eval_crowded": True} if args.eval_crowded else {}),     # absent: the keys written before the flag
           **({"eval_dataset": bench.file_digest(args.eval_dataset)} if args.eval_dataset else {})}
    name = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16] + ".json"
    path = os.path.join(args.eval_cache, name)
    if os.path.isfile(path):        # the file name is the key's hash
        try:
            with open(path) as f:
                cached = json.load(f)["result"]
        except (ValueError, KeyError, TypeError):   # damaged (by hand: it is written whole): evaluate again, rewrite
            cached = {}
        if isinstance(cached, dict) and set(EVAL_KEYS) <= cached.keys():   # else written before bench.evaluate
            return cached                     # returned all that training records (the still count): again, rewrite
    res = evaluate_executor(model, args, demonstrator)
    os.makedirs(args.eval_cache, exist_ok=True)
    tmp = f"{path}.{os.getpid()}.tmp"
    with open(tmp, "w") as f:        # written whole, then renamed: a run started beside this one never reads half
        json.dump({"key": key, "result": res}, f)
    os.replace(tmp, path)
    return res


def executor_path(args: Args, name: str) -> str:
    """Where a stage saves its Executor: --out, or <run_dir>/executor_<name>.pt (name: the variant, or the trainer)."""
    return args.out or os.path.join(args.run_dir, f"executor_{name}.pt")


def save_executor(model, path: str, meta: dict):
    """Save an Executor as bench.py loads it: the toy's with its LoRA folded in (a full checkpoint with the base's
    network and cost), a real model's LoRA alone (bench.py --lora; the base stays where --model_path says). Returns
    the network saved: the merged copy, or the model itself."""
    if model.backend == "toy":
        merged = models.merge_lora(model)
        models.save_checkpoint(merged, path, meta)
        return merged
    models.save_lora(model, path, meta)
    return model


KEPT = []
"""The Executors --keep_executors saved in this process, in order (main's Ctrl-C line names the last)."""


def keep_executor(model, out: str, step: int, meta: dict) -> None:
    """--keep_executors: the Executor an evaluation before the last scored, saved as `out` with _step<N> before its
    extension and the step in its meta."""
    root, ext = os.path.splitext(out)
    path = f"{root}_step{step}{ext}"
    save_executor(model, path, {**meta, "step": step})
    KEPT.append(path)


def executor_start(args: Args, model) -> dict | None:
    """--executor_init's weights (None without it), checked against the base's before anything is written: Fig. 1's
    second stage, RL from a distilled Executor whose Demonstrator stays the base."""
    if not args.executor_init:
        return None
    start, want = models.load_checkpoint(args.executor_init)[0].state_dict(), model.state_dict()
    if start.keys() != want.keys() or any(start[k].shape != want[k].shape for k in want):
        raise ValueError(f"--executor_init {args.executor_init!r} is not an Executor of this base (--init "
                         f"{args.init or models.SHIPPED_BASE!r}): its weights differ in name or shape")
    return start


def executor_meta(args: Args, stage: str, **more) -> dict:
    """The meta of a saved Executor: the stage that trained it, `more` (the distill stage's variant) and the run's
    settings, which bench.py reads (--trained_pairs)."""
    return {"stage": stage, **more, "args": dataclasses.asdict(args)}


def executor_parameters(model, args: Args, start_from: dict | None = None) -> tuple:
    """What of the Executor trains, and its Demonstrator (--executor_weights). lora: a fresh LoRA on `model` (B = 0:
    the base exactly); the Demonstrator is `model` with adapters off, returned as None (distill.teacher_velocity's
    default). all: every weight of `model`, beside a frozen copy of it taken first, the Demonstrator; then
    `start_from` (--executor_init's weights, from executor_start) is loaded into `model`, so the Demonstrator stays
    the base. Returns (the parameters the optimizer steps, the Demonstrator network or None)."""
    if args.executor_weights == "all":
        teacher = copy.deepcopy(model).requires_grad_(False)
        if start_from is not None:     # after the Demonstrator's frozen copy of the base is taken
            model.load_state_dict(start_from)
        return [p.requires_grad_(True) for p in model.parameters()], teacher
    models.add_lora(model, args.lora_rank, args.lora_alpha, convs=args.lora_convs, embeddings=args.lora_embeddings)
    return models.lora_parameters(model), None


def demonstrator_rollouts(model, x_0, c_D: dict, frame0, tasks: list, args: Args, teacher=None) -> tuple:
    """Eq. 3's Demonstrator trajectory under c_D from noise x_0: ((xs, ts), the velocities its sampler took) and the
    rows kept -- under --off_judged those whose videos (the trajectory's end decoded after its first frame) the
    judges pass against their tasks T (judge_rollouts' solved; NaN, no judgment, fails), else every row."""
    traj, v_D = distill.rollout(model, x_0, c_D, train_steps(args), True, velocities=True, teacher=teacher)
    if not args.off_judged:
        return traj, v_D, torch.arange(len(tasks))
    solved = judge_rollouts(model.decode(traj[0][-1], frame0), tasks)["solved"]
    return traj, v_D, torch.nonzero(solved == 1).flatten()


def demonstrator_pool(model, pairs: list, args: Args, teacher, logf) -> SimpleNamespace:
    """--off_pool N (ours): the Demonstrator's trajectories for Eq. 3, N from fresh noise for each training pair,
    rolled out once in batches of --batch (under --off_judged judged then, and only those the judges pass kept), so a
    step draws its batch from them and runs the Executor alone. The noise has its own generator (--seed): a resumed
    run rolls out the same pool. Returns SimpleNamespace(xs (S+1, P, ...), ts (S+1,), vs (S, P, ...),
    pair (P,): each trajectory's index into `pairs`); a pool under --batch trajectories is refused."""
    gen, start = torch.Generator().manual_seed(args.seed), time.time()
    which = np.repeat(np.arange(len(pairs)), args.off_pool)
    xs, vs, kept = [], [], []
    for i in range(0, len(which), args.batch):
        idx = which[i:i + args.batch]
        frame0, _, descs = _batch(pairs, idx)
        x_0 = torch.randn(len(idx), *model.latent_shape(), generator=gen)
        (x, ts), v_D, keep = demonstrator_rollouts(model, x_0, model.condition(frame0, descs), frame0,
                                                   [pairs[j].task.text for j in idx], args, teacher)
        xs.append(x[:, keep])
        vs.append(v_D[:, keep])
        kept.append(idx[keep.cpu().numpy()])
        done = i + len(idx)
        if done == len(which) or (i // args.batch) % 20 == 19:
            print(f"[off] Demonstrator pool: {done}/{len(which)} rollouts, {sum(map(len, kept))} kept | "
                  f"{_eta(start, done, len(which))}", flush=True)
    pool = SimpleNamespace(xs=torch.cat(xs, 1), ts=ts, vs=torch.cat(vs, 1), pair=np.concatenate(kept))
    rec = {"pool": True, "rollouts": len(which), "kept": len(pool.pair), "seconds": time.time() - start,
           "kept_wrong_d": float(np.mean([pairs[j].error != "" for j in pool.pair])) if len(pool.pair) else None}
    logf.write(json.dumps(rec) + "\n")      # the wrong D's share kept: measured from the oracle, never used
    if len(pool.pair) < args.batch:
        raise ValueError(f"--off_pool: the Demonstrator pool kept {len(pool.pair)} of {len(which)} rollouts, fewer "
                         f"than a batch of {args.batch}; roll out more (a larger --off_pool)")
    return pool


def distill_variant(args: Args, variant: str, pairs: list, logf, at_0: dict, base=None, start_from=None,
                    fixed: dict | None = None, state: dict | None = None) -> tuple:
    """Train a fresh Executor (a LoRA on the base, or every weight: --executor_weights) with one self-distillation
    objective; evaluate every eval_every steps and at the last. at_0 is the base's evaluation given T (or
    --executor_prompt): a fresh Executor (LoRA B = 0) is the base exactly, so every variant's step 0 is that one
    evaluation. `base`: a real model, whose +SFT baseline trains on `pairs`, --sft_dataset's rows (None: the toy
    base, loaded afresh). `start_from`: --executor_init's weights, loaded into every weight of the Executor after its
    Demonstrator's frozen copy of the base is taken, and scored at step 0 (a fresh optimizer: a second run from a
    saved Executor, not the same run made longer). Under --executor_ema the evaluations, the kept Executors and the
    model returned are an average of the trained weights, from where the Executor starts. `fixed`: the run's
    evaluations that a resumed run does not repeat (the Demonstrator's), for a resumable state saved every
    --save_every steps (None: no state, as in a run of several variants); `state`: one to resume from, which
    restores the weights, optimizers, EMA and every RNG where the saved run stood. Returns (model, list of eval
    records)."""
    seed_everything(args.seed, args.threads)
    gen = torch.Generator().manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    model = base if base is not None else models.load_checkpoint(args.init or None)[0]
    params, teacher = executor_parameters(model, args, start_from)
    opt = torch.optim.Adam(params, lr=args.lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=1e-4)  # Table 3
    ema = [p.detach().clone() for p in params] if args.executor_ema else None   # Table 3's EMA, from the start
    fake, fake_opt = None, None
    if variant == "dmd":
        fake = distill.make_fake_score(model, args.lora_rank, args.lora_alpha)
        fake_opt = torch.optim.Adam(models.lora_parameters(fake), lr=args.lr)
    pool = demonstrator_pool(model, pairs, args, teacher, logf) if variant == "off" and args.off_pool else None
    evals, start = [], time.time()

    def log_eval(step):
        with weights_swapped(params, ema):      # under --executor_ema the average is kept and scored
            if args.keep_executors and 0 < step < args.steps:       # the last step's is the stage's own save
                keep_executor(model, executor_path(args, variant), step,
                              executor_meta(args, "distill", variant=variant))
            res = evaluate_executor(model, args) if step or start_from is not None else at_0
        rec = {"variant": variant, "step": step, **{k: res[k] for k in EVAL_KEYS}, "seconds": time.time() - start}
        evals.append(rec)
        logf.write(json.dumps({"eval": True, **rec}) + "\n")
        logf.flush()
        print(f"[{variant}] eval step {step:4d} | {eval_line(rec)}", flush=True)

    first = 1
    if state is not None:       # the state's evaluations include step 0's
        first, evals = restore_state(state, model, opt, fake, fake_opt, rng, gen, ema), state["evals"]
        print(f"[{variant}] resumed {run_state_path(args)} at step {first - 1}", flush=True)
    else:
        log_eval(0)
    for step in range(first, args.steps + 1):
        t0 = time.time()
        drawn = rng.choice(len(pool.pair), args.batch, replace=False) if pool is not None else None  # --off_pool
        idx = pool.pair[drawn] if pool is not None else rng.choice(len(pairs), args.batch, replace=False)
        extra, loss_of = {}, None
        if base is not None:    # Table 1's +SFT on a real model: its labelled videos, --micro_batch at a time (each
            rows = [pairs[i] for i in idx]         # part draws its own x_0 and t: the same law as one pass)
            videos = np.stack([world.load_video(r["video"], (model.width, model.height)) for r in rows])
            m = args.micro_batch or len(rows)
            parts = [SimpleNamespace(rows=slice(i, i + m), share=len(rows[i:i + m]) / len(rows))
                     for i in range(0, len(rows), m)]
            loss_of = lambda p: (  # noqa: E731 -- a part's loss, as _update takes it
                video_loss(model, videos[p.rows], [r["task"] for r in rows[p.rows]], args), {})
        elif variant == "sft":  # Sec. 4.4's +SFT baseline: plain world videos labelled with derived short tasks
            videos, labels = world.sft_batch(rng, args.batch, args.train_crowded)
            loss = video_loss(model, videos, labels, args)
        elif variant == "paired":  # the costly supervision WMSD does without: correct executions labelled with T
            # (or with a control's prompt, --executor_prompt)
            ps = [pairs[i] for i in idx]
            videos = np.stack([world.render(p.scene, world.simulate(p.scene, p.plan_oracle)) for p in ps])
            loss = video_loss(model, videos, _batch(pairs, idx, args.executor_prompt)[1], args)
        else:                   # the self-distillation objectives: Executor under c_E, Demonstrator under c_D
            frame0, tasks, descs = _batch(pairs, idx, args.executor_prompt)
            c_E, c_D = model.condition(frame0, tasks), model.condition(frame0, descs)
            x_0 = torch.randn(args.batch, *model.latent_shape(), generator=gen) if pool is None else None
            if variant == "off":    # Eq. 3 on the Demonstrator's states
                if pool is not None:    # --off_pool: its trajectories, rolled out (and judged) before the first step
                    traj, v_D, keep = (pool.xs[:, drawn], pool.ts), pool.vs[:, drawn], drawn
                else:
                    traj, v_D, keep = demonstrator_rollouts(model, x_0, c_D, frame0,
                                                            [pairs[i].task.text for i in idx], args, teacher)
                if args.off_judged and pool is None:    # ours: only the rollouts the judges pass, judged against T
                    extra["judged_kept"] = len(keep) / len(idx)     # and, measured only, the wrong D's share kept
                    extra["kept_wrong_d"] = (float(np.mean([pairs[idx[i]].error != "" for i in keep.tolist()]))
                                             if len(keep) else float("nan"))
                    traj, v_D = (traj[0][:, keep], traj[1]), v_D[:, keep]
                    c_E, c_D = models.condition_rows(c_E, keep), models.condition_rows(c_D, keep)
                if len(keep):
                    loss = distill.off_policy_loss(model, traj, c_E, c_D, gen, teacher, window=state_window(args),
                                                   motion_weight=args.distill_motion_weight, teacher_v=v_D)
                else:                   # no rollout passed: nothing to regress on, no update
                    loss = torch.zeros((), requires_grad=True)
            elif variant == "on":   # Eq. 5 / Eq. 11 on the Executor's own states
                loss = distill.on_policy_loss(model, distill.rollout(model, x_0, c_E, train_steps(args)),
                                              c_E, c_D, gen, state_window(args), args.distill_motion_weight, teacher)
            else:                   # App. A.2.1: G_theta from the Executor's own states, then the fake score
                x = distill.dmd_generator(model, distill.rollout(model, x_0, c_E, train_steps(args)), c_E, gen)
                loss = distill.dmd_generator_loss(model, fake, x, c_E, c_D, gen)
                fake_loss = distill.dmd_fake_score_loss(fake, x.detach(), c_E, gen)
                fake_opt.zero_grad(set_to_none=True)
                fake_loss.backward()
                fake_opt.step()
                extra["fake_loss"] = fake_loss.item()
        if loss_of is None:     # the toy's loss above, on the whole batch: one part
            parts, loss_of = [SimpleNamespace(share=1.0)], lambda p: (loss, {})
        value, gnorm, _ = _update(step, opt, params, parts, loss_of, gen, variant)   # Table 3: max grad norm 1
        if ema is not None and step % args.executor_ema_every == 0:
            ema_step(ema, params, executor_ema_decay(args.executor_ema, args.executor_ema_schedule,
                                                     step // args.executor_ema_every - 1))
        rec = {"variant": variant, "step": step, "loss": value, "grad_norm": float(gnorm),
               "step_seconds": time.time() - t0, **extra}
        logf.write(json.dumps(rec) + "\n")
        if step % args.log_every == 0 or step == args.steps:
            print(f"[{variant}] step {step:4d}/{args.steps} | loss {rec['loss']:.5f} | grad {rec['grad_norm']:.3f} | "
                  f"{rec['step_seconds']:.2f} s/step | {_eta(start, step - first + 1, args.steps - first + 1)}",
                  flush=True)
        if step % args.eval_every == 0 or step == args.steps:
            log_eval(step)
        if fixed is not None and (step % args.save_every == 0 or step == args.steps):
            logf.flush()      # the log on disk holds every step the state has seen
            save_state(run_state_path(args), step, model, opt, fake, fake_opt, rng, gen, evals, fixed, args, ema)
    if ema is not None:         # the Executor returned, saved and shown is the average its evaluations scored
        with torch.no_grad():
            for p, e in zip(params, ema):
                p.copy_(e)
    return model, evals


def distill_stage(args: Args) -> dict:
    """Run each variant from the same base (or --executor_init's Executor); plot task score vs step (Fig. 4 left)
    with the Demonstrator as a line; save each Executor and a GIF of its rollouts beside the Demonstrator's."""
    # the toy's benches and judges, or a real model's own (--eval_dataset, --judge), whatever an rl run before it in
    # this process set; no PickScore (the rl stage's)
    global BENCH, JUDGE, PICK
    BENCH, JUDGE, PICK = None, None, None
    seed_everything(args.seed, args.threads)
    t0 = time.time()
    one = "," not in args.variant    # a run of one variant keeps a resumable state; one of several does not
    state = load_state(run_state_path(args), args) if args.resume else None
    if one and not args.resume:
        refuse_to_overwrite(run_state_path(args))
    if args.model != "toy":     # Table 1's +SFT row (parse_args lets a real model run nothing else here)
        base = load_real(args)  # a bad model or file stops here, before anything is trained
        pairs = sft_rows(args.sft_dataset, base, args.batch)
        JUDGE, BENCH = make_judge(args), load_bench(args, base, [])
        print(f"{len(pairs)} labelled videos from {args.sft_dataset}")
    else:
        pairs = toy_pairs(args)
        print(f"{len(pairs)} training pairs from the toy VLM (error rate {args.error_rate}"
              f"{', crowded scenes' if args.train_crowded else ''}"
              f"{f', {args.train_arrangements} places of each task' if args.train_arrangements > 1 else ''}) "
              f"in {time.time() - t0:.0f} s")
        base = None
    net = base if base is not None else models.load_checkpoint(args.init or None)[0]
    start_from = executor_start(args, net)       # a bad --executor_init stops here too
    os.makedirs(args.run_dir, exist_ok=True)     # after the inputs are read: a bad one leaves no empty run dir
    demo = state["fixed"]["demonstrator"] if state else base_evaluation(net, args, demonstrator=True)
    demo = {k: demo[k] for k in ("task", "agent", "consistency", "avg")}
    # step 0's score: the base given T, unless step 0 scores --executor_init's Executor or a resumed state holds it
    at_0 = base_evaluation(net, args) if start_from is None and state is None else None
    d = "the bench file's D" if BENCH is not None else "the toy VLM's D"
    print(f"{'On the crowded bench, the ' if args.eval_crowded else ''}Demonstrator (base given {d}): "
          f"task {demo['task']:.3f} agent {demo['agent']:.3f} "
          f"consistency {demo['consistency']:.3f}")
    if start_from is not None:
        print(f"every variant's Executor starts from {args.executor_init} (its Demonstrator: the base)")
    variants = args.variant.split(",")
    results = {"demonstrator": demo, "variants": {},
               "executor_prompt": args.executor_prompt, "executor_init": os.path.basename(args.executor_init),
               "executor_ema": args.executor_ema,
               "bench": args.eval_dataset or ("crowded" if args.eval_crowded else "toy")}
    log = os.path.join(args.run_dir, "distill.jsonl")
    if state is not None:
        keep_logged_steps(log, state["step"] + 1)
    with open(log, "a" if state is not None else "w") as logf:
        for v in variants:
            model, evals = distill_variant(args, v, pairs, logf, at_0, base, start_from,
                                           fixed={"demonstrator": demo} if one else None, state=state)
            results["variants"][v] = evals
            save_executor(model, executor_path(args, v), executor_meta(args, "distill", variant=v))
            write_rollout_gif(model, os.path.join(args.run_dir, f"rollouts_{v}.gif"), args)
    plot_fig4_left(results, os.path.join(args.run_dir, "fig4_left.png"))
    with open(os.path.join(args.run_dir, "distill_summary.json"), "w") as f:
        json.dump(results, f, indent=1)
    print(f"wrote {args.run_dir}/fig4_left.png, distill_summary.json, rollouts_*.gif")
    return results


def plot_fig4_left(results: dict, path: str) -> None:
    plt, fig, axes = bench.figure(2, width=5)
    for ax, key in zip(axes, ("task", "avg")):
        for v, evals in results["variants"].items():
            ax.plot([e["step"] for e in evals], [e[key] for e in evals], marker="o", ms=3, label=f"Executor, {v}")
        ax.axhline(results["demonstrator"][key], color="k", ls="--", lw=1,
                   label=f"Demonstrator ({bench.given_d(results.get('bench'))})")
        ax.set_xlabel("training step")
        ax.set_ylabel(f"bench {key} score")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    given = executor_given(results.get("executor_prompt", "task"))
    where = results.get("bench", "toy")
    where = bench_title(where == "crowded") if where in ("toy", "crowded") else os.path.basename(where)
    start = f", from {results['executor_init']}" if results.get("executor_init") else ""
    fig.suptitle(f"Self-distillation variants on {where} (paper Fig. 4 "
                 f"left)\nExecutor given {given}{start}")
    bench.save_figure(plt, fig, path)


def write_rollout_gif(model, path: str, args: Args, n: int = 6, scale: int = 8) -> None:
    """Rows: bench pairs; left: the Demonstrator given the toy VLM's D, right: the Executor given T (or its
    --executor_prompt; same noise). A real model's videos are thinned to 24 frames and rows of at most 128 px: at
    LTX-2's 121 frames of 384 x 576 the full GIF did not finish writing in a minute (measured on a GPU, docs/real-models.md).
    Only the toy's 16-px rows are enlarged (8x); the scale once came from the first frames, which are the toy
    bench's 16 px for a real model too, and made a 116 MB GIF of 1024-px rows at LTX-2's size (measured).
    A real model's rows are also written whole, beside the GIF: write_rollout_mp4s."""
    pairs = eval_pairs(args)[:n]
    frame0 = np.stack([p.frame0 for p in pairs])
    batch = args.micro_batch or n
    prompts = bench.prompts_for(pairs, args.executor_prompt)
    base = model      # the Demonstrator: the base (adapters off), or under --executor_weights all the toy base afresh
    if args.executor_weights == "all":
        base = models.load_checkpoint(args.init or None)[0].to(next(model.parameters()).device)
    with models.adapters_disabled(base):
        demo = models.generate(base, frame0, [p.d_vlm for p in pairs], args.sample_steps, seed=0, batch=batch)
    exe = models.generate(model, frame0, prompts, args.sample_steps, seed=0, batch=batch)
    if args.model != "toy":
        write_rollout_mp4s(bench.side_by_side(demo, exe), pairs, prompts, os.path.splitext(path)[0],
                           getattr(model, "fps", 24.0))
    F, H = demo.shape[1:3]   # a real model's 121 frames of 384 px: 24 frames evenly spaced, rows of at most 128 px
    keep, k = np.linspace(0, F - 1, min(F, 24)).round().astype(int), -(-H // 128)
    grid = bench.side_by_side(demo[:, keep, ::k, ::k], exe[:, keep, ::k, ::k])  # the toy's 6 frames of 16 px
    scale = max(1, scale * world.H // grid.shape[2])   # enlarged to the toy's 128 px rows; a real model's are already
    frames = [np.concatenate(list(grid[:, f]), axis=0) for f in range(grid.shape[1])]
    imgs = [Image.fromarray(f).resize((f.shape[1] * scale, f.shape[0] * scale), Image.NEAREST) for f in frames]
    imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=400, loop=0)


def write_rollout_mp4s(grid: np.ndarray, pairs: list, prompts: list[str], out_dir: str, fps: float) -> None:
    """A real model's rollout rows whole, every frame at its own size (the GIF thins them): out_dir/000.mp4, ...,
    the Demonstrator left and the Executor right, at the model's frame rate (bench.save_videos), and
    out_dir/videos.jsonl, a row a video: its file, the pair's T ("task"), the Demonstrator's prompt and the
    Executor's. Without PyAV (requirements-real.txt) a line says so and the GIF alone is written."""
    if importlib.util.find_spec("av") is None:
        print(f"  {out_dir}/*.mp4 not written: PyAV is not installed (pip install -r requirements-real.txt); "
              f"the GIF is", flush=True)
        return
    rows = [{"task": p.task.text, "demonstrator": p.d_vlm, "executor": prompt} for p, prompt in zip(pairs, prompts)]
    index = bench.save_videos(out_dir, grid, rows, fps)
    print(f"  wrote {len(rows)} rollout videos, the Demonstrator beside the Executor, to {out_dir}/ ({fps:g} fps; "
          f"index: {index})", flush=True)


# ================================================================================================================
# stage: the whole method -- RL from the judges with the distillation reward and the anchor (Alg. 1, rl.py)
# ================================================================================================================

TRAINERS = tuple(rl.OBJECTIVES)


def rl_config(args: Args) -> rl.RLConfig:
    return rl.RLConfig(clip_range=args.clip_range, kl_beta=args.kl_beta, timesteps=args.awm_timesteps,
                       times=args.awm_times, weighting=args.awm_weighting, ghuber_power=args.ghuber_power,
                       ratio=args.awm_ratio, nft_beta=args.nft_beta, adv_max=args.adv_clip or 5.0)


JUDGE = None
"""The VLM judge of this run (reward.VLMJudge), set by rl_stage from --judge; None = reward.py's toy judges."""
BENCH = None
"""The bench of this run, set by rl_stage from --eval_dataset (load_bench); None = the toy bench."""


def make_judge(args: Args):
    if args.judge == "toy":
        return None
    if args.judge == "qwen-vl-tiny":
        judge = reward.VLMJudge.tiny(world.VOCAB + ["[", "]:"], seed=args.seed)
    elif args.judge == "qwen-vl-random":      # built on the GPU directly, in bf16
        judge = reward.VLMJudge.random(world.VOCAB + ["[", "]:"], seed=args.seed)
    else:
        judge = reward.VLMJudge.from_pretrained(args.judge_path)
    if torch.cuda.is_available():     # beside the video model, on this process's GPU (torchrun: its LOCAL_RANK)
        judge.model.to("cuda")
        judge.device = judge.model.device
    if args.offload_judge:
        judge.offload()
    return judge


PICK = None
"""This run's PickScore (reward.PickScore), set by rl_stage from --pick; None: no PickScore."""
PICK_CHOICES = ("none", "pickscore", "pickscore-tiny")


def weighed_pick(args: Args):
    """PICK where Eq. 10 weighs it (--lambda_pick > 0), for judge_rollouts; None where it only measures, at each
    evaluation (--pick with --lambda_pick 0: Fig. 4's quality panel), so the rollouts are not scored by it."""
    return PICK if args.lambda_pick > 0 else None


def make_pick(args: Args):
    """--pick's reward.PickScore, on this process's GPU when there is one (beside the video model and the judge)."""
    if args.pick == "none":
        return None
    pick = (reward.PickScore.tiny(world.VOCAB + ["[", "]:"], seed=args.seed) if args.pick == "pickscore-tiny" else
            reward.PickScore.from_pretrained(args.pick_path, args.pick_processor_path))
    if torch.cuda.is_available():
        pick.model.to("cuda")
        pick.device = pick.model.device
    return pick


TOY_TASK_REWARDS = ("end_state", "attributed")   # --task_reward: reward.judge_task | reward.judge_task_reward


def fig5_setting(args: Args) -> str:
    """The name of the training setting the flags select (Fig. 5), for the final table's Executor row and the
    curve's title."""
    if args.executor_update == "off":    # without --alternate, Eq. 3 alone: Fig. 4 left's off-policy variant
        return "off-policy distillation + RL on the teacher" if args.alternate else "off-policy distillation (Eq. 3)"
    if anchor_only(args):
        return "the anchor alone (Eq. 11, on-policy)"
    if args.beta_d == 0 and args.lambda_distill == 0:
        return "RL from the judges alone"
    if args.demonstrator == "executor":
        return "WMSD, the Executor as its own Demonstrator (App. A.3)"
    return "WMSD, alternating (Alg. 2)" if args.alternate else "WMSD"


def judge_rollouts(videos: np.ndarray, tasks: list[str], task_reward: str = "end_state", pick=None) -> dict:
    """Alg. 1 line 6: the judges' graded scores of each rollout as rewards (the toy judges' margins, or a VLM's
    log p(yes) - log p(no)). Where no judgment is possible -- a malformed video or answer, a missing agent, or a judge
    that raises -- the score is NaN: rl.advantages skips that rollout and the log counts it (paper Tab. 4); a judge
    failure never stops the run. task_reward picks the toy r_task (--task_reward). With `pick` (a reward.PickScore:
    weighed_pick), PickScore against T (Table 3's third reward), NaN where it fails. Returns {"task", "consistency",
    "pick" (0 without one), "solved", "invalid", "judge_errors"}: (N,)."""
    n = len(tasks)
    if JUDGE is not None:                       # a VLM, batched; a failing batch is counted and skipped
        errors = [0] * n
        try:
            jts = JUDGE.task_reward(videos, tasks)
        except Exception:  # noqa: BLE001
            jts, errors = [reward.INVALID] * n, [e + 1 for e in errors]
        try:
            jcs = JUDGE.consistency_reward(videos)
        except Exception:  # noqa: BLE001
            jcs, errors = [reward.INVALID] * n, [e + 1 for e in errors]
    else:
        judge_task = reward.judge_task_reward if task_reward == "attributed" else reward.judge_task
        jts, jcs, errors = [], [], []
        for v, t in zip(videos, tasks):
            e = 0
            try:
                r = reward.read_video(v)
                jt = judge_task(r, t) if r else reward.INVALID
            except Exception:  # noqa: BLE001 -- a failing judge is counted and skipped, like a malformed VLM answer
                r, jt, e = None, reward.INVALID, e + 1
            try:
                jc = reward.judge_consistency(r) if r else reward.INVALID
            except Exception:  # noqa: BLE001
                jc, e = reward.INVALID, e + 1
            jts.append(jt)
            jcs.append(jc)
            errors.append(e)
    scores = np.zeros(n)
    if pick is not None:
        try:
            scores = pick(videos, tasks)
        except Exception:  # noqa: BLE001
            scores, errors = np.full(n, np.nan), [e + 1 for e in errors]
    out = {"task": [np.nan if j.score is None else j.score for j in jts], "pick": scores,
           "consistency": [np.nan if j.score is None else j.score for j in jcs],
           "solved": [np.nan if a.yes is None else float(a.yes and bool(b.yes)) for a, b in zip(jts, jcs)],
           "judge_errors": errors}
    res = {k: torch.tensor(v, dtype=torch.float32) for k, v in out.items()}
    res["invalid"] = torch.isnan(res["task"]) | torch.isnan(res["consistency"]) | torch.isnan(res["pick"])
    return res


# ---- processes: the same loop under torchrun (gloo on CPU, NCCL on GPUs) ------------------------------------------

def _under_torchrun() -> bool:
    """Launched as one of several processes (torchrun sets WORLD_SIZE), whether or not the group is up yet."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def _dist_init() -> None:
    if _under_torchrun() and not dist.is_initialized():
        if torch.cuda.is_available():
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")


def _comm_device() -> torch.device:
    """Where collectives need their tensors: the GPU under NCCL, the CPU under gloo."""
    return torch.device("cuda") if dist.is_initialized() and dist.get_backend() == "nccl" else torch.device("cpu")


def _rank() -> int:
    return dist.get_rank() if dist.is_initialized() else 0


def _world() -> int:
    return dist.get_world_size() if dist.is_initialized() else 1


def _shard(n: int) -> tuple[int, int]:
    """This process's rows of a batch of n: (offset, count); contiguous, equal shares."""
    w = _world()
    if n % w:
        raise ValueError(f"rollouts per step ({n}) must be divisible by the number of processes ({w})")
    return _rank() * (n // w), n // w


def _gather(x: torch.Tensor) -> torch.Tensor:
    """Concatenate every process's (n, ...) shard in rank order: the whole batch on every process."""
    if not dist.is_initialized():
        return x
    y = x.to(_comm_device()).contiguous()
    parts = [torch.empty_like(y) for _ in range(_world())]
    dist.all_gather(parts, y)
    return torch.cat(parts).to(x.device)


def _mean_over_processes(x: float) -> float:
    if not dist.is_initialized():
        return x
    t = torch.tensor([x], dtype=torch.float64, device=_comm_device())
    dist.all_reduce(t)
    return float(t) / _world()


class TrainingFault(RuntimeError):
    """A non-finite reward, advantage or loss: the run stops, the last good checkpoint is left as it was."""


def _check_finite(step: int, name: str, x: torch.Tensor, skip: torch.Tensor | None = None) -> None:
    bad = ~torch.isfinite(x) if skip is None else (~torch.isfinite(x) & ~skip)
    if bad.any():
        raise TrainingFault(f"step {step}: {name} is not finite ({int(bad.sum())} of {bad.numel()} values, e.g. "
                            f"{x[bad].flatten()[0].item()})")


# ---- one iteration ----------------------------------------------------------------------------------------------

def _rollouts(net, c: dict, x_0: torch.Tensor, args: Args, noises: torch.Tensor | None):
    """Alg. 1 line 5: one rollout per row of c from x_0, by the SDE sampler if `noises` (its standard normal draws)
    are given, else the ODE; the velocities along the way are kept (Eq. 9 reuses them).
    Returns (rl.Rollouts, velocities (S, n, ...))."""
    vs = []

    def v(x, t):
        vs.append(net(x, t, c))
        return vs[-1]

    with torch.no_grad():
        if noises is not None:
            xs, ts, log_probs = flow.sample_sde(v, x_0, train_steps(args), args.noise_level, noises=noises)
        else:
            (xs, ts), log_probs = flow.sample_ode(v, x_0, train_steps(args), return_trajectory=True), None
    return rl.Rollouts(xs, ts, c, log_probs, args.noise_level), torch.stack(vs)


def _update(step: int, opt, params, parts: list, loss_of, gen: torch.Generator, what: str) -> tuple:
    """One optimizer step on this process's micro-batches (--micro_batch). Each part's loss is backpropagated
    weighted by its share of the rows: every loss here is a mean over rows, so the summed gradient is the whole
    batch's. Each part starts from the same generator state, so it draws what the whole batch draws and keeps its
    own rows (part.shard, as processes do: rl.Rollouts.shard). Then the LoRA gradients are averaged over processes
    (the same update a single process makes on the whole batch), clipped (Table 3: max grad norm 1), and stepped.
    loss_of(part) -> (loss, info). Returns (loss, grad norm, info), loss and info as weighted means over parts."""
    opt.zero_grad(set_to_none=True)
    draws, total, info = gen.get_state(), 0.0, {}
    for p in parts:
        gen.set_state(draws)
        loss, part_info = loss_of(p)
        _check_finite(step, f"{what} loss", loss.detach())
        (loss * p.share).backward()
        total += loss.item() * p.share
        for k, v in part_info.items():
            info[k] = info.get(k, 0.0) + v * p.share
    if dist.is_initialized():
        for p in params:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            dist.all_reduce(p.grad)
            p.grad /= _world()
    gnorm = torch.nn.utils.clip_grad_norm_(params, 1.0)
    opt.step()
    return total, float(gnorm), info


def _mean(x: torch.Tensor) -> float:
    return float(torch.nanmean(x)) if torch.isfinite(x).any() else float("nan")


def _group_batch(net, frame0, tasks, descs, args: Args, gen, sde: bool, prompts=None) -> SimpleNamespace:
    """Alg. 1 lines 3-5's batch: each (image, T, D) repeated group_size times, this process's rows of it, and the
    step's sampling noise. `prompts`: the Executor's text per task (a control's, Args.executor_prompt); None = T. The noise is drawn for the whole batch on the CPU generator (so every process, on any
    device, draws the same numbers) and this process keeps its rows, moved to the network's device."""
    G, N = args.group_size, len(tasks) * args.group_size
    off, n = _shard(N)
    rows, dev = slice(off, off + n), next(net.parameters()).device
    x_0 = torch.randn(N, *net.latent_shape(), generator=gen)
    noises = torch.randn(train_steps(args), N, *net.latent_shape(), generator=gen) if sde else None
    return SimpleNamespace(
        N=N, n=n, rows=rows, shard=(off, N), groups=torch.arange(N) // G,
        frame0=np.repeat(frame0, G, axis=0)[rows], tasks=[t for t in tasks for _ in range(G)][rows],
        descs=[d for d in descs for _ in range(G)][rows],
        prompts=[q for q in (tasks if prompts is None else prompts) for _ in range(G)][rows],
        x_0=x_0[rows].to(dev), noises=None if noises is None else noises[:, rows].to(dev))


def _parts(net, b: SimpleNamespace, args: Args, executor: bool = True) -> list:
    """This process's b.n rows of a step in micro-batches of at most --micro_batch (0: one part), each with its
    conditions -- c_E (the Executor's prompts; not for a Demonstrator round) and c_D (the descriptions) -- its share
    of the rows, and `shard`: where its rows lie in the whole batch of b.N (their random draws are the batch's).
    The conditions are computed once per distinct (image, prompt) of this process (models.distinct_condition), not
    once per rollout of a group, and each part takes its rows of them."""
    m = args.micro_batch or b.n
    c_E, i_E = models.distinct_condition(net, b.frame0, b.prompts) if executor else (None, None)
    c_D, i_D = models.distinct_condition(net, b.frame0, b.descs)
    parts = []
    for i in range(0, b.n, m):
        r = slice(i, min(i + m, b.n))
        parts.append(SimpleNamespace(rows=r, share=(r.stop - r.start) / b.n, shard=(b.shard[0] + i, b.N),
                                     c_E=models.condition_rows(c_E, i_E[r]) if executor else None,
                                     c_D=models.condition_rows(c_D, i_D[r])))
    return parts


def _sample_parts(net, parts: list, b: SimpleNamespace, args: Args, cond: str) -> np.ndarray:
    """Alg. 1 line 5 on each part under its condition `cond` ("c_E" or "c_D"): part.ro (rl.Rollouts, sharded as
    its rows) and part.vs (the velocities along the way). Returns the decoded videos of all parts, in row order."""
    for p in parts:
        p.ro, p.vs = _rollouts(net, getattr(p, cond), b.x_0[p.rows], args,
                               None if b.noises is None else b.noises[:, p.rows])
        p.ro.shard = p.shard
    return np.concatenate([net.decode(p.ro.x1, b.frame0[p.rows]) for p in parts])


def rl_step(step: int, model, opt, params, args: Args, cfg: rl.RLConfig, frame0, tasks, descs, gen,
            teacher=None, prompts=None) -> dict:
    """One Executor iteration of Alg. 1 (Alg. 2 lines 18-25) on tasks_per_step (image, T, D), each repeated
    group_size times; split across processes under torchrun, and within a process into --micro_batch parts.
    `teacher`: a trained Demonstrator (Alg. 2); None = the base with adapters off. `prompts`: the Executor's text
    per task (a control's, Args.executor_prompt); None = T, the paper's c_E. The judges judge T either way."""
    sde = args.executor_update != "off" and (args.trainer in rl.NEEDS_SDE or args.sampler == "sde")
    b = _group_batch(model, frame0, tasks, descs, args, gen, sde, prompts)
    N, n, rows, groups, tasks = b.N, b.n, b.rows, b.groups, b.tasks
    parts = _parts(model, b, args)
    t0 = time.time()
    if args.executor_update == "off":   # setting (iii): the Executor only imitates the teacher's trajectories, Eq. 3
        def off_policy(p):
            traj, v_D = distill.rollout(model, b.x_0[p.rows], p.c_D, train_steps(args), demonstrator=True,
                                        velocities=True, teacher=teacher)
            return distill.off_policy_loss(model, traj, p.c_E, p.c_D, gen, teacher, p.shard, state_window(args),
                                           args.distill_motion_weight, teacher_v=v_D), {}
        loss, gnorm, _ = _update(step, opt, params, parts, off_policy, gen, "off-policy")
        return {"loss": _mean_over_processes(loss), "grad_norm": gnorm, "sample_s": time.time() - t0}
    videos = _sample_parts(model, parts, b, args, "c_E")
    t1 = time.time()
    # lines 6-8: judges, r_distill (Eq. 9), advantages of the Eq. 10 reward -- over the whole group
    local = judge_rollouts(videos, tasks, args.task_reward, weighed_pick(args))
    moved = bench.moved_pixels(videos, (bench.MOTION_LEVEL, bench.STILL_LEVEL))   # one pass over the videos
    local["motion"] = torch.tensor(moved[:, 0], dtype=torch.float32)
    local["still"] = torch.tensor(moved[:, 1] == 0, dtype=torch.float32)
    for p in parts:   # the Demonstrator along the Executor's trajectories: Eq. 9 uses them all, Eq. 11 one each
        p.vD = distill.teacher_velocities(model, (p.ro.xs, p.ro.ts), p.c_D, teacher) if args.lambda_distill > 0 else None
    local["distill"] = local["r_distill"] = torch.zeros(n)
    if args.lambda_distill > 0:   # Eq. 9's terms (n, S): their sum is r_distill; App. A.3 credits them per transition
        terms = torch.cat([distill.distill_reward(model, (p.ro.xs, p.ro.ts), p.c_E, p.c_D, per_step=True,
                                                  student_v=p.vs, teacher_v=p.vD,
                                                  motion_weight=args.distill_motion_weight) for p in parts]).cpu()
        local["distill"] = local["r_distill"] = terms.sum(1)
        if args.distill_reward == "per_step":
            local["distill"] = distill.distill_reward_to_go(terms)
    # every reward lives on the CPU beside the judges' (advantages are computed there, then sent to the device)
    rewards = {k: _gather(v) for k, v in local.items()}
    for k in ("task", "consistency", "pick"):
        _check_finite(step, f"reward r_{k}", rewards[k], skip=rewards["invalid"])
    _check_finite(step, "reward r_distill", rewards["distill"])
    weights = {"task": args.lambda_task, "distill": args.lambda_distill, "consistency": args.lambda_cons}
    if weighed_pick(args) is not None:
        weights["pick"] = args.lambda_pick              # Table 3's third reward
    anchor = anchor_only(args)   # no reward weighed: no advantages, no L_RL, Eq. 11 alone
    A_all = (torch.zeros(N) if anchor else
             rl.advantages({k: rewards[k] for k in weights}, weights, groups, args.adv_agg, args.adv_clip))
    _check_finite(step, "advantage", A_all)
    A = A_all[rows].to(b.x_0.device)
    t2 = time.time()

    def wmsd(p):   # lines 9-11: L_RL, the anchor (Eq. 11) on the rollouts' own states, Eq. 12
        l_rl, info = ((torch.zeros((), device=A.device), {}) if anchor else
                      rl.OBJECTIVES[args.trainer](model, p.ro, A[p.rows], cfg, gen))
        l_anchor = (distill.anchor_loss(model, (p.ro.xs, p.ro.ts), p.c_E, p.c_D, gen, teacher, p.shard,
                                        state_window(args), args.distill_motion_weight, teacher_v=p.vD)
                    if args.beta_d > 0 else None)
        info["l_rl"] = l_rl.item()
        if l_anchor is not None:
            info["l_anchor"] = l_anchor.item()
        return rl.final_loss(l_rl, l_anchor, args.beta_d), info

    for _ in range(args.inner_epochs):
        loss, gnorm, info = _update(step, opt, params, parts, wmsd, gen, "Executor")
    l_rl, l_anchor = info.pop("l_rl"), info.pop("l_anchor", None)
    return {"loss": _mean_over_processes(loss), "l_rl": _mean_over_processes(l_rl),
            "l_anchor": None if l_anchor is None else _mean_over_processes(l_anchor),
            "grad_norm": gnorm, "r_task": _mean(rewards["task"]), "r_cons": _mean(rewards["consistency"]),
            **({"r_pick": _mean(rewards["pick"])} if weighed_pick(args) is not None else {}),
            "r_distill": float(rewards["r_distill"].mean()), "solved": _mean(rewards["solved"]),
            "invalid": int(rewards["invalid"].sum()), "judge_errors": int(rewards["judge_errors"].sum()),
            "adv_abs": float(A_all.abs().mean()),
            # the collapse to still videos (docs/given-t.md), step by step: how many rollouts show nothing moving
            # (bench.still_videos), their mean motion (bench.moved_pixels at bench.MOTION_LEVEL), and how far A points
            # towards less motion (bench.pull, as bench.py --rank_rdistill)
            "still": int(rewards["still"].sum()), "motion": float(rewards["motion"].mean()),
            "still_push": bench.pull(A_all, (-rewards["motion"]).tolist(), groups) if A_all.dim() == 1 else None,
            "A": [round(a, 6) for a in A_all.tolist()] if A_all.dim() == 1 else [[round(a, 6) for a in row]
                                                                                 for row in A_all.tolist()],
            "rollouts_per_s": N / max(t1 - t0, 1e-9),
            "sample_s": t1 - t0, "reward_s": t2 - t1, "update_s": time.time() - t2,
            **{k: _mean_over_processes(v) for k, v in info.items()}}


def demonstrator_round(step: int, demo, opt, params, args: Args, cfg: rl.RLConfig, frame0, tasks, descs,
                       gen) -> dict:
    """Alg. 2 lines 11-16: the Demonstrator phi (base + its own LoRA) rolls out under c_D, is judged on the task T,
    and is updated by L_RL(phi) + beta_phi L_base, where L_base is the anchor of Eq. 11 with the *base* f_0 (phi's
    adapters off) as the reference, on phi's own states, under c_D."""
    b = _group_batch(demo, frame0, tasks, descs, args, gen, args.trainer in rl.NEEDS_SDE or args.sampler == "sde")
    parts = _parts(demo, b, args, executor=False)
    judged = judge_rollouts(_sample_parts(demo, parts, b, args, "c_D"), b.tasks, args.task_reward,
                            weighed_pick(args))
    rewards = {k: _gather(v) for k, v in judged.items()}
    weights = {"task": args.lambda_task, "consistency": args.lambda_cons}
    if weighed_pick(args) is not None:
        weights["pick"] = args.lambda_pick              # in phi's rounds too
    A_all = rl.advantages({k: rewards[k] for k in weights}, weights, b.groups, args.adv_agg, args.adv_clip)
    _check_finite(step, "Demonstrator advantage", A_all)
    A = A_all[b.rows].to(b.x_0.device)

    def alg2(p):
        l_rl, _ = rl.OBJECTIVES[args.trainer](demo, p.ro, A[p.rows], cfg, gen)
        l_base = distill.anchor_loss(demo, (p.ro.xs, p.ro.ts), p.c_D, p.c_D, gen, shard=p.shard)   # phi vs f_0, c_D
        return rl.final_loss(l_rl, l_base, args.beta_phi), {}

    loss, gnorm, _ = _update(step, opt, params, parts, alg2, gen, "Demonstrator")
    return {"demo_round": True, "loss": _mean_over_processes(loss), "grad_norm": gnorm,
            "r_task": _mean(rewards["task"]), "r_cons": _mean(rewards["consistency"]),
            **({"r_pick": _mean(rewards["pick"])} if weighed_pick(args) is not None else {}),
            "solved": _mean(rewards["solved"])}


# ---- the run: state checkpoints, resume, the loop -------------------------------------------------------------------

# these change memory or speed, not the numbers: a resumed run may change them
_RESUME_FREE = ("resume", "steps", "threads", "run_dir", "out", "log_every", "save_every", "eval_every", "toy",
                "eval_cache", "keep_executors", "micro_batch", "grad_checkpoint", "offload_text", "offload_judge")


def run_state_path(args: Args) -> str:
    """Where the rl stage, and a distill run of one variant, keep the resumable state (--save_every, --resume; main's
    Ctrl-C line points to it)."""
    return os.path.join(args.run_dir, "state.pt")


def save_state(path: str, step: int, model, opt, demo_net, demo_opt, rng, gen, evals: list, fixed: dict,
               args: Args, ema: list | None = None) -> None:
    """Everything a resumed run needs, written atomically (temp file + rename): the LoRA weights (the base is the
    --init checkpoint; under --executor_weights all, every weight), optimizer state, the LoRA and optimizer of the
    second network trained beside the Executor (demo_net: Alg. 2's Demonstrator phi under --alternate, or the DMD
    variant's fake score), the Executor's EMA under --executor_ema, every RNG state, the evaluations so far, the
    run's fixed evaluations (those it does not repeat on resuming) and the step."""
    lora = lambda m: {k: v.detach().clone() for k, v in m.state_dict().items() if "lora_" in k}  # noqa: E731
    trained = model.state_dict() if args.executor_weights == "all" else lora(model)    # what the Executor trains
    state = {"step": step, "lora": trained, "opt": opt.state_dict(),
             "demo_lora": lora(demo_net) if demo_net is not None else None,
             "demo_opt": demo_opt.state_dict() if demo_opt is not None else None,
             "rng_numpy": rng.bit_generator.state, "gen": gen.get_state(), "torch_rng": torch.get_rng_state(),
             "py_random": random.getstate(), "evals": evals, "fixed": fixed, "args": dataclasses.asdict(args),
             "ema": ema}
    models.atomic_save(state, path)


def load_state(path: str, args: Args) -> dict:
    """Read a state written by save_state; a clear error if it is missing, corrupt, or from a different run."""
    if not os.path.isfile(path):
        raise ValueError(f"--resume: no state to resume at {path!r}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        step, saved = int(state["step"]), state["args"]
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"--resume: {path!r} is corrupt: {models.load_error(e)}") from None
    default = dataclasses.asdict(Args())   # a setting the state lacks did not exist when it was written: its default
    diff = [k for k, v in dataclasses.asdict(args).items()
            if k not in _RESUME_FREE and saved.get(k, default[k]) != v]
    if diff:
        raise ValueError(f"--resume: {path!r} was written with different settings: "
                         + ", ".join(f"--{k} {saved.get(k, default[k])!r} (now {getattr(args, k)!r})" for k in diff))
    if step >= args.steps:
        raise ValueError(f"--resume: the saved run already reached step {step} of --steps {args.steps}")
    return state


def restore_state(state: dict, model, opt, demo_net, demo_opt, rng, gen, ema: list | None) -> int:
    """Put every piece save_state kept back where the interrupted run left it (the EMA in place); returns the step
    to go on from."""
    model.load_state_dict(state["lora"], strict=False)
    opt.load_state_dict(state["opt"])
    if ema is not None:     # the state was loaded to the CPU; the average lives beside its weights
        with torch.no_grad():
            for e, saved in zip(ema, state["ema"]):
                e.copy_(saved)
    if demo_net is not None:
        demo_net.load_state_dict(state["demo_lora"], strict=False)
        demo_opt.load_state_dict(state["demo_opt"])
    rng.bit_generator.state = state["rng_numpy"]
    gen.set_state(state["gen"])
    torch.set_rng_state(state["torch_rng"])
    random.setstate(state["py_random"])
    return state["step"] + 1


def keep_logged_steps(path: str, first: int) -> None:
    """Cut a resumed run's JSON-lines log to the steps its state has seen (those before `first`): the steps logged
    after the last save are run, and logged, again."""
    lines = open(path).read().splitlines()
    with open(path, "w") as f:
        f.writelines(line + "\n" for line in lines if json.loads(line)["step"] < first)


def refuse_to_overwrite(path: str) -> None:
    """A run started afresh (no --resume) in a --run_dir whose state.pt is an unfinished run's would overwrite that
    state at its first save, and the unfinished run could never be resumed: refused, naming the ways on. A finished
    run's state (its step = its --steps), or one that cannot be read, is overwritten as the run's other files are."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        step, steps = int(state["step"]), int(state["args"]["steps"])
    except Exception:  # noqa: BLE001 -- no state, or none to resume from
        return
    if step < steps:
        raise ValueError(f"--run_dir {os.path.dirname(path) or '.'!r} holds an unfinished run (its state.pt: step "
                         f"{step} of {steps}); continue it with --resume and its settings, give this run another "
                         f"--run_dir, or delete {path!r} to start afresh here")


def load_base(args: Args):
    """The base video model named by --model (the Executor and, adapters off, the Demonstrator)."""
    if args.model == "toy":
        model = models.load_checkpoint(args.init or None)[0]
        return model.to("cuda") if args.toy_gpu else model
    return load_real(args)


def load_real(args: Args):
    """A real --model (or its tiny or random stand-in), on the GPU where there is one, with its memory flags. An
    --eval_height and --eval_width its VAE cannot take are a ValueError here, before any work."""
    cuda = torch.cuda.is_available()   # a real model, or its tiny or random stand-in, runs on the GPU when there is one
    if args.model.endswith("-tiny"):
        model = REAL_MODELS[args.model[:-len("-tiny")]].tiny(world.VOCAB + ["[", "]:"], seed=args.seed)
        model = model.to("cuda") if cuda else model
    elif args.model.endswith("-random"):   # real sizes, built on the GPU directly, in bf16
        model = REAL_MODELS[args.model[:-len("-random")]].random(world.VOCAB + ["[", "]:"], seed=args.seed)
    else:
        model = REAL_MODELS[args.model].from_pretrained(args.model_path, device="cuda" if cuda else "cpu")
    if args.grad_checkpoint:       # recomputed in the backward pass: only with gradients on, so sampling is unchanged
        model.transformer.enable_gradient_checkpointing()
    if args.offload_text:
        models.offload(model.text_encoder)
    if args.eval_height:          # Table 3's evaluation size, tried once
        with models.resolution(model, args.eval_height, args.eval_width):
            pass
    return model


def load_pairs(args: Args, model) -> list:
    """Alg. 1 lines 3-4's (image, T, D): the toy VLM's pairs, or a WorldTasks JSONL file (--dataset)."""
    if not args.dataset:
        return toy_pairs(args)
    return dataset_pairs(args.dataset, model, args.tasks_per_step, "--tasks_per_step")


def toy_pairs(args: Args) -> list:
    """The toy VLM's training pairs: --train_pairs of them, on scenes disjoint from the bench (--train_crowded: on
    5-sprite scenes disjoint from the crowded bench). With --train_arrangements M > 1, the first --train_pairs / M
    of them, each followed by M - 1 new places of its sprites (world.arrangements, drawn from the run's seed; no
    place twice, none a bench scene or another task's scene)."""
    m = args.train_arrangements
    pairs = world.train_pairs(args.train_pairs // m, seed=args.seed + 1, error_rate=args.error_rate,
                              crowded=args.train_crowded)
    if m == 1:
        return pairs
    rng = np.random.default_rng([args.seed, 7])
    avoid = set(world.bench_scene_keys(args.train_crowded)) | {world.scene_key(p.scene) for p in pairs}
    return [q for p in pairs for q in (p, *world.arrangements(p, m - 1, rng, avoid))]


def dataset_pairs(path: str, model, need: int, flag: str, size: tuple | None = None) -> list:
    """The rows of a WorldTasks JSONL file as (image, T, D) pairs, the images resized to the model's resolution (or
    to `size`, (width, height): a bench evaluated at another, --eval_height); a clear error naming the line of a bad
    row, or if there are fewer than `need` rows (`flag` asks for them)."""
    size = size or (getattr(model, "width", world.W), getattr(model, "height", world.H))     # (width, height)
    rows = world.load_dataset(path)
    for r in rows:   # what the model would refuse mid-run, said now with its line
        try:
            if model.backend == "toy":          # the toy world's agents and instructions only
                world.parse_task(r["task"])
            model.check_prompts([r["task"], r["description"]])   # the toy's words; a real text path's length
            with Image.open(r["image"]) as img:   # OSError: not an image PIL reads, or one cut short
                r["frame0"] = np.asarray(img.convert("RGB").resize(size, Image.BILINEAR))
        except (ValueError, OSError) as e:
            raise ValueError(f"{path} line {r['line']}: {e}") from None
    if len(rows) < need:
        raise ValueError(f"dataset {path!r} has {len(rows)} rows, fewer than {flag} {need}")
    return [SimpleNamespace(frame0=r["frame0"], task=SimpleNamespace(text=r["task"], **task_groups(r)),
                            d_vlm=r["description"], image=r["image"])
            for r in rows]


def task_groups(row: dict) -> dict:
    """Fig. 7's subgroups of a WorldTasks row: family (its task type) and agent_type, the taxonomy's categories where
    the row carries them (world.classify_tasks; world.UNCLASSIFIED for a malformed answer), else the keyword family
    and no agent type (bench.agent_type_scores: "other agent"); agent, the name in T's brackets."""
    if "task_type" in row:
        family, agent_type = row["task_type"] or world.UNCLASSIFIED, row.get("agent_type") or world.UNCLASSIFIED
    else:
        family, agent_type = row.get("family") or world.task_family(row["task"]), None
    return dict(family=family, agent_type=agent_type, agent=world.split_task(row["task"])[0])


def sft_rows(path: str, model, need: int) -> list[dict]:
    """--sft_dataset's rows, {"video": path, "task": T}, every one checked before training starts: JSON with the two
    fields, a video file (world.video_length) of the model's frame count, a task the model's text path takes. A bad
    row is a ValueError naming its line (world.read_jsonl); fewer than `need` rows (--batch) is one too."""
    def check(r: dict) -> dict:
        if not (isinstance(r, dict) and isinstance(r.get("video"), str) and isinstance(r.get("task"), str)):
            raise ValueError('a row is {"video": FILE, "task": T}')
        r = {"video": os.path.join(os.path.dirname(path), r["video"]), "task": r["task"]}
        if (n := world.video_length(r["video"])) != model.frames:
            raise ValueError(f"{r['video']} has {n} frames; the model makes {model.frames}")
        model.check_prompts([r["task"]])
        return r
    rows = [r for _, r in world.read_jsonl(path, "--sft_dataset", check)]
    if len(rows) < need:
        raise ValueError(f"--sft_dataset {path!r} has {len(rows)} videos, fewer than --batch {need}")
    return rows


def load_bench(args: Args, model, train: list) -> list | None:
    """--eval_dataset's first --eval_n rows, the bench every evaluation uses; None: the toy bench. A row that is
    also a training row of `train` (load_pairs; same image and task) is an error: the bench is held out."""
    if not args.eval_dataset:
        return None
    size = (args.eval_width, args.eval_height) if args.eval_height else None     # the frames at the bench's size
    pairs = dataset_pairs(args.eval_dataset, model, args.eval_n, "--eval_n", size)[:args.eval_n]
    if train:       # --dataset's rows (the toy VLM's pairs and SFT videos have no image file to share)
        train_rows = {(p.image, p.task.text) for p in train}
        shared = [p for p in pairs if (p.image, p.task.text) in train_rows]
        if shared:
            raise ValueError(f"{len(shared)} of the {len(pairs)} bench rows of {args.eval_dataset!r} are also "
                             f"--dataset rows (first: {shared[0].task.text!r}); the bench must be held out")
    return pairs


def rl_stage(args: Args) -> dict:
    """Alg. 1 from the shipped base (or --executor_init's Executor): every step samples tasks_per_step (image, T, D)
    from the toy VLM's pairs (lines 3-4), rolls out groups, judges, computes r_distill and advantages, and updates the
    Executor's LoRA (or every weight) by L_RL + beta_d L_anchor (Eq. 12). Evaluates every eval_every steps; saves a
    resumable state every save_every steps; ends with the bench table (Base given T, Demonstrator given the toy VLM's
    D, Executor given T), a curve, a GIF and the Executor checkpoint (LoRA merged: loadable by bench.py). Under
    torchrun the rollouts of each step are split across processes and rank 0 alone evaluates and writes."""
    _dist_init()
    rank0 = _rank() == 0
    say = print if rank0 else (lambda *a, **k: None)
    rng = seed_everything(args.seed, args.threads)
    gen = torch.Generator().manual_seed(args.seed)
    state_path = run_state_path(args)
    if not args.resume:
        refuse_to_overwrite(state_path)
    state = load_state(state_path, args) if args.resume else None
    start = time.time()
    global JUDGE, BENCH, PICK
    model = load_base(args)   # a bad checkpoint, missing weights or an --eval_height the VAE cannot take stop here,
    start_from = executor_start(args, model)                  # and so does a bad --executor_init, before any writing
    JUDGE, PICK = make_judge(args), make_pick(args)
    pairs = load_pairs(args, model)
    BENCH = load_bench(args, model, pairs if args.dataset else [])
    if BENCH is None and args.model != "toy":
        say("note: no --eval_dataset, so this real model is evaluated on the toy bench's sprite frames", flush=True)
    if rank0:
        os.makedirs(args.run_dir, exist_ok=True)
    keys = (*EVAL_KEYS, *(("pick",) if PICK is not None else ()), "seconds_per_video")
    given = EXECUTOR_PROMPTS[args.executor_prompt]
    base_row = f"Base ({given})"
    if state is not None:
        fixed = state["fixed"]
    elif rank0:
        fixed = {base_row: base_evaluation(model, args),             # no adapters yet: the base given T
                 bench.DEMO_ROW: base_evaluation(model, args, demonstrator=True)}
        fixed = {name: {k: r[k] for k in keys} for name, r in fixed.items()}
    else:
        fixed = {}
    demo_net = demo_opt = demo_params = None
    if args.alternate > 0:       # Alg. 2: a Demonstrator phi of its own, trained in every N-th iteration
        demo_net = models.copy_for_adapter(model)
        models.add_lora(demo_net, args.lora_rank, args.lora_alpha, convs=args.lora_convs,
                        embeddings=args.lora_embeddings)
        demo_params = models.lora_parameters(demo_net)
        demo_opt = torch.optim.Adam(demo_params, lr=args.lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=1e-4)
    params, frozen = executor_parameters(model, args, start_from)
    opt = torch.optim.Adam(params, lr=args.lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=1e-4)  # Table 3
    # the Demonstrator of Eqs. 9, 11: the fixed base (None: adapters off; or its frozen copy under --executor_weights
    # all), Alg. 2's phi, or the Executor itself (A.3)
    teacher = demo_net if demo_net is not None else (model if args.demonstrator == "executor" else frozen)
    ema = [p.detach().clone() for p in params] if args.executor_ema else None   # Table 3's EMA, from the base
    cfg = rl_config(args)
    first, log_mode, evals = 1, "w", []
    if state is not None:
        first = restore_state(state, model, opt, demo_net, demo_opt, rng, gen, ema)
        evals, log_mode = state["evals"], "a"
        if rank0:
            keep_logged_steps(os.path.join(args.run_dir, "rl.jsonl"), first)
        say(f"resumed {state_path} at step {first - 1}")
    elif rank0:        # step 0: the base given T, or the --executor_init Executor's evaluation
        at_0 = fixed[base_row] if start_from is None else evaluate_executor(model, args)
        evals = [{"step": 0, **{k: at_0[k] for k in eval_keys(at_0)}}]
    demo = fixed.get(bench.DEMO_ROW, {})
    if rank0:
        say(f"{len(pairs)} training pairs{' on crowded scenes' if args.train_crowded else ''}; {_world()} "
            f"process(es); {'on the crowded bench, ' if args.eval_crowded else ''}base given {given}: task "
            f"{fixed[base_row]['task']:.3f} consistency {fixed[base_row]['consistency']:.3f}; Demonstrator (toy "
            f"VLM's D): task "
            f"{demo['task']:.3f} consistency {demo['consistency']:.3f}  [{time.time() - start:.0f} s]", flush=True)
    if rank0 and start_from is not None and state is None:   # rank 0 alone holds the evaluations
        say(f"  eval step 0 (--executor_init, given {given}): {eval_line(evals[0])}", flush=True)
    logf = open(os.path.join(args.run_dir, "rl.jsonl"), log_mode) if rank0 else None
    if logf and first == 1:
        logf.write(json.dumps({"eval": True, **evals[0]}) + "\n")
    loop_start = time.time()
    for step in range(first, args.steps + 1):
        t0 = time.time()
        if torch.cuda.is_available():
            torch.cuda.reset_peak_memory_stats()
        idx = rng.choice(len(pairs), args.tasks_per_step, replace=False)
        frame0, tasks, descs = _batch(pairs, idx)
        prompts = None if args.executor_prompt == "task" else bench.prompts_for([pairs[i] for i in idx],
                                                                                 args.executor_prompt)
        try:
            if args.alternate > 0 and step % args.alternate == 0:
                rec = demonstrator_round(step, demo_net, demo_opt, demo_params, args, cfg, frame0, tasks, descs, gen)
            else:
                rec = rl_step(step, model, opt, params, args, cfg, frame0, tasks, descs, gen, teacher=teacher,
                              prompts=prompts)
        except TrainingFault as e:
            last = f"the last good state {state_path} is intact" if os.path.exists(state_path) else \
                "no state was saved yet (--save_every)"
            raise TrainingFault(f"{e}; stopping -- {last}") from None
        executor_updates = step - (step // args.alternate if args.alternate else 0)   # Alg. 2's rounds are phi's
        if ema is not None and not rec.get("demo_round") and executor_updates % args.executor_ema_every == 0:
            done = executor_updates // args.executor_ema_every - 1   # EMA updates before this one
            ema_step(ema, params, executor_ema_decay(args.executor_ema, args.executor_ema_schedule, done))
        rec = {"step": step, **rec, "step_seconds": time.time() - t0}
        if torch.cuda.is_available():   # the step's high-water mark of tensors on this process's GPU, GiB
            rec["gpu_peak_gb"] = torch.cuda.max_memory_allocated() / 2 ** 30
        if logf:
            logf.write(json.dumps(rec) + "\n")
            logf.flush()
        what = ("Demonstrator round | " if rec.get("demo_round") else "") + " ".join(
            f"{k} {rec[k]:+.3f}" for k in ("r_task", "solved", "r_cons", "r_pick", "r_distill") if k in rec) + (
            f" still {rec['still']}" if "still" in rec else "")
        say(f"step {step:4d}/{args.steps} | {what} | loss {rec['loss']:+.4f} grad {rec['grad_norm']:.2f} | "
            f"{rec['step_seconds']:.1f} s" + (f" ({rec['sample_s']:.1f} sampling, {rec['reward_s']:.1f} rewards, "
                                               f"{rec['update_s']:.1f} update)" if "reward_s" in rec else "")
            + (f" | GPU peak {rec['gpu_peak_gb']:.1f} GiB" if "gpu_peak_gb" in rec else "")
            + f" | {_eta(loop_start, step - first + 1, args.steps - first + 1)}", flush=True)
        if step % args.eval_every == 0 and step < args.steps:    # the last step's is the final evaluation's
            if rank0:
                with weights_swapped(params, ema):
                    if args.keep_executors:
                        keep_executor(model, executor_path(args, args.trainer), step, executor_meta(args, "rl"))
                    res = evaluate_executor(model, args)
                evals.append({"step": step, **{k: res[k] for k in eval_keys(res)}})
                logf.write(json.dumps({"eval": True, **evals[-1]}) + "\n")
                say(f"  eval step {step}: {eval_line(res)}", flush=True)
            if dist.is_initialized():
                dist.barrier()
        if rank0 and (step % args.save_every == 0 or step == args.steps):
            logf.flush()      # the log on disk holds every step the state has seen
            save_state(state_path, step, model, opt, demo_net, demo_opt, rng, gen, evals, fixed, args, ema)
    if dist.is_initialized():   # the last collective is behind us: every process leaves the group together
        dist.barrier()          # (how a process then exits: main, which skips Python's finalization under torchrun)
        dist.destroy_process_group()
    if not rank0:
        return {}
    out = executor_path(args, args.trainer)
    with weights_swapped(params, ema):   # the Executor that is saved and judged: the average, under --executor_ema
        merged = save_executor(model, out, executor_meta(args, "rl"))
        final = evaluate_executor(merged, args)     # the last point of the curve too: the same network, merged
        write_rollout_gif(model, os.path.join(args.run_dir, "rollouts_rl.gif"), args)
    evals = ([e for e in evals if e["step"] != args.steps]
             + [{"step": args.steps, **{k: final[k] for k in eval_keys(final)}}])
    logf.write(json.dumps({"eval": True, **evals[-1]}) + "\n")
    logf.close()
    say(f"  eval step {args.steps}: {eval_line(final)}", flush=True)
    trainer = "" if anchor_only(args) or not reward_weights(args) else f"{args.trainer}, "   # no L_RL: no trainer
    every = ", every weight" if args.executor_weights == "all" else ""
    every += f" from {os.path.basename(args.executor_init)}" if args.executor_init else ""
    name = f"{fig5_setting(args)} ({trainer}{given}{every}{f', EMA {args.executor_ema}' if ema else ''})"
    rows = {**fixed, name: {k: final[k] for k in keys}}
    if demo_net is not None:
        rows["trained Demonstrator phi (toy VLM's D)"] = {
            k: v for k, v in evaluate_executor(demo_net, args, demonstrator="trained").items() if k in keys}
    if BENCH is not None:   # the Demonstrator's D is the bench file's, written by whatever VLM made it
        rows = {name.replace(bench.given_d("toy"), bench.given_d("file")): r for name, r in rows.items()}
    pick = PICK is not None      # PickScore's column (Fig. 4's quality measure)
    table = [f"| model | task | agent | consistency | avg | still |{' pick |' if pick else ''} s/video |",
             "|---|---|---|---|---|---|---|" + ("---|" if pick else "")]
    table += [f"| {name} | {r['task']:.3f} | {r['agent']:.3f} | {r['consistency']:.3f} | {r['avg']:.3f} | "
              f"{r.get('still', float('nan')):.3f} |"                         # nan: a state saved before the still
              + (f" {r['pick']:.3f} |" if pick else "") + f" {r['seconds_per_video']:.4f} |"   # count existed
              for name, r in rows.items()]
    summary = {"args": dataclasses.asdict(args), "evals": evals, "minutes": (time.time() - start) / 60,
               "table": rows}
    with open(os.path.join(args.run_dir, "rl_summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    steps = [r for r in map(json.loads, open(os.path.join(args.run_dir, "rl.jsonl"))) if "motion" in r]
    plot_rl_curve(evals, demo, os.path.join(args.run_dir, "rl_curve.png"), args, steps)
    print("\n".join(table))
    print("\n".join(f"the Executor: {line}" for line in bench.fig7_lines(final)))     # Fig. 7's two panels
    print(f"done in {summary['minutes']:.1f} min; wrote {out}, {args.run_dir}/rl.jsonl, state.pt, rl_curve.png, "
          f"rollouts_rl.gif, rl_summary.json")
    return summary


def plot_rl_curve(evals: list, demo: dict, path: str, args: Args, steps: list = ()) -> None:
    """The bench scores at each evaluation beside the Demonstrator's -- task, consistency, their average with the
    agent score and, where the run records it (--pick), PickScore: Fig. 4's two measures -- and a last panel for the
    collapse to still videos: the share of still videos on the bench and, step by step from `steps` (rl.jsonl's
    Executor records), the share of still training rollouts and their mean motion relative to the first 10 logged
    steps'."""
    keys = ("task", "consistency", "avg", *(("pick",) if all("pick" in e for e in evals) else ()))
    plt, fig, axes = bench.figure(len(keys) + 1, width=4)
    d = bench.given_d(args.eval_dataset)
    for ax, key in zip(axes, keys):
        ax.plot([e["step"] for e in evals], [e[key] for e in evals], marker="o", ms=3, label=f"Executor ({args.trainer})")
        ax.axhline(demo[key], color="k", ls="--", lw=1, label=f"Demonstrator ({d})")
        ax.set_xlabel("RL step")
        ax.set_ylabel("bench PickScore against T" if key == "pick" else f"bench {key} score")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    ax = axes[len(keys)]
    if steps:
        x = [r["step"] for r in steps]
        ax.plot(x, [r["still"] / len(r["A"]) for r in steps], lw=1, label="training rollouts still")
        first = max(np.mean([r["motion"] for r in steps[:10]]), 1e-9)   # one step's batch alone is noisy
        ax.plot(x, [r["motion"] / first for r in steps], lw=1, label="training rollouts' motion / first 10 steps'")
    ax.plot([e["step"] for e in evals], [e.get("still", float("nan")) for e in evals], "ko", ms=3,
            label="bench videos still")
    ax.set_xlabel("RL step")
    ax.set_ylabel("share")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    where = os.path.basename(args.eval_dataset) if args.eval_dataset else bench_title(args.eval_crowded)
    fig.suptitle(f"{fig5_setting(args)} on {where}: lambda_distill={args.lambda_distill}, "
                 f"beta_d={args.beta_d}, lambda_cons={args.lambda_cons}, seed {args.seed}\n"
                 f"Executor given {executor_given(args.executor_prompt)}")
    bench.save_figure(plt, fig, path)


STAGES = {"pretrain": pretrain, "distill": distill_stage, "rl": rl_stage}


def main(argv=None):
    args = parse_args(argv)
    print("config: " + json.dumps(dataclasses.asdict(args)))
    state = run_state_path(args)
    before = os.path.getmtime(state) if os.path.isfile(state) else None      # an earlier run's state, if any
    KEPT.clear()                                                              # this run's, not an earlier call's
    try:
        STAGES[args.stage](args)
    except (ValueError, FileNotFoundError) as e:   # bad settings, checkpoints or state: one line, exit 2
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except TrainingFault as e:                     # a non-finite quantity: one line, exit 1
        print(f"error: {e}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:                      # Ctrl-C: what is kept, exit 130 (128 + SIGINT) as a shell would
        ours = os.path.isfile(state) and (args.resume or os.path.getmtime(state) != before)   # saved or resumed
        kept = (f"{state} holds the last state saved (every --save_every steps): the same command with --resume "
                "continues from it") if ours else "no resumable state was saved"
        if KEPT:        # --keep_executors
            kept += f"; {KEPT[-1]} is the Executor of the last evaluation"
        print(f"\ninterrupted; {kept}", file=sys.stderr)
        sys.exit(130)
    if _under_torchrun():
        # Under torchrun a gloo worker thread can still hold the last reference to the final barrier, and through it
        # to the collectives before it and their tensors; freeing a tensor that Python has let go of takes the GIL.
        # If Python is finalizing by then, the thread is ended inside that C++ destructor and the process aborts
        # ("terminate called without an active exception": rank 1, 3 runs in 109 of the two-process test's command
        # on 2 cores, docs/timing.md). Every file is closed or flushed by now, so leave without finalizing.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


if __name__ == "__main__":
    main(sys.argv[1:])
