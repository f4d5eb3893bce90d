"""Evaluate a checkpoint on the WorldTasks-toy bench (Sec. 4.1.2; the table format of Tab. 1 / App. A.4 Tab. 4).

One video per bench pair, generated from the pair's first frame and a prompt chosen by --condition:
  task    the short task T              ("Base" row of Tab. 1; the Executor's condition c_E)
  vlm     the toy VLM's description D   ("+VLM" row: the Demonstrator, reasoning outsourced to an imperfect VLM)
  oracle  the error-free description    (the Demonstrator with a perfect VLM -- an upper reference)
Each video is judged by reward.py on Task / Agent / Consistency (always against the task T). A score is
successes / valid judgments; failures (no judgment possible) are counted, as in Tab. 4. Avg is the mean of the
three scores; its successes/valid sum the per-video mean over videos with all three judgments valid.

  python bench.py --condition oracle --n 200 --seed 0            # the shipped base, error-free descriptions
  python bench.py --checkpoint runs/x.pt --condition task --json  # last line: one JSON object
  python bench.py --compare "WMSD=runs" "no anchor=runs/b" --png cmp.png   # curves + table of finished rl runs
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import torch

import models
import reward
import world

DEFAULT_ERROR_RATE = 0.3  # the toy VLM's share of wrong descriptions; chosen so the "+VLM" row lands in 0.45-0.70
KEYS = ("task", "agent", "consistency")


def prompts_for(pairs: list, condition: str) -> list[str]:
    return [{"task": p.task.text, "vlm": p.d_vlm, "oracle": p.d_oracle}[condition] for p in pairs]


def score_table(judgments: list[dict]) -> dict:
    """judgments: per video {task|agent|consistency: reward.Judgment} -> scores, successes, valid, failures."""
    succ = {k: sum(bool(j[k].yes) for j in judgments) for k in KEYS}
    valid = {k: sum(j[k].yes is not None for j in judgments) for k in KEYS}
    full = [j for j in judgments if all(j[k].yes is not None for k in KEYS)]
    succ["avg"] = float(sum(np.mean([bool(j[k].yes) for k in KEYS]) for j in full))
    valid["avg"] = len(full)
    out = {k: succ[k] / valid[k] if valid[k] else float("nan") for k in KEYS}
    out["avg"] = float(np.mean([out[k] for k in KEYS]))
    out.update(successes=succ, valid=valid, failures={k: len(judgments) - valid[k] for k in valid}, n=len(judgments))
    return out


def family_scores(pairs: list, judgments: list[dict]) -> dict:
    """Task score per task family (paper Fig. 7 left): {family: [successes, valid]}."""
    out = {f: [0, 0] for f in world.FAMILIES}
    for p, j in zip(pairs, judgments):
        if j["task"].yes is not None:
            out[p.task.family][0] += int(j["task"].yes)
            out[p.task.family][1] += 1
    return out


def evaluate(model, condition: str, n: int = 200, seed: int = 0, error_rate: float = DEFAULT_ERROR_RATE,
             steps: int = 10, judge=None) -> tuple[dict, np.ndarray, list]:
    """Generate and judge n bench videos (by reward.py's toy judges, or a reward.VLMJudge with the bench prompts of
    Figs. 15-17). Returns (result dict, videos uint8 (n, F, H, W, 3), pairs)."""
    pairs = world.bench_pairs(error_rate)[:n]
    frame0 = np.stack([p.frame0 for p in pairs])
    t0 = time.time()
    videos = models.generate(model, frame0, prompts_for(pairs, condition), steps=steps, seed=seed)
    seconds = time.time() - t0
    t1 = time.time()
    if judge is None:
        judgments = [reward.judge_all(v, p.task.text) for v, p in zip(videos, pairs)]
    else:
        judgments = judge.bench(videos, [p.task.text for p in pairs])
    res = score_table(judgments)
    res.update(condition=condition, seed=seed, error_rate=error_rate, steps=steps, seconds=seconds,
               seconds_per_video=seconds / max(n, 1), judge_seconds=time.time() - t1,
               families=family_scores(pairs, judgments))
    return res, videos, pairs


def format_table(res: dict, title: str = "") -> str:
    rows = [f"{title}condition={res['condition']} n={res['n']} seed={res['seed']} error_rate={res['error_rate']} "
            f"steps={res['steps']}",
            "| judgment    | score | successes/valid | failures |", "|---|---|---|---|"]
    for k in (*KEYS, "avg"):
        s = res["successes"][k]
        rows.append(f"| {k:11s} | {res[k]:.3f} | {s if isinstance(s, int) else round(s, 1)}/{res['valid'][k]} | "
                    f"{res['failures'][k]} ({100 * res['failures'][k] / max(res['n'], 1):.1f}%) |")
    fam = ", ".join(f"{f} {s}/{v}" for f, (s, v) in res["families"].items())
    rows.append(f"task by family: {fam}")
    rows.append(f"sampling {res['seconds']:.1f} s ({res['seconds_per_video']:.3f} s/video), "
                f"judging {res['judge_seconds']:.1f} s")
    return "\n".join(rows)


def save_strip(videos: np.ndarray, path: str, rows: int = 8, scale: int = 6) -> None:
    """A PNG with one video per row, frames left to right."""
    from PIL import Image
    v = videos[:rows]
    img = np.concatenate([np.concatenate(list(vid), axis=1) for vid in v], axis=0)
    Image.fromarray(img).resize((img.shape[1] * scale, img.shape[0] * scale), Image.NEAREST).save(path)


def read_run(run_dir: str) -> dict:
    """A train.py rl run: its evaluations (step, task, agent, consistency, avg) from rl.jsonl, and the fixed rows
    (base given T, Demonstrator) from rl_summary.json when the run finished."""
    import os
    path = os.path.join(run_dir, "rl.jsonl")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no rl.jsonl in {run_dir!r}")
    evals = [r for r in map(json.loads, open(path)) if r.get("eval")]
    summ = os.path.join(run_dir, "rl_summary.json")
    fixed = json.load(open(summ))["table"] if os.path.isfile(summ) else {}
    return {"evals": evals, "fixed": fixed}


def compare_runs(runs: dict, path: str | None = None) -> str:
    """Curves of several rl runs (label -> run dir) on one figure -- task and consistency vs step, the
    Demonstrator as a dashed line (the paper's Fig. 5 layout) -- and a markdown table of start, peak and end."""
    data = {label: read_run(d) for label, d in runs.items()}
    rows = ["| run | task @0 | task peak (step) | task @end | consistency @end | agent @end |", "|---|---|---|---|---|---|"]
    for label, r in data.items():
        ev = r["evals"]
        peak = max(ev, key=lambda e: e["task"])
        rows.append(f"| {label} | {ev[0]['task']:.3f} | {peak['task']:.3f} ({peak['step']}) | {ev[-1]['task']:.3f} | "
                    f"{ev[-1]['consistency']:.3f} | {ev[-1]['agent']:.3f} |")
    if path:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
        demo = next((r["fixed"].get("Base + VLM (Demonstrator, toy VLM's D)") for r in data.values()
                     if r["fixed"]), None)
        for ax, key in zip(axes, ("task", "consistency")):
            for label, r in data.items():
                ax.plot([e["step"] for e in r["evals"]], [e[key] for e in r["evals"]], marker="o", ms=3, label=label)
            if demo:
                ax.axhline(demo[key], color="k", ls="--", lw=1, label="Demonstrator (toy VLM's D)")
            ax.set_xlabel("step")
            ax.set_ylabel(f"bench {key} (Executor given T)")
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        plt.close(fig)
    return "\n".join(rows)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None, help="model checkpoint (default: the shipped base)")
    p.add_argument("--condition", choices=["task", "vlm", "oracle"], default="task", help="which prompt the model gets")
    p.add_argument("--n", type=int, default=200, help="bench pairs to evaluate (1..200)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampling noise")
    p.add_argument("--error_rate", type=float, default=DEFAULT_ERROR_RATE, help="toy VLM's share of wrong descriptions")
    p.add_argument("--steps", type=int, default=10, help="Euler steps")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--png", default=None, help="write the first 8 videos as a PNG strip here")
    p.add_argument("--json", action="store_true", help="end with one line of JSON")
    p.add_argument("--compare", nargs="+", metavar="LABEL=RUN_DIR", default=None,
                   help="instead of evaluating: plot and tabulate finished train.py rl runs (with --png)")
    a = p.parse_args(argv)
    if a.compare:
        try:
            runs = dict(item.split("=", 1) for item in a.compare)
            print(compare_runs(runs, a.png))
        except (ValueError, FileNotFoundError) as e:
            print(f"error: --compare: {e} (give LABEL=RUN_DIR pairs of finished rl runs)", file=sys.stderr)
            sys.exit(2)
        return
    if not 1 <= a.n <= 200:
        p.error(f"--n must lie in 1..200, got {a.n}")
    if not 0 <= a.error_rate <= 1:
        p.error(f"--error_rate must lie in [0, 1], got {a.error_rate}")
    if a.steps < 1:
        p.error(f"--steps must be >= 1, got {a.steps}")
    torch.set_num_threads(a.threads)
    try:
        model, _ = models.load_checkpoint(a.checkpoint)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    model.eval()
    res, videos, _ = evaluate(model, a.condition, a.n, a.seed, a.error_rate, a.steps)
    res["checkpoint"] = a.checkpoint or "shipped base"
    print(format_table(res, f"checkpoint={res['checkpoint']} "))
    if a.png:
        save_strip(videos, a.png)
        print(f"wrote {a.png}")
    if a.json:
        print(json.dumps(res))


if __name__ == "__main__":
    main()
