"""Training entry point. Stages so far:

  pretrain -- build the toy base model (the stand-in for downloaded LTX-2 weights, Sec. 3 "Setup"): rectified-flow
              training (App. A.9, flow.flow_matching_loss) of ToyVideoFlow on world videos captioned like the
              detailed description D, with a share of vague captions ("red square moves") and empty captions, as
              real video models see. It never sees a short task T. Writes checkpoints/base.pt (EMA weights).

  python train.py --stage pretrain --seed 0            # rebuilds checkpoints/base.pt (~10 min on 2 CPU cores)
  python train.py --toy                                # the laptop preset (pretraining until the WMSD stages land)

Self-distillation (distill.py) and RL (rl.py) stages are added by later issues.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import os
import random
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import torch

import flow
import models
import world


@dataclass
class Args:
    stage: str = "pretrain"
    """which stage to run: pretrain"""
    toy: bool = False
    """the laptop preset: the toy world and model on CPU (the values below are already the toy's)"""
    seed: int = 0
    """one seed for python, numpy and torch; a rerun with the same seed gives the same numbers on CPU"""
    threads: int = 2
    """torch CPU threads"""
    out: str = models.SHIPPED_BASE
    """where the trained checkpoint goes"""
    log: str = "runs/pretrain.jsonl"
    """metrics, one JSON object per logged step"""
    steps: int = 1500
    """optimizer steps"""
    batch: int = 32
    """videos per step"""
    lr: float = 1e-3
    """AdamW learning rate (linear warm-up over 100 steps, cosine decay to 10%)"""
    weight_decay: float = 0.0
    """AdamW weight decay"""
    ema: float = 0.995
    """EMA decay of the weights that are saved"""
    p_vague: float = 0.15
    """share of captions that name the mover but not the motion"""
    p_empty: float = 0.10
    """share of empty captions"""
    log_every: int = 50
    """steps between progress lines"""
    width: int = 32
    """U-Net channels at full resolution"""
    x_weighting: bool = True
    """weight the velocity loss by (1 - t)^2, i.e. the error of the predicted clean video x1_hat; the plain velocity
    loss puts weight 1/(1-t)^2 on nearly clean states and learns motion (decided at small t) slowly"""


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
                           choices=["pretrain"] if f.name == "stage" else None)
    args = Args(**vars(p.parse_args(argv)))
    for name in ("steps", "batch", "log_every", "threads", "width"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if not 0 <= args.p_vague + args.p_empty <= 1:
        p.error("--p_vague + --p_empty must lie in [0, 1]")
    if not 0 <= args.ema < 1:
        p.error("--ema must lie in [0, 1)")
    return args


def _field_docs(cls) -> dict:
    """The string literal under each dataclass field (its docstring)."""
    import ast
    import inspect
    tree = ast.parse(inspect.getsource(cls))
    body, docs = tree.body[0].body, {}
    for a, b in zip(body, body[1:]):
        if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant):
            docs[a.target.id] = b.value.value
    return docs


def seed_everything(seed: int, threads: int) -> np.random.Generator:
    random.seed(seed)
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    return np.random.default_rng(seed)


def _eta(start: float, done: int, total: int) -> str:
    el = time.time() - start
    return f"{el / 60:.1f} min, ETA {el / max(done, 1) * (total - done) / 60:.1f} min"


# ================================================================================================================
# stage: pretrain the base model
# ================================================================================================================

def pretrain(args: Args) -> dict:
    rng = seed_everything(args.seed, args.threads)
    model = models.make_model("toy", width=args.width)
    ema = copy.deepcopy(model).requires_grad_(False)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / 100) * (
        0.1 + 0.9 * 0.5 * (1 + np.cos(np.pi * min(s / args.steps, 1.0)))))
    exclude = world.bench_scene_keys()  # the bench's scenes are never seen in training
    print(f"pretraining {sum(p.numel() for p in model.parameters()) / 1e6:.2f}M parameters for {args.steps} steps")
    os.makedirs(os.path.dirname(args.log) or ".", exist_ok=True)
    logf, start, run_loss = open(args.log, "w"), time.time(), []
    for step in range(1, args.steps + 1):
        videos, captions = world.pretraining_batch(rng, args.batch, args.p_vague, args.p_empty, exclude)
        x_1 = model.encode_video(videos)                       # (B, T, 3, H, W) data
        c = model.condition(videos[:, 0], captions)
        x_0 = torch.randn_like(x_1)                            # noise
        t = torch.rand(args.batch)                             # t ~ U[0, 1]
        w = (1 - t).clamp(min=model.cfg.min_one_minus_t) ** 2 if args.x_weighting else None
        loss = flow.flow_matching_loss(lambda x, tt: model(x, tt, c), x_0, x_1, t, weight=w)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        with torch.no_grad():
            for pe, p in zip(ema.parameters(), model.parameters()):
                pe.lerp_(p, 1 - args.ema)
        run_loss.append(loss.item())
        if step % args.log_every == 0 or step == args.steps:
            rec = {"step": step, "loss": float(np.mean(run_loss)), "grad_norm": float(gnorm),
                   "lr": sched.get_last_lr()[0], "seconds": time.time() - start}
            logf.write(json.dumps(rec) + "\n")
            logf.flush()
            print(f"step {step:5d}/{args.steps} | loss {rec['loss']:.4f} | grad {rec['grad_norm']:.2f} | "
                  f"{_eta(start, step, args.steps)}", flush=True)
            run_loss = []
    minutes = (time.time() - start) / 60
    models.save_checkpoint(ema, args.out, {"stage": "pretrain", "args": dataclasses.asdict(args),
                                           "minutes": round(minutes, 2)})
    print(f"saved {args.out} after {minutes:.1f} min")
    return {"minutes": minutes}


def main(argv=None):
    args = parse_args(argv)
    print("config: " + json.dumps(dataclasses.asdict(args)))
    {"pretrain": pretrain}[args.stage](args)


if __name__ == "__main__":
    main(sys.argv[1:])
