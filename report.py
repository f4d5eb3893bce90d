"""The reproduction report: the paper's findings on the toy, over seeds, in one folder (README "The reproduction report").

Runs every experiment of EXPERIMENTS as a train.py run per training seed, then writes report.md and the figures:
  Tab. 1 and Tab. 4   base given T, +SFT, paired SFT, the Demonstrator (+VLM) and WMSD's Executor on the 200-pair bench
  Fig. 4 left         the self-distillation variants (off-, on-policy, DMD, SFT, and the full on-policy objective:
                      Eq. 12 with r_distill the only reward) vs step: the task score, and the average of task, agent
                      and consistency the paper plots
  Fig. 4 right        the task and the average score vs the anchor weight beta_d (Eq. 12)
  Fig. 5              the four training settings: (i) RL only, (ii) WMSD, (iii) off-policy + RL on the teacher,
                      (iv) Alg. 2; task, agent and consistency, as the paper's
  Fig. 7              the task score per task family and the agent score per agent type; seed by seed, with counts
  Fig. 8              WMSD with and without the consistency reward, frames side by side
  beyond the paper    the Executor's gain over the Demonstrator vs the toy VLM's error rate
  per seed            the values behind each mean ± sd: every final evaluation and run curve, seed by seed
Finished runs are kept in OUT_DIR/runs and reused when their command and base checkpoint are unchanged, so an
interrupted report loses nothing. The arithmetic over seeds (mean ± sd, Tab. 4's successes / valid) is here; the
evaluation itself is bench.evaluate.

  python report.py results                 # 36 runs: 12 experiments x seeds 0 1 2, then every table and figure
  python report.py /tmp/report --quick     # the same plumbing with tiny runs (its numbers mean nothing)
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

import models
from bench import (DEFAULT_ERROR_RATE, DEMO_ROW, FIG7, FIG7_SUPPORT, KEYS, curve_band, evaluate, fig7_shown, figure,
                   file_digest, fmt, mean_sd, output_path_error, read_run, save_figure, save_strip, side_by_side,
                   subgroup_score)


# name -> (train.py stage, flags beyond the budget's); one run per (name, seed); the comment says what each feeds.
EXPERIMENTS = {
    "wmsd": ("rl", []),                                                    # Tab. 1/4, Figs. 4R (b=1), 5 (ii), 7, 8
    "no_anchor": ("rl", ["--beta_d", "0", "--lambda_distill", "0"]),       # Fig. 5 (i): RL from the judges alone
    "teacher_rl": ("rl", ["--alternate", "2", "--executor_update", "off"]),  # Fig. 5 (iii): off-policy + RL on D
    "alternate": ("rl", ["--alternate", "2"]),                             # Fig. 5 (iv): Alg. 2
    "no_cons": ("rl", ["--lambda_cons", "0"]),                             # Fig. 8
    "beta_0.1": ("rl", ["--beta_d", "0.1"]),                               # Fig. 4 right
    "beta_0.01": ("rl", ["--beta_d", "0.01"]),
    "beta_0": ("rl", ["--beta_d", "0"]),
    "err_0": ("rl", ["--error_rate", "0"]),                                # gain over the Demonstrator vs VLM errors
    "err_0.5": ("rl", ["--error_rate", "0.5"]),
    "distill": ("distill", ["--variant", "off,on,dmd,sft,paired"]),        # Fig. 4 left; Tab. 1's SFT rows
    "on_full": ("rl", ["--lambda_task", "0", "--lambda_cons", "0"]),       # Fig. 4 left: the full on-policy objective
}
BETAS = {"beta_0": 0.0, "beta_0.01": 0.01, "beta_0.1": 0.1, "wmsd": 1.0}
ON_FULL = "on + r_distill (Eq. 12, no judges)"   # Fig. 4 left's full on-policy objective: the on_full runs
FIG4 = {"task": "the task score", "avg": "the average of task, agent, consistency (the paper's)"}   # Fig. 4's panels
# a point of an eval curve (the list of a run's eval records) for key k, as the tables and Fig. 4 right read it
AT = {"0": lambda ev, k: ev[0][k], "end": lambda ev, k: ev[-1][k], "peak": lambda ev, k: max(e[k] for e in ev)}
ERRORS = {"err_0": 0.0, "wmsd": DEFAULT_ERROR_RATE, "err_0.5": 0.5}
FIG5 = {"no_anchor": "(i) RL only, no anchor", "wmsd": "(ii) WMSD", "teacher_rl": "(iii) off-policy + RL on the teacher",
        "alternate": "(iv) alternating (Alg. 2)"}
BUDGETS = {  # train.py flags per stage; --quick checks the plumbing only (its numbers mean nothing)
    "full": {"rl": ["--steps", "25", "--eval_every", "10", "--eval_n", "64"],
             "distill": ["--steps", "25", "--eval_every", "10", "--eval_n", "64"]},
    "quick": {"rl": ["--steps", "2", "--eval_every", "1", "--eval_n", "6", "--tasks_per_step", "2", "--group_size", "2",
                     "--train_pairs", "8", "--sample_steps", "3"],
              "distill": ["--steps", "2", "--eval_every", "1", "--eval_n", "6", "--batch", "4", "--train_pairs", "8",
                          "--sample_steps", "3"]},
}
SUMMARY = {"rl": "rl_summary.json", "distill": "distill_summary.json"}


def finished_run(d: str, stage: str, cmd: list, base: str) -> bool:
    """Whether run dir d holds a finished run of this command from this base checkpoint (then the report reuses
    it; a rebuilt base, or changed flags, means the run is done again)."""
    done = os.path.join(d, "report_cmd.json")
    if not (os.path.isfile(done) and os.path.isfile(os.path.join(d, SUMMARY[stage]))):
        return False
    rec = json.load(open(done))
    return rec["cmd"] == cmd and rec.get("base") == base


def run_experiments(out: str, seeds: list[int], budget: str, jobs: int = 2, init: str = "") -> dict:
    """Run every (experiment, seed) of EXPERIMENTS that `out`/runs does not already hold finished with the same
    command, `jobs` at a time (each train.py with 2 // jobs threads). Returns {(name, seed): run_dir}. A run that
    fails stops the report with its log's last lines (after the runs already queued); Ctrl-C, or a run that was
    interrupted, starts no more. Finished runs are kept, so a rerun picks up where it stopped. The runs share one
    --eval_cache: the base's own evaluations are computed once, not in every run."""
    todo, dirs, base = [], {}, file_digest(init or models.SHIPPED_BASE)
    for name, (stage, flags) in EXPERIMENTS.items():
        for seed in seeds:
            d = os.path.join(out, "runs", f"{name}_s{seed}")
            cmd = [sys.executable, os.path.join(os.path.dirname(os.path.abspath(__file__)), "train.py"), "--stage",
                   stage, "--seed", str(seed), "--run_dir", d, "--eval_cache", os.path.join(out, "runs", "eval_cache"),
                   *BUDGETS[budget][stage], *flags,
                   *(["--init", init] if init else [])]
            dirs[(name, seed)] = d
            if not finished_run(d, stage, cmd[2:], base):
                todo.append((name, seed, d, cmd))
    todo.sort(key=lambda item: item[0] != "distill")   # the longest runs first, so no core idles at the end
    print(f"report: {len(dirs) - len(todo)} of {len(dirs)} runs already done; running {len(todo)}, {jobs} at a time",
          flush=True)
    start, finished, stop = time.time(), [], threading.Event()    # stop: after Ctrl-C, start no more runs
    done = threading.Lock()   # one run's count and progress line at a time: two threads printing at once mixed lines

    def one(item):
        if stop.is_set():
            return
        name, seed, d, cmd = item
        os.makedirs(d, exist_ok=True)
        state = os.path.join(d, "state.pt")   # an interrupted run's: the run is done again from the start, which
        if os.path.isfile(state):               # train.py refuses while an unfinished run's state is there
            os.remove(state)
        t0 = time.time()
        with open(os.path.join(d, "log.txt"), "w") as log:
            rc = subprocess.run(cmd + ["--threads", str(max(1, 2 // jobs))], stdout=log, stderr=subprocess.STDOUT).returncode
        if rc in (130, -signal.SIGINT):     # the run was interrupted (a terminal's Ctrl-C reaches it as well)
            stop.set()
        if rc != 0:
            tail = open(os.path.join(d, "log.txt")).read().splitlines()[-8:]
            raise RuntimeError(f"run {name} seed {seed} failed (exit {rc}); {d}/log.txt ends:\n" + "\n".join(tail))
        json.dump({"cmd": cmd[2:], "base": base, "minutes": (time.time() - t0) / 60},
                  open(os.path.join(d, "report_cmd.json"), "w"))
        with done:
            finished.append(name)
            so_far = (time.time() - start) / 60    # the ETA: the minutes so far per finished run, times the runs left
            print(f"report: [{len(finished)}/{len(todo)}] {name} seed {seed} done in {(time.time() - t0) / 60:.1f} "
                  f"min ({so_far:.1f} min so far, ETA {so_far / len(finished) * (len(todo) - len(finished)):.1f} min)",
                  flush=True)

    with ThreadPoolExecutor(jobs) as pool:
        futures = [pool.submit(one, item) for item in todo]
        try:
            for f in futures:
                f.result()
        except KeyboardInterrupt:       # Ctrl-C: start no more runs (a failed run lets the queued ones go on)
            stop.set()
            raise
    return dirs


def table4_cell(results: list[dict], key: str) -> str:
    """Tab. 4's cell over seeds: mean score (successes / valid summed over seeds; failure rate)."""
    succ = sum(r["successes"][key] for r in results)
    valid = sum(r["valid"][key] for r in results)
    n = sum(r["n"] for r in results)
    score = succ / valid if valid else float("nan")
    s = f"{succ:g}" if key != "avg" else f"{succ:.1f}"
    return f"{score:.3f} ({s}/{valid}; {100 * (n - valid) / max(n, 1):.1f}%)"


def curve_cells(runs: list, points) -> str:
    """A table row's cells: for each (key, point of AT) in points, mean ± sd over runs (an eval curve per seed)."""
    return " | ".join(fmt(AT[at](ev, k) for ev in runs) for k, at in points)


def per_seed_rows(seeds: list[int], finals: dict, curves: dict) -> list[str]:
    """The per-seed table's rows, a row per (label, seed): for each label of `finals` (a final evaluation per seed)
    its task, agent, consistency and avg; for each label of `curves` (an eval curve per seed) the same at the
    curve's end, then the curve's task and avg peaks."""
    K, rows = (*KEYS, "avg"), []
    for label, rs in finals.items():
        rows += [f"| {label} | {s} | " + " | ".join(f"{r[k]:.3f}" for k in K) + " | | |" for s, r in zip(seeds, rs)]
    for label, runs in curves.items():
        rows += [f"| {label} | {s} | " + " | ".join(f"{ev[-1][k]:.3f}" for k in K) +
                 f" | {AT['peak'](ev, 'task'):.3f} | {AT['peak'](ev, 'avg'):.3f} |" for s, ev in zip(seeds, runs)]
    return rows


def subgroup_rows(seeds: list[int], groups: dict) -> list[str]:
    """Fig. 7's table per seed, a row per (label, seed): each task family's task score, then each agent type's agent
    score, each written "score (successes/valid)"; `groups`: label -> a final evaluation per seed."""
    return [f"| {label} | {s} | " + " | ".join(f"{subgroup_score(c):.3f} ({c[0]:g}/{c[1]})"
                                               for part in FIG7 for c in r[part].values()) + " |"
            for label, rs in groups.items() for s, r in zip(seeds, rs)]


def fig7_table(seeds: list[int], groups: dict) -> list[str]:
    """Fig. 7's table: each label's mean ± sd over seeds for the subgroups Fig. 7 shows (bench.fig7_shown: over 5% of
    the bench's pairs, in the first evaluation), the subgroups' sizes with the rest named, then every subgroup seed by
    seed (subgroup_rows). `groups`: label -> a final evaluation per seed."""
    first = next(iter(groups.values()))[0]
    shown = {part: fig7_shown(first, part) for part in FIG7}
    head = [f"{key}: {g}" for part, key in FIG7.items() for g in shown[part]]
    every = [f"{key}: {g}" for part, key in FIG7.items() for g in first[part]]
    lines = ["| model | " + " | ".join(head) + " |", "|---|" + "---|" * len(head)]
    for label, rs in groups.items():
        lines.append(f"| {label} | " + " | ".join(fmt(subgroup_score(r[part][g]) for r in rs)
                                                  for part in FIG7 for g in shown[part]) + " |")
    sizes = ", ".join(f"{g} {v}" for part in FIG7 for g, (_, v) in first[part].items())
    rest = ", ".join(f"{g} ({first['sizes'][part][g]} pairs)" for part in FIG7 for g in first[part]
                     if g not in shown[part])
    return lines + [f"\nSubgroup sizes (valid judgments, seed {seeds[0]}): {sizes}." +
                    (f" At most {FIG7_SUPPORT:.0%} of the bench's pairs, so not in the figure or the table above, "
                     f"as in the paper: {rest}." if rest else ""), "",
                    "Per seed, each score with its successes / valid judgments:", "",
                    "| model | seed | " + " | ".join(every) + " |", "|---|---|" + "---|" * len(every),
                    *subgroup_rows(seeds, groups)]


def write_report(out: str, dirs: dict, seeds: list[int], n: int, init: str = "") -> str:
    """Every table and figure of the report (README "The reproduction report") from finished runs: evaluates the final checkpoints (bench noise seed =
    the run's seed) and reads the logged curves. Writes out/report.md and out/*.png; returns the markdown."""
    rows, lines = {}, []
    base, _ = models.load_checkpoint(init or None)
    base.eval()
    finals = {}
    for seed in seeds:
        ev = lambda m, cond: evaluate(m, cond, n, seed)[0]  # noqa: E731
        rows.setdefault("Base (T)", []).append(ev(base, "task"))
        rows.setdefault("Base + SFT (T)", []).append(
            ev(models.load_checkpoint(os.path.join(dirs[("distill", seed)], "executor_sft.pt"))[0], "task"))
        rows.setdefault("Base + paired SFT (T; correct executions: a reference, not WMSD)", []).append(
            ev(models.load_checkpoint(os.path.join(dirs[("distill", seed)], "executor_paired.pt"))[0], "task"))
        rows.setdefault("Base + VLM (the Demonstrator: the toy VLM's D)", []).append(ev(base, "vlm"))
        for name in ("wmsd", "no_cons"):
            m = models.load_checkpoint(os.path.join(dirs[(name, seed)], "executor_awm.pt"))[0]
            res, videos, pairs = evaluate(m, "task", n, seed)
            finals[(name, seed)] = (res, videos)
            if name == "wmsd":
                rows.setdefault("WMSD (T)", []).append(res)
    K = (*KEYS, "avg")
    # Table 1 and Table 4
    lines += ["## Table 1: WorldTasks-toy bench", "",
              f"Mean ± sd over seeds {seeds}; {n} bench pairs; s/video = sampling seconds per video on this machine "
              "(the toy VLM writes D in well under a millisecond, so +VLM costs the same).", "",
              "`solved` (ours, not a paper column): task and consistency both yes -- the task judge reads only the end "
              "state, so a smear that reaches the goal passes it.", "",
              "| model | task | agent | consistency | avg | solved | s/video |", "|---|---|---|---|---|---|---|"]
    for name, rs in rows.items():
        lines.append(f"| {name} | " + " | ".join(fmt(r[k] for r in rs) for k in (*K, "solved")) +
                     f" | {mean_sd(r['seconds_per_video'] for r in rs)[0]:.4f} |")
    lines += ["", "## Table 4: successes / valid judgments (failure rate), summed over seeds", "",
              "| model | task | agent | consistency | avg | solved |", "|---|---|---|---|---|---|"]
    for name, rs in rows.items():
        lines.append(f"| {name} | " + " | ".join(table4_cell(rs, k) for k in (*K, "solved")) + " |")
    # Fig. 4 left: self-distillation variants (SFT, and the full objective's rl runs too) vs step. The paper plots
    # the average WorldTasks score, the mean of task, agent and consistency (its other panel, PickScore, has no toy
    # counterpart); the task score is the one issue 3's target names. Both, side by side; Fig. 4 right likewise.
    dist = [json.load(open(os.path.join(dirs[("distill", s)], "distill_summary.json"))) for s in seeds]
    variants = {v: [d["variants"][v] for d in dist] for v in dist[0]["variants"]}   # name -> an eval curve per seed
    curves = {name: [read_run(dirs[(name, s)]) for s in seeds] for name in EXPERIMENTS if name != "distill"}
    variants[ON_FULL] = [r["evals"] for r in curves["on_full"]]
    plt, fig, axes = figure(2, 5.2)
    for ax, key in zip(axes, FIG4):
        for v, runs in variants.items():
            curve_band(ax, runs, key, v)
        ax.axhline(mean_sd(d["demonstrator"][key] for d in dist)[0], color="k", ls="--", lw=1, label="Demonstrator")
        ax.set(xlabel="step", ylabel=f"bench {key}", title=FIG4[key])
    axes[0].legend(fontsize=7)
    fig.suptitle("Fig. 4 left: self-distillation variants, the Executor given T", fontsize=10)
    save_figure(plt, fig, os.path.join(out, "fig4_left.png"))
    lines += ["", "## Fig. 4 left: self-distillation variants", "", "![](fig4_left.png)", "",
              "`avg` is the paper's metric in Fig. 4, the mean of the task, agent and consistency scores.", "",
              "| variant | task @0 | task @end | avg @0 | avg @end | consistency @end |", "|---|---|---|---|---|---|"]
    for v, runs in variants.items():
        lines.append(f"| {v} | " + curve_cells(runs, (("task", "0"), ("task", "end"), ("avg", "0"), ("avg", "end"),
                                                ("consistency", "end"))) + " |")
    # Fig. 4 right: the task and the average score vs beta_d, at a curve's end and peak (the figure and the table)
    plt, fig, axes = figure(2, 5)
    for ax, key in zip(axes, FIG4):
        for what in ("end", "peak"):
            ms = [mean_sd(AT[what](r["evals"], key) for r in curves[name]) for name in BETAS]
            ax.errorbar(list(BETAS.values()), [m for m, _ in ms], [sd for _, sd in ms], marker="o", capsize=3,
                        label=f"@{what}")
        ax.set_xscale("symlog", linthresh=0.01)
        ax.set(xlabel="β_d (anchor weight)", ylabel=f"bench {key}", title=FIG4[key])
    axes[0].legend(fontsize=7)
    fig.suptitle("Fig. 4 right: the anchor weight, the Executor given T", fontsize=10)
    save_figure(plt, fig, os.path.join(out, "fig4_right.png"))
    lines += ["", "## Fig. 4 right: the task and the average score vs the anchor weight β_d", "",
              "![](fig4_right.png)", "",
              "| β_d | task peak | task @end | avg peak | avg @end | consistency @end |", "|---|---|---|---|---|---|"]
    for name, b in BETAS.items():
        lines.append(f"| {b:g} | " + curve_cells([r["evals"] for r in curves[name]], (
            ("task", "peak"), ("task", "end"), ("avg", "peak"), ("avg", "end"), ("consistency", "end"))) + " |")
    # Fig. 5: the four training settings
    demo = [r["fixed"][DEMO_ROW] for r in curves["wmsd"]]
    plt, fig, axes = figure(3, 4.5)
    for ax, key in zip(axes, KEYS):   # the paper's three evaluation dimensions
        for name, label in FIG5.items():
            curve_band(ax, [r["evals"] for r in curves[name]], key, label)
        ax.axhline(mean_sd(d[key] for d in demo)[0], color="k", ls="--", lw=1, label="Demonstrator (toy VLM's D)")
        ax.set(xlabel="step", ylabel=f"bench {key}")
    axes[0].legend(fontsize=7)
    fig.suptitle("Fig. 5: training settings, the Executor given T", fontsize=10)
    save_figure(plt, fig, os.path.join(out, "fig5.png"))
    lines += ["", "## Fig. 5: training settings", "", "![](fig5.png)", "",
              "| setting | task @0 | task peak | task @end | agent @end | consistency @end |", "|---|---|---|---|---|---|"]
    for name, label in FIG5.items():
        lines.append(f"| {label} | " + curve_cells([r["evals"] for r in curves[name]], (
            ("task", "0"), ("task", "peak"), ("task", "end"), ("agent", "end"), ("consistency", "end"))) + " |")
    lines.append(f"| Demonstrator (toy VLM's D) | | | {fmt(d['task'] for d in demo)} | {fmt(d['agent'] for d in demo)} | "
                 f"{fmt(d['consistency'] for d in demo)} |")
    # Fig. 7: per task family and per agent type
    groups = {"Base (T)": rows["Base (T)"], "Demonstrator": rows["Base + VLM (the Demonstrator: the toy VLM's D)"],
              "WMSD (T)": rows["WMSD (T)"]}
    first = rows["Base (T)"][0]
    plt, fig, axes = figure(2)
    for ax, (part, key) in zip(axes, FIG7.items()):
        names = fig7_shown(first, part)
        for i, (label, rs) in enumerate(groups.items()):
            ms = [mean_sd(subgroup_score(r[part][g]) for r in rs) for g in names]
            ax.bar(np.arange(len(names)) + 0.27 * (i - 1), [m for m, _ in ms], 0.27, yerr=[sd for _, sd in ms],
                   capsize=2, label=label)
        ax.set_xticks(np.arange(len(names)), [f"{g}\n(n={first[part][g][1]})" for g in names])
        ax.set(ylabel=f"bench {key} score", ylim=(0, 1.05))
    axes[0].legend(fontsize=7)
    save_figure(plt, fig, os.path.join(out, "fig7.png"))
    lines += ["", "## Fig. 7: task score per task family, agent score per agent type", "", "![](fig7.png)", "",
              *fig7_table(seeds, groups)]
    # Fig. 8: with and without the consistency reward
    a, b = (finals[(name, seeds[0])][1][:6] for name in ("wmsd", "no_cons"))
    save_strip(side_by_side(a, b, line=1), os.path.join(out, "fig8.png"), rows=6, scale=5)
    lines += ["", "## Fig. 8: with and without the consistency reward", "",
              f"Frames of the first 6 bench videos (seed {seeds[0]}), left WMSD, right WMSD without r_cons:", "",
              "![](fig8.png)", "", "| | task | agent | consistency |", "|---|---|---|---|"]
    for name, label in (("wmsd", "WMSD"), ("no_cons", "without the consistency reward")):
        rs = [finals[(name, s)][0] for s in seeds]
        lines.append(f"| {label} | " + " | ".join(fmt(r[k] for r in rs) for k in KEYS) + " |")
    # beyond the paper: the Executor's gain over the Demonstrator vs the toy VLM's error rate
    plt, fig, (ax,) = figure(1, 5)
    lines += ["", "## Beyond the paper: gain over the Demonstrator vs the toy VLM's error rate", "",
              "![](error_rate.png)", "", "| error rate | Demonstrator task | WMSD task @end | gain |", "|---|---|---|---|"]
    pts = []
    for name, e in ERRORS.items():
        d = [r["fixed"][DEMO_ROW]["task"] for r in curves[name]]
        x = [r["evals"][-1]["task"] for r in curves[name]]
        gain = [b - a for a, b in zip(d, x)]
        pts.append((e, mean_sd(d), mean_sd(x), mean_sd(gain)))
        lines.append(f"| {e:g} | {fmt(d)} | {fmt(x)} | {fmt(gain, 3)} |")
    for i, label in ((1, "Demonstrator (toy VLM's D)"), (2, "WMSD Executor (T)")):
        ax.errorbar([p[0] for p in pts], [p[i][0] for p in pts], [p[i][1] for p in pts], marker="o", capsize=3,
                    label=label)
    ax.set(xlabel="toy VLM error rate", ylabel="bench task score", title="Executor vs Demonstrator")
    ax.legend(fontsize=7)
    save_figure(plt, fig, os.path.join(out, "error_rate.png"))
    # per seed: the values behind each mean ± sd above (Fig. 7's subgroups have their own), a row per model and seed
    lines += ["", "## Per seed: the values behind the means", "",
              f"The final evaluations on {n} bench pairs (Table 1, Fig. 8); the Demonstrator's, each run's own on the "
              "curves' `--eval_n` pairs at that toy VLM error rate; then each run's curve on those pairs: its end and "
              "its peaks. A run NAME is `runs/NAME_sSEED` here.", "",
              "| model or run | seed | task | agent | consistency | avg | task peak | avg peak |",
              "|---|---|---|---|---|---|---|---|"]
    evaluated = {**rows, "WMSD without r_cons (T)": [finals[("no_cons", s)][0] for s in seeds],
                 **{f"Demonstrator (toy VLM's D, error rate {e:g}) in {name}":
                    [r["fixed"][DEMO_ROW] for r in curves[name]] for name, e in ERRORS.items()}}
    curve_runs = {**{f"distill --variant {v} @end": runs for v, runs in variants.items() if v != ON_FULL},
                  **{f"{name} @end ({' '.join(EXPERIMENTS[name][1]) or 'the defaults'})": [r["evals"] for r in rs]
                     for name, rs in curves.items()}}
    lines += per_seed_rows(seeds, evaluated, curve_runs)
    md = "\n".join(lines) + "\n"
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write(md)
    return md


REPORT_FILES = ("report.md", "fig4_left.png", "fig4_right.png", "fig5.png", "fig7.png", "fig8.png", "error_rate.png")


def report(out: str, seeds: list[int], quick: bool, jobs: int = 2, init: str = "") -> None:
    os.makedirs(out, exist_ok=True)
    start = time.time()
    dirs = run_experiments(out, seeds, "quick" if quick else "full", jobs, init)
    md = write_report(out, dirs, seeds, 6 if quick else 200, init)
    minutes = (time.time() - start) / 60
    run_minutes = sum(json.load(open(os.path.join(d, "report_cmd.json")))["minutes"] for d in dirs.values())
    with open(os.path.join(out, "report.md"), "a") as f:
        f.write(f"\nWritten by `python report.py {out}{' --quick' if quick else ''} --seeds "
                f"{' '.join(map(str, seeds))} --jobs {jobs}`: {len(dirs)} runs whose own wall times sum to "
                f"{run_minutes:.1f} min ({jobs} at a time, {max(1, 2 // jobs)} thread(s) each, on {os.cpu_count()} "
                f"CPU cores); this invocation took {minutes:.1f} min (runs already finished are reused).\n")
    print(md)
    print(f"wrote {', '.join(os.path.join(out, f) for f in REPORT_FILES)} in {minutes:.1f} min")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", metavar="OUT_DIR", help="where the runs (OUT_DIR/runs), report.md and the figures go")
    p.add_argument("--quick", action="store_true", help="tiny runs that check the plumbing")
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="training seeds (default 0 1 2; --quick: 0 1)")
    p.add_argument("--jobs", type=int, default=2, help="runs at a time (each gets 2 // jobs threads)")
    p.add_argument("--checkpoint", default=None, help="base checkpoint the runs start from (default: the shipped base)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads for the final evaluations")
    a = p.parse_args(argv)
    if a.jobs < 1:
        p.error(f"--jobs must be >= 1, got {a.jobs}")
    if a.threads < 1:
        p.error(f"--threads must be >= 1, got {a.threads}")
    if a.seeds and min(a.seeds) < 0:
        p.error(f"--seeds must be >= 0 (train.py's --seed), got {' '.join(map(str, a.seeds))}")
    if a.seeds and len(set(a.seeds)) < len(a.seeds):    # a seed twice: two runs in one folder, counted twice
        p.error(f"--seeds must differ, got {' '.join(map(str, a.seeds))}")
    if bad := output_path_error(a.out, "OUT_DIR", directory=True):
        p.error(bad)
    if a.checkpoint:
        try:
            models.load_checkpoint(a.checkpoint)
        except (FileNotFoundError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
    models.use_cpu(a.threads)
    try:
        report(a.out, a.seeds or ([0, 1] if a.quick else [0, 1, 2]), a.quick, a.jobs, a.checkpoint or "")
    except RuntimeError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:           # the runs that finished are kept; exit 130 (128 + SIGINT) as a shell would
        print(f"\ninterrupted; the runs that finished are kept in {os.path.join(a.out, 'runs')}, and the same command "
              "reuses them", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
