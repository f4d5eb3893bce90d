"""Evaluate a checkpoint on the WorldTasks-toy bench (Sec. 4.1.2; the table format of Tab. 1 / App. A.4 Tab. 4).

One video per bench pair, generated from the pair's first frame and a prompt chosen by --condition:
  task    the short task T              ("Base" row of Tab. 1; the Executor's condition c_E)
  vlm     the toy VLM's description D   ("+VLM" row: the Demonstrator, reasoning outsourced to an imperfect VLM)
  oracle  the error-free description    (the Demonstrator with a perfect VLM -- an upper reference)
  vague   "red square moves": who moves, not how (probes whether the base commits to *some* motion)
  empty   an empty prompt
  goal    "red square moves to the blue circle": the goal caption of T (probes what the base learned from
          goal-captioned pretraining clips, train.py --p_goal)
  instruction  "[red square]: move left 2 up 1 for 3 frames": the toy VLM's D in the task's form
          (world.instruction_form; the prompt of docs/results.md's positive control, train.py --executor_prompt)
  oracle_instruction  the error-free description in the task's form (docs/results.md's second control: c_E carries
          the right motion while the Demonstrator's D is still wrong 30% of the time)
  oracle_direction  "[red square]: move left 2 up 1": the same without its duration (world.direction_form; the
          docs/results.md's partial control: c_E carries part of the Demonstrator's decision)
Each video is judged by reward.py on Task / Agent / Consistency (always against the task T). A score is
successes / valid judgments; failures (no judgment possible) are counted, as in Tab. 4. Avg is the mean of the
three scores; its successes/valid sum the per-video mean over videos with all three judgments valid. `solved`
(ours, not a paper column) is the share of videos that solve the task *and* are plausible: the task judge reads only
the end state, so a smear that reaches the goal passes it. `by_agent` (ours too) is the share solved by the addressed
agent alone (task and agent both yes), what Fig. 10's training task reward asks: the end state also passes a video in
which a bystander moves the goal to the agent.

  python bench.py --condition oracle --n 200 --seed 0            # the shipped base, error-free descriptions
  python bench.py --checkpoint runs/x.pt --condition task --json  # last line: one JSON object
  python bench.py --condition vlm --guidance 3    # classifier-free guidance against the empty caption, w = 3
  python bench.py --crowded --condition vlm       # the crowded bench: 200 pairs on scenes of 5 sprites, where
                                                  # every scene a model trained on holds 2-4 (a test of transfer)
  python bench.py --checkpoint R/executor_on.pt --trained_pairs R/executor_on.pt --n 32   # the first 32 pairs the
                                                  # run trained on, not the bench: does it fit its own pairs?
  python bench.py --checkpoint R/executor_on.pt --trained_pairs R/executor_on.pt --n 32 --keyed_on moved
                         # those pairs' sprites moved where each pair's plan P no longer solves T: does it still make P?
  python bench.py --checkpoint R/executor_on.pt --trained_pairs R/executor_on.pt --n 512 --keyed_on arranged
                         # a --train_arrangements run's tasks on 6 new places each: has it learned to read the frame?
  python bench.py --compare "WMSD=runs" "no anchor=runs/b" --png cmp.png   # curves + table of train.py runs
  python bench.py --compare "WMSD=runs/s0,runs/s1" --png cmp.png        # seeds of one setting: mean, min-max band
  python bench.py --handoff task,vlm --png h.png   # prompt A for the first k Euler steps, then B: where is it decided?
  python bench.py --rank_rdistill --n 100 --seed 1   # within a group of rollouts given T, what r_distill and the
                                                   # advantages favour: still videos, or solving
  python bench.py --gallery g.png --executor runs/executor_awm.pt   # the first 6 pairs: simulator, Demonstrator,
                                                   # base and Executor, frame by frame, with the judges' verdicts

A real model on a real-image bench (a WorldTasks JSONL file; the judge a Qwen-VL with the prompts of Figs. 15-17):
  python bench.py --model ltx2 --model_path LTX2 --judge qwen-vl --judge_path QWEN --dataset bench.jsonl --batch 4
  ... --condition vlm                            # the "+VLM" row: the Demonstrator, the base given the file's D
  ... --lora runs/executor_awm.pt                # the Executor: the base + the LoRA train.py wrote, given T

The reproduction report (every experiment over seeds, into tables and figures) is report.py; it evaluates with
this file's `evaluate` and draws with its plotting helpers.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time

import numpy as np
import torch

import distill
import flow
import models
import reward
import rl
import world

DEFAULT_ERROR_RATE = 0.3  # the toy VLM's share of wrong descriptions; chosen so the "+VLM" row lands in 0.45-0.70
KEYS = ("task", "agent", "consistency")
DEMO_ROW = "Base + VLM (Demonstrator, toy VLM's D)"  # the Demonstrator's row in train.py's rl_summary.json table


def given_d(bench: str | None) -> str:
    """Whose D the Demonstrator is given on a bench (bench: "toy", "crowded", a WorldTasks file, or None: the toy's),
    as figures and tables name it."""
    return "toy VLM's D" if bench in (None, "toy", "crowded") else "the bench file's D"


REAL_MODELS = models.REAL_MODELS   # --model: the paper's two bases (train.py's too)
CONDITIONS = ("task", "vlm", "oracle", "vague", "empty", "goal", "instruction", "oracle_instruction",
              "oracle_direction")
VLM_CONDITIONS = ("vlm", "instruction")   # the prompts made from the toy VLM's D: only they read --error_rate
PROMPT_NAMES = {"task": "T", "vlm": "the toy VLM's D", "oracle": "the error-free D", "vague": "a vague caption",
                "empty": "an empty prompt", "goal": "T's words as a pretraining goal caption",
                "instruction": "the toy VLM's D in the task's form",
                "oracle_instruction": "the error-free D in the task's form",
                "oracle_direction": "the error-free D's direction and speed in the task's form, not its duration",
                }   # each condition, as a label says it


def prompts_for(pairs: list, condition: str) -> list[str]:
    """The prompt of each pair under a condition (module docstring); vague and empty probe the base alone."""
    if condition == "vague":
        return [world.vague_caption(p.scene, p.plan_oracle) for p in pairs]
    if condition == "goal":
        return [world.goal_caption(p.task) for p in pairs]
    if condition == "instruction":
        return [world.instruction_form(p.d_vlm) for p in pairs]
    if condition == "oracle_instruction":
        return [world.instruction_form(p.d_oracle) for p in pairs]
    if condition == "oracle_direction":
        return [world.direction_form(p.d_oracle) for p in pairs]
    # read only the field the condition names: a real-image pair (train.load_pairs) has a task and a D, no oracle
    field = {"task": lambda p: p.task.text, "vlm": lambda p: p.d_vlm, "oracle": lambda p: p.d_oracle,
             "empty": lambda p: ""}[condition]
    return [field(p) for p in pairs]


# score_table's joint scores (ours, not paper columns): name -> (judgment, judgment, what format_table prints)
JOINT = {"solved": ("task", "consistency", "solved by a plausible video (task and consistency both yes)"),
         "by_agent": ("task", "agent", "solved by the addressed agent alone (task and agent both yes; "
                                       "Fig. 10's training task reward)")}


TRAINED_PAIRS_ARGS = ("train_pairs", "seed", "error_rate", "train_crowded")   # what train.toy_pairs reads
LATER_PAIRS_ARGS = {"train_arrangements": 1}      # what it reads since a later flag, and what older runs did


def trained_pairs(path: str, n: int) -> tuple[list, float, dict]:
    """The first n of the pairs a toy train.py run trained on (bench.py --trained_pairs), made again from the run's
    flags that its checkpoint records: train.toy_pairs at the run's --train_pairs, --seed, --error_rate,
    --train_crowded and --train_arrangements (1 where it records none). Evaluated instead of the bench, they ask
    whether a model fits the pairs it trained on, not only the held-out ones. Returns (pairs, the run's error rate,
    the run: its arrangements, seed and every scene it trained on, which --keyed_on arranged reads). A ValueError
    for a checkpoint that trained on none of them, or on fewer than n."""
    import train     # train imports this module
    meta = models.load_checkpoint(path)[1]
    run = meta.get("args", {})
    if meta.get("stage") not in ("distill", "rl") or run.get("model", "toy") != "toy" or run.get("dataset"):
        on = f"stage {meta.get('stage', 'not recorded')}"
        if run.get("model", "toy") != "toy":
            on = f"--model {run['model']}"
        if run.get("dataset"):
            on = f"--dataset {run['dataset']}"
        raise ValueError(f"--trained_pairs {path!r} was not trained on the toy VLM's pairs ({on}): give a toy "
                         "Executor that train.py's distill or rl stage wrote")
    if missing := [k for k in TRAINED_PAIRS_ARGS if k not in run]:
        raise ValueError(f"--trained_pairs {path!r} does not record its run's --{', --'.join(missing)}, so its pairs "
                         "cannot be made again")
    if meta.get("variant") == "sft":
        raise ValueError(f"--trained_pairs {path!r} is the +SFT baseline, trained on world videos labelled with "
                         "short tasks (world.sft_batch), not on the toy VLM's pairs")
    if n > run["train_pairs"]:
        raise ValueError(f"--n {n} is more than the {run['train_pairs']} pairs {path!r} trained on")
    made = {k: run.get(k, v) for k, v in LATER_PAIRS_ARGS.items()} | {k: run[k] for k in TRAINED_PAIRS_ARGS}
    pairs = train.toy_pairs(train.Args(**made))
    scenes = world.bench_scene_keys(run["train_crowded"]) | {world.scene_key(p.scene) for p in pairs}
    return pairs[:n], run["error_rate"], {"arrangements": made["train_arrangements"], "seed": run["seed"],
                                          "scenes": scenes}


def score_table(judgments: list[dict]) -> dict:
    """judgments: per video {task|agent|consistency: reward.Judgment} -> scores, successes, valid, failures."""
    succ = {k: sum(bool(j[k].yes) for j in judgments) for k in KEYS}
    valid = {k: sum(j[k].yes is not None for j in judgments) for k in KEYS}
    full = [j for j in judgments if all(j[k].yes is not None for k in KEYS)]
    succ["avg"] = float(sum(np.mean([bool(j[k].yes) for k in KEYS]) for j in full))
    valid["avg"] = len(full)
    out = {k: succ[k] / valid[k] if valid[k] else float("nan") for k in KEYS}
    out["avg"] = float(np.mean([out[k] for k in KEYS]))
    # ours, not paper columns: two judgments both yes, over the videos where both were judged. The task judge (Fig. 15)
    # looks only at the end state, so it passes a smear that reaches the goal, and a bystander that moves the goal to
    # the agent. solved: task and consistency (a plausible video); by_agent: task and agent, solved by the addressed
    # agent alone -- what Fig. 10's training task reward asks (reward.judge_task_reward).
    for name, (a, b, _) in JOINT.items():
        both = [j for j in judgments if j[a].yes is not None and j[b].yes is not None]
        succ[name], valid[name] = sum(bool(j[a].yes and j[b].yes) for j in both), len(both)
        out[name] = succ[name] / len(both) if both else float("nan")
    out.update(successes=succ, valid=valid, failures={k: len(judgments) - valid[k] for k in valid}, n=len(judgments))
    return out


def family_scores(pairs: list, judgments: list[dict], key: str = "task", group=lambda p: p.task.family) -> dict:
    """A judgment's score per subgroup of the bench: {group: [successes, valid]}. Default: task score per task
    family (paper Fig. 7 left); agent_type_scores gives Fig. 7 right."""
    out = {}
    for p, j in zip(pairs, judgments):
        g = out.setdefault(group(p), [0, 0])
        if j[key].yes is not None:
            g[0] += int(j[key].yes)
            g[1] += 1
    return dict(sorted(out.items()))


def vlm_error_scores(pairs: list, judgments: list[dict]) -> dict:
    """Task score on the pairs whose toy-VLM description D is right vs wrong (whatever the condition): where the
    Demonstrator must fail, and where an Executor that beats it (Tab. 1) would have to gain."""
    if not all(hasattr(p, "error") for p in pairs):    # a real-image bench: whether D is wrong is not known
        return {}
    return family_scores(pairs, judgments, "task", lambda p: "D wrong" if p.error else "D right")


STILL_LEVEL = 16   # still_videos: a pixel has moved when a colour channel is more than this many levels off frame 0
MOTION_LEVEL = 32  # rank_rdistill's and the rl stage's motion: pixel-frames more than this many levels off frame 0


def moved_pixels(videos: np.ndarray, level) -> np.ndarray:
    """How many pixel-frames of each video (frames 1..) differ from its first frame by more than `level` of 255 in
    some colour channel: (n,) int for one level, (n, k) for a tuple of k levels, counted in the same single pass.
    videos: uint8 (n, F, H, W, 3); one frame at a time and without a wider copy, so a real-size video stays cheap."""
    levels = np.atleast_1d(level)
    first = videos[:, 0]
    counts = np.zeros((len(videos), len(levels)), dtype=np.int64)
    for f in range(1, videos.shape[1]):
        frame = videos[:, f]
        diff = (np.maximum(frame, first) - np.minimum(frame, first)).max(-1)    # uint8 |frame - first|, no overflow
        counts += (diff[..., None] > levels).sum((1, 2))
    return counts[:, 0] if np.ndim(level) == 0 else counts


def still_videos(videos: np.ndarray, level: int = STILL_LEVEL) -> int:
    """How many videos show nothing moving: no pixel moved (moved_pixels) in any frame (ours, not a paper column).
    A network that makes the same still video whatever the prompt -- the collapse of App. A.3's
    Executor-as-its-own-Demonstrator -- is scored plausible by the consistency judge, and Eqs. 9 and 11 read it as
    perfect agreement; this count is where the bench shows it."""
    return int((moved_pixels(videos, level) == 0).sum())


def kind_scores(pairs: list, judgments: list[dict]) -> dict:
    """Task score per kind of toy task (world.Task.kind: move_to, level_with, centre; edge tasks by side), finer
    than Fig. 7's families: it tells the tasks whose direction T's words name ("go to the left edge") from those
    that need where a sprite is ("move to the blue circle"). Empty on a real-image bench, whose tasks have no kind."""
    if not all(hasattr(p.task, "kind") for p in pairs):
        return {}
    return family_scores(pairs, judgments, "task",
                         lambda p: f"edge ({p.task.target})" if p.task.kind == "edge" else p.task.kind)


def consistency_faults(judgments: list[dict]) -> dict:
    """How many videos the toy consistency judge failed for each kind of violation (reward.CONSISTENCY_FAULTS; a
    video can have several): what makes the videos implausible. Empty for a VLM judge, which gives no kinds."""
    out = {}
    for j in judgments:
        if j["consistency"].yes is False:
            for kind in {w.split()[0] for w in j["consistency"].why.split(", ") if w}:
                if kind in reward.CONSISTENCY_FAULTS:
                    out[kind] = out.get(kind, 0) + 1
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def agent_type(p) -> str:
    """A bench pair's agent type (paper Fig. 7 right): the first-person camera vs a sprite; on a real-image bench, the
    taxonomy's agent category where its rows carry one (world.classify_tasks; train.task_groups), else any other
    agent."""
    if getattr(p.task, "agent_type", None):
        return p.task.agent_type
    return "first-person view" if p.task.agent == world.FIRST_PERSON else "sprite" if hasattr(p, "scene") \
        else "other agent"


def agent_type_scores(pairs: list, judgments: list[dict]) -> dict:
    """Agent score per agent type (agent_type; paper Fig. 7 right)."""
    return family_scores(pairs, judgments, "agent", agent_type)


FIG7_SUPPORT = 0.05   # Fig. 7 shows "all categories with more than 5% benchmark support" (Sec. 4.3)
FIG7 = {"families": "task", "agent_types": "agent"}   # Fig. 7: an evaluation's subgroups -> the score they count


def subgroup_sizes(pairs: list) -> dict:
    """How many bench pairs each Fig. 7 subgroup holds, judged or not: {"families": {g: n}, "agent_types": {g: n}}.
    A subgroup's support is its share of the bench (fig7_lines), not of the valid judgments."""
    out = {"families": {}, "agent_types": {}}
    for p in pairs:
        for part, g in (("families", p.task.family), ("agent_types", agent_type(p))):
            out[part][g] = out[part].get(g, 0) + 1
    return out


def fig7_shown(res: dict, part: str) -> list[str]:
    """The subgroups of `part` ("families" or "agent_types") that Fig. 7 shows: those with more than FIG7_SUPPORT of
    the bench's res["n"] pairs (res["sizes"], subgroup_sizes), in res[part]'s order."""
    return [g for g in res[part] if res["sizes"][part][g] > FIG7_SUPPORT * res["n"]]


def subgroup_score(counts) -> float:
    """Fig. 7's score of a subgroup (a task family or an agent type) from its (successes, valid judgments); nan where
    none of its videos was judged, as the bench table's scores: no judgment is not a failure."""
    return counts[0] / counts[1] if counts[1] else float("nan")


def fig7_lines(res: dict) -> list[str]:
    """Fig. 7 as text, one line a panel: the task score per task type and the agent score per agent type, "score
    (successes/valid)", for the subgroups with more than FIG7_SUPPORT of the bench's pairs, as the paper shows them.
    The smaller subgroups follow on the same line with their sizes, so nothing is hidden."""
    lines = []
    for part, key in FIG7.items():
        sizes, big = res["sizes"][part], fig7_shown(res, part)
        cells = ", ".join(f"{g} {subgroup_score(c):.3f} ({c[0]}/{c[1]})" for g, c in res[part].items() if g in big)
        small = ", ".join(f"{g} {s}/{v} ({sizes[g]} pairs)" for g, (s, v) in res[part].items() if g not in big)
        lines.append(f"Fig. 7, {key} score by {key} type (over {FIG7_SUPPORT:.0%} of the bench): {cells or 'none'}"
                     + (f"; at most {FIG7_SUPPORT:.0%}, not shown in the paper's figure: {small}" if small else ""))
    return lines


KEYED_ON = ("moved", "retasked", "arranged")   # --keyed_on: does a model key what it does on T's words or the frame?
ARRANGED = 6        # --keyed_on arranged: new places of each task's sprites


def displacement(plan: world.Plan) -> np.ndarray:
    """A plan's displacement of its mover, first frame to last: (vx k, vy k) pixels (for the camera, the view's)."""
    return np.array([plan.vx * plan.k, plan.vy * plan.k])


def shown_displacement(video: np.ndarray, scene: world.Scene, plan: world.Plan) -> np.ndarray | None:
    """The displacement of `plan`'s mover that a video shows, read off its first and last frames
    (world.read_sprites): that sprite's shift, or for the camera (mover -1) minus the sprites' mean shift, rounded.
    None where it cannot be read (the sprite, or every sprite, not found in one of the two frames)."""
    first, last = ({s.colour: np.array([s.x, s.y]) for s in world.read_sprites(f)} for f in (video[0], video[-1]))
    if plan.mover == -1:
        shifts = [last[c] - first[c] for c in first if c in last]
        return -np.round(np.mean(shifts, 0)) if shifts else None
    c = scene.sprites[plan.mover].colour
    return last[c] - first[c] if c in first and c in last else None


def solves(scene: world.Scene, plan: world.Plan, task: world.Task) -> bool:
    """Whether the task judge passes `plan`'s simulated video on `scene` for `task`."""
    return reward.judge_all(world.render(scene, world.simulate(scene, plan)), task.text)["task"].yes is True


def moved_plan(pair, scene: world.Scene) -> world.Plan | None:
    """--keyed_on moved's rule for a new place of a pair's sprites (scene S'; the pair: scene S, task T, T's correct
    plan P): T's correct plan on S', P', where T is feasible on S', P is valid there but does not solve T, and P'
    moves the agent by more than 1 px otherwise than P; else None."""
    sols = world.solutions(scene, pair.task)
    if not sols or not world.plan_is_valid(scene, pair.plan_oracle):
        return None
    q = world.canonical_solution(sols)
    if (np.abs(displacement(q) - displacement(pair.plan_oracle)).max() <= 1
            or solves(scene, pair.plan_oracle, pair.task)):
        return None
    return q


def moved_pairs(pairs: list, seed: int = 0, tries: int = 20000) -> list:
    """--keyed_on moved: for each pair, the same sprites at new places (world.new_place: as random_scene places them)
    until moved_plan finds one; the moved pair's D is that scene's error-free description of its plan P'.
    -> [(pair, moved pair)], leaving out the pairs for which `tries` draws find none (an edge task whose P already
    goes as far as a plan can)."""
    rng = np.random.default_rng(seed)
    out = []
    for p in pairs:
        for _ in range(tries):
            s2 = world.new_place(p.scene, rng)
            if s2 is not None and (q := moved_plan(p, s2)):
                d = world.describe(s2, q)
                out.append((p, world.Pair(s2, p.task, d, d, q, q, "", world.render(s2, world.simulate(s2, q))[0])))
                break
    return out


def other_tasks(pair) -> list:
    """--keyed_on retasked's choices for a pair (scene S, task T, T's correct plan P): [(T', T''s correct plan)] for
    every other task T' feasible on S (world.candidate_tasks) whose correct plan does not solve T and which P does
    not solve: doing one of the two tasks never does the other."""
    out = []
    for t in world.candidate_tasks(pair.scene):
        sols = world.solutions(pair.scene, t) if t.text != pair.task.text else []
        if not sols:
            continue
        q = world.canonical_solution(sols)
        if not solves(pair.scene, q, pair.task) and not solves(pair.scene, pair.plan_oracle, t):
            out.append((t, q))
    return out


def retasked_pairs(pairs: list, seed: int = 0) -> list:
    """--keyed_on retasked: for each pair, the same first frame with one of other_tasks drawn at random; its D is
    the error-free description of that task's plan. -> [(pair, retasked pair)], leaving out the pairs whose scene has
    no other task."""
    rng = np.random.default_rng(seed)
    out = []
    for p in pairs:
        if opts := other_tasks(p):
            t, q = opts[rng.integers(len(opts))]
            d = world.describe(p.scene, q)
            out.append((p, world.Pair(p.scene, t, d, d, q, q, "", p.frame0)))
    return out


def arranged_pairs(pairs: list, arrangements: int, seed: int, avoid: frozenset) -> list:
    """--keyed_on arranged: each task of the pairs (the first of each run of `arrangements` pairs: a
    --train_arrangements run's pairs come as each task on its places in turn) on ARRANGED new places of its sprites
    where it is feasible (world.arrangements, none a scene in `avoid`: the bench's and the run's own), drawn from
    (seed, 8). Does what a model does for a task carry over to other places of the same sprites, where T's words are
    the same and only the frame tells the motion? -> [(the task's pair, a new pair)]."""
    rng, avoid = np.random.default_rng([seed, 8]), set(avoid)
    return [(p, q) for p in pairs[::arrangements] for q in world.arrangements(p, ARRANGED, rng, avoid)]


def keyed_scores(which: str, videos: np.ndarray, made: list) -> dict:
    """What videos made for --keyed_on's pairs (`made`: [(original pair, new pair)]) show of what the model does on the
    originals. arranged: only how many tasks were arranged anew. moved: the shares of videos that make the original plan
    P's displacement (trained_motion) and the new scene's plan P''s (needed_motion), within 1 px, and whose displacement
    cannot be read (unread); retasked: the share judged to solve the original task T (trained_task). The new pairs' own
    scores are bench.evaluate's."""
    if which == "arranged":     # the new pairs' own scores are all there is
        return {"tasks": len({id(p) for p, _ in made})}
    if which == "retasked":
        return {"trained_task": float(np.mean([reward.judge_all(v, p.task.text)["task"].yes is True
                                               for v, (p, _) in zip(videos, made)]))}
    shown = [shown_displacement(v, q.scene, p.plan_oracle) for v, (p, q) in zip(videos, made)]
    near = lambda d, plan: d is not None and np.abs(d - displacement(plan)).max() <= 1   # noqa: E731
    return {"trained_motion": float(np.mean([near(d, p.plan_oracle) for d, (p, _) in zip(shown, made)])),
            "needed_motion": float(np.mean([near(d, q.plan_oracle) for d, (_, q) in zip(shown, made)])),
            "unread": float(np.mean([d is None for d in shown]))}


def evaluate(model, condition: str, n: int = 200, seed: int = 0, error_rate: float = DEFAULT_ERROR_RATE,
             steps: int = 10, judge=None, batch: int = 200, pairs: list | None = None,
             guidance: float = 1.0, pick=None, verdicts: bool = False) -> tuple[dict, np.ndarray, list]:
    """Generate and judge n bench videos (by reward.py's toy judges, or a reward.VLMJudge with the bench prompts of
    Figs. 15-17), `batch` videos per sampling pass (the same videos for any batch), with classifier-free guidance
    w = `guidance` (1: none; flow.guided_field). The bench is the toy one, or `pairs` (a real-image bench,
    train.load_bench). With `pick` (a reward.PickScore) the result also holds "pick", the videos' mean PickScore
    against T, Fig. 4's quality measure. With `verdicts` it holds "verdicts" too, each video's three judgments
    ({key: [True, False or None (no judgment)] for key in KEYS}; save_videos). Returns (result dict, videos uint8
    (n, F, H, W, 3), pairs)."""
    pairs = (world.bench_pairs(error_rate) if pairs is None else pairs)[:n]
    frame0 = np.stack([p.frame0 for p in pairs])
    t0 = time.time()
    videos = models.generate(model, frame0, prompts_for(pairs, condition), steps=steps, seed=seed, batch=batch,
                             guidance=guidance)
    seconds = time.time() - t0
    t1 = time.time()
    if judge is None:
        judgments = [reward.judge_all(v, p.task.text) for v, p in zip(videos, pairs)]
    else:
        judgments = judge.bench(videos, [p.task.text for p in pairs])
    res = score_table(judgments)
    res.update(condition=condition, seed=seed, error_rate=error_rate, steps=steps, guidance=guidance,
               seconds=seconds, seconds_per_video=seconds / max(len(pairs), 1), judge_seconds=time.time() - t1,
               families=family_scores(pairs, judgments), agent_types=agent_type_scores(pairs, judgments),
               sizes=subgroup_sizes(pairs),
               kinds=kind_scores(pairs, judgments), by_vlm_error=vlm_error_scores(pairs, judgments),
               faults=consistency_faults(judgments), still=still_videos(videos) / max(len(pairs), 1))
    if pick is not None:
        res["pick"] = float(np.mean(pick(videos, [p.task.text for p in pairs])))
    if verdicts:
        res["verdicts"] = {k: [j[k].yes for j in judgments] for k in KEYS}
    return res, videos, pairs


VIDEO_INDEX = "videos.jsonl"    # save_videos' index of a folder of bench videos


def save_videos(out_dir: str, videos: np.ndarray, rows: list[dict], fps: float | None = None) -> str:
    """Videos as files to watch, and beside them out_dir/VIDEO_INDEX, a row a video: {"video": its file, **rows[i]}
    (bench.py --videos: the pair's T, the prompt given and the bench's three verdicts; train.write_rollout_mp4s: T
    and both prompts). With `fps` (a real model's frame rate) each video is an mp4 at its own size
    (world.write_video: through PyAV, in requirements-real.txt); without, a GIF enlarged to 128 px rows, 400 ms a
    frame, as the toy's rollout GIFs. Returns the index's path."""
    from PIL import Image
    os.makedirs(out_dir, exist_ok=True)
    index = []
    for i, (v, row) in enumerate(zip(videos, rows)):
        name = f"{i:03d}.mp4" if fps else f"{i:03d}.gif"
        if fps:
            world.write_video(os.path.join(out_dir, name), v, fps)
        else:
            s = max(1, 8 * world.H // v.shape[1])
            imgs = [Image.fromarray(f).resize((f.shape[1] * s, f.shape[0] * s), Image.NEAREST) for f in v]
            imgs[0].save(os.path.join(out_dir, name), save_all=True, append_images=imgs[1:], duration=400, loop=0)
        index.append({"video": name, **row})
    path = os.path.join(out_dir, VIDEO_INDEX)
    world.write_jsonl(path, index)
    return path


def switched_field(model, c_a: dict, c_b: dict, t_switch: float):
    """The velocity field v(x_t, t | c_A) for t < t_switch and v(x_t, t | c_B) from t_switch on (bench.handoff)."""
    return lambda x, t: model(x, t, c_a if float(t[0]) < t_switch else c_b)


def handoff(model, cond_a: str, cond_b: str, n: int = 200, seed: int = 0, error_rate: float = DEFAULT_ERROR_RATE,
            steps: int = 10) -> dict:
    """Where in the flow is the motion decided? (a diagnostic of ours, not a paper experiment)

    For each k = 0 .. steps, one bench video per pair whose Euler steps 0 .. k-1 follow v(x_t, t | c_A) and steps
    k .. steps-1 follow v(x_t, t | c_B): the prompt switches from A to B at t_k = k / steps. The noise x_0 is
    evaluate()'s, so k = 0 is evaluate(cond_b) and k = steps is evaluate(cond_a). With A = task, B = vlm: how late
    can the Demonstrator still take over the base's own start given T and solve the task -- after that switch time
    the Demonstrator's velocity at the Executor's states no longer carries *where to go*, only how to get there.

    Also, along the unswitched A trajectories (x_{t_0} .. x_{t_{steps-1}}), Eq. 4's discrepancy at each grid state,
    l(t_k) = || v(x_{t_k}, t_k | c_A) - v(x_{t_k}, t_k | c_B) ||^2 (distill.discrepancy, averaged over pairs): the
    per-time target on-policy distillation (Eqs. 5, 11) regresses when A is c_E and B is c_D. `model` is one network
    for both prompts (a bench checkpoint has its LoRA merged, so distill's adapters-off teacher is the same net).
    Returns {"switch": [t_k], "task"/"agent"/"consistency"/"solved": [score per k], "task_per_pair": [[yes per
    pair] per k], "discrepancy": [l(t_k)], ...}; `kept` in the printed table: of the pairs A alone solves (k = steps),
    the share still solved with the switch at t_k."""
    pairs = world.bench_pairs(error_rate)[:n]
    frame0 = np.stack([p.frame0 for p in pairs])
    c_a = model.condition(frame0, prompts_for(pairs, cond_a))
    c_b = model.condition(frame0, prompts_for(pairs, cond_b))
    x_0 = models.seeded_noise(model, n, seed)   # evaluate()'s noise
    ts = flow.time_grid(steps)
    out = {"cond_a": cond_a, "cond_b": cond_b, "n": n, "seed": seed, "steps": steps, "error_rate": error_rate,
           "switch": ts.tolist(), **{k: [] for k in (*KEYS, "solved", "task_per_pair")}}
    with torch.no_grad():
        xs, _ = flow.sample_ode(lambda x, t: model(x, t, c_a), x_0, steps, return_trajectory=True)  # A alone, k = steps
        out["discrepancy"] = [float(distill.discrepancy(model, xs[k], ts[k].expand(n), c_a, c_b).mean())
                              for k in range(steps)]
        for k in range(steps + 1):
            x_1 = xs[-1] if k == steps else flow.sample_ode(switched_field(model, c_a, c_b, float(ts[k])), x_0, steps)
            videos = model.decode(x_1, frame0)
            judgments = [reward.judge_all(vid, p.task.text) for vid, p in zip(videos, pairs)]
            res = score_table(judgments)
            for key in (*KEYS, "solved"):
                out[key].append(res[key])
            out["task_per_pair"].append([j["task"].yes for j in judgments])   # True / False / None per pair
            print(f"switch {cond_a} -> {cond_b} at t = {float(ts[k]):.1f}: task {res['task']:.3f} "
                  f"consistency {res['consistency']:.3f} solved {res['solved']:.3f}", flush=True)
    return out


def plot_handoff(res: dict, path: str) -> None:
    """Left: the bench scores against the switch time t_k; right: Eq. 4's discrepancy along A's trajectories."""
    plt, fig, (ax, ax2) = figure(2, width=4.6)
    for key in ("task", "solved", "consistency"):
        ax.plot(res["switch"], res[key], marker="o", ms=3, label=key)
    ax.set_xlabel(f"switch time t_k: {res['cond_a']} before, {res['cond_b']} from it on")
    ax.set_ylabel("bench score")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax2.plot(res["switch"][:-1], res["discrepancy"], marker="o", ms=3)
    ax2.set_xlabel("t on the unswitched trajectories")
    ax2.set_ylabel(f"|| v(. | {res['cond_a']}) - v(. | {res['cond_b']}) ||^2 (Eq. 4)")
    ax2.grid(alpha=0.3)
    fig.suptitle(f"{res.get('checkpoint', '')}: {res['n']} bench pairs, noise seed {res['seed']}", fontsize=10)
    save_figure(plt, fig, path)


GALLERY_MAX = 12   # --gallery draws at most this many pairs: a picture, not a bench


def gallery(base, executor=None, condition: str = "task", n: int = 6, seed: int = 0,
            error_rate: float = DEFAULT_ERROR_RATE, steps: int = 10, path: str | None = None,
            crowded: bool = False) -> list[dict]:
    """What a task looks like and what each model does with it: the first n bench pairs (not chosen), each shown
    as the simulator executing its error-free D, the Demonstrator (the base given the toy VLM's D), the base given
    `condition` (T by default), and the Executor given the same if one is given. A generated video is the one
    `evaluate` judges for that pair (the same seeded noise). Returns one {"label", "videos" (n, F, H, W, 3),
    "judgments"} per row, each video judged by the toy judges against T; with `path` also draws them. `crowded`:
    the crowded bench's pairs (world.crowded_pairs) instead of the bench's."""
    pairs = (world.crowded_pairs if crowded else world.bench_pairs)(error_rate)[:n]
    frame0 = np.stack([p.frame0 for p in pairs])
    rows = [{"label": "simulator: the error-free D",
             "videos": np.stack([world.render(p.scene, world.simulate(p.scene, p.plan_oracle)) for p in pairs])}]
    models_ = [("Demonstrator: base given the toy VLM's D", base, "vlm"),
               (f"base given {PROMPT_NAMES[condition]}", base, condition)]
    if executor is not None:
        models_.append((f"Executor given {PROMPT_NAMES[condition]}", executor, condition))
    for label, model, cond in models_:
        videos = models.generate(model, frame0, prompts_for(pairs, cond), steps=steps, seed=seed)
        rows.append({"label": label, "videos": videos})
    for r in rows:
        r["judgments"] = [reward.judge_all(v, p.task.text) for v, p in zip(r["videos"], pairs)]
    if path:
        _draw_gallery(pairs, rows, path, seed, "crowded bench" if crowded else "bench")
    return rows


def _draw_gallery(pairs: list, rows: list[dict], path: str, seed: int, bench: str = "bench") -> None:
    """One block per pair, headed by T and the toy VLM's D (and what is wrong with D, if it is); in it one strip
    of frames per row of `gallery`, its label on the left and the judges' verdicts on the right."""
    def verdict(j):
        return "   ".join(f"{name} {'–' if j[k].yes is None else '✓' if j[k].yes else '✗'}"
                          for k, name in (("task", "task"), ("agent", "agent"), ("consistency", "consistent")))

    def framed(video):   # frames left to right, a 1-px grey line between them and around
        img = np.concatenate([np.pad(f, ((1, 1), (1, 0), (0, 0)), constant_values=128) for f in video], axis=1)
        return np.pad(img, ((0, 0), (0, 1), (0, 0)), constant_values=128)

    plt = pyplot()
    cols = 1 if len(pairs) <= 3 else 2
    lines = -(-len(pairs) // cols)
    imgs = [[framed(r["videos"][i]) for r in rows] for i in range(len(pairs))]
    h, w = imgs[0][0].shape[:2]
    inch = 0.035                                    # inches per pixel of the strips
    img_w, img_h = w * inch, len(rows) * (h + 3) * inch
    left = 0.3 + 0.062 * max(len(r["label"]) for r in rows)   # label column (inches, ~ a character at 8 pt)
    right, head = 2.0, 0.55                                      # verdict column, title
    fw, fh = cols * (left + img_w + right), lines * (img_h + head) + 0.35
    fig = plt.figure(figsize=(fw, fh))
    for i, p in enumerate(pairs):
        x0, y0 = (i % cols) * (left + img_w + right) + left, fh - 0.35 - (i // cols + 1) * (img_h + head)
        ax = fig.add_axes([x0 / fw, y0 / fh, img_w / fw, img_h / fh])
        ax.axis("off")
        ax.imshow(np.concatenate([np.pad(im, ((0, 3), (0, 0), (0, 0)), constant_values=255) for im in imgs[i]]),
                  interpolation="nearest")
        for k, r in enumerate(rows):
            y = k * (h + 3) + h / 2
            ax.text(-3, y, r["label"], ha="right", va="center", fontsize=8)
            ax.text(w + 3, y, verdict(r["judgments"][i]), ha="left", va="center", fontsize=8)
        wrong = f"  (wrong: {p.error})" if p.error else ""
        ax.set_title(f"{bench} pair {i}   T = {p.task.text}\nthe toy VLM's D: {p.d_vlm}{wrong}", fontsize=8.5,
                     loc="left")
    fig.suptitle(f"The first {len(pairs)} {bench} pairs (not chosen): frame 0 given, frames 1-"
                 f"{rows[0]['videos'].shape[1] - 1} generated (noise seed {seed}); the verdicts are the toy judges', "
                 f"against T", fontsize=9, y=1 - 0.12 / fh)
    models.make_parent(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _spearman(a, b) -> float:
    """Spearman's rank correlation, tied values sharing their mean rank; nan when either side is constant."""
    def ranks(v):
        v = np.asarray(v, dtype=float)
        r = np.empty(len(v))
        r[np.argsort(v, kind="stable")] = np.arange(len(v))
        for u in np.unique(v):
            r[v == u] = r[v == u].mean()
        return r
    ra, rb = ranks(a), ranks(b)
    return float("nan") if ra.std() == 0 or rb.std() == 0 else float(np.corrcoef(ra, rb)[0, 1])


def _within(x, y, groups) -> tuple[float, float]:
    """Mean over groups of Spearman(x, y) within each group (on the rows where both are finite; a group with no rank
    order on either side is left out), and the share of those groups where it is above 0. (nan, nan) if none."""
    rho = []
    for g in groups:
        a, b = np.asarray(x[g], dtype=float), np.asarray(y[g], dtype=float)
        ok = np.isfinite(a) & np.isfinite(b)
        rho.append(_spearman(a[ok], b[ok]) if ok.sum() > 1 else float("nan"))
    rho = np.array(rho)[~np.isnan(rho)]
    return (float(rho.mean()), float((rho > 0).mean())) if len(rho) else (float("nan"), float("nan"))


def pull(A: torch.Tensor, y, ids: torch.Tensor) -> float:
    """Mean over rollouts of A times y standardised within its group (rl.group_advantages: 0 in a group where y is
    constant, and where y is NaN): a correlation when A has unit spread over the batch, as gdpo's has."""
    return float((A * rl.group_advantages(torch.tensor(y, dtype=torch.float32), ids)).mean())


# train.py's defaults (Args: lambda_task, lambda_cons, lambda_distill 1, adv_agg gdpo, adv_clip 5; a test checks)
RANK_WEIGHTS = {"task": 1.0, "consistency": 1.0, "distill": 1.0}


def rank_rdistill(model, condition: str = "task", n: int = 100, group: int = 8, seed: int = 1,
                  error_rate: float = DEFAULT_ERROR_RATE, steps: int = 10, chunk: int = 25) -> dict:
    """What does r_distill's group-relative advantage reward? (a diagnostic of ours, not a paper experiment)

    For each of the first n bench pairs, `group` ODE rollouts of `model` given `condition` (the Executor's prompt
    c_E), from noise seed `seed` as the rl stage draws a group; for each rollout r_distill (Eq. 9,
    distill.distill_reward) against the Demonstrator given the toy VLM's D, its motion (pixel-frames whose colour
    differs from frame 0 by more than 32 levels in some channel), the task judgment and the judges' graded scores
    r_task and r_cons (train.py's rewards, --task_reward end_state). Rewards only rank rollouts within a group (Eq.
    10's advantages), so every statistic is taken within each group, then averaged over groups:
    Spearman(r_distill, -motion); Spearman(r_distill, task yes) over the groups with both outcomes and every
    judgment valid; and in those, whether the solving rollouts' mean r_distill lies above the failing ones'. The
    same two Spearmans of r_task and r_cons. Spearman is blind to size, and a reward of tiny weight still breaks
    the others' ties, so for the advantages rl.advantages makes at train.py's defaults (RANK_WEIGHTS, gdpo, clip 5),
    from the judges alone ("A_judges", RL from the judges) and from the judges and r_distill ("A_wmsd", the rl
    stage's L_RL with or without the anchor), the statistic is their mean product with the group-standardised
    -motion and task yes (rl.group_advantages; 0 in a group where it is constant): a correlation, as gdpo's A has
    unit spread over the batch, of how far the advantage points towards still (or solving) rollouts. Returns the
    statistics and the per-rollout "r_distill", "motion", "task", "r_task", "r_cons", "A_judges" and "A_wmsd" lists
    (pair-major)."""
    pairs = world.bench_pairs(error_rate)[:n]
    x_0 = models.seeded_noise(model, n * group, seed)
    r_all, motion, task, r_task, r_cons = [], [], [], [], []
    score = lambda j: float("nan") if j.score is None else j.score
    with torch.no_grad():
        for i in range(0, n, chunk):
            ps = [p for p in pairs[i:i + chunk] for _ in range(group)]
            frame0 = np.stack([p.frame0 for p in ps])
            c_E = model.condition(frame0, prompts_for(ps, condition))
            c_D = model.condition(frame0, [p.d_vlm for p in ps])
            traj = flow.sample_ode(lambda x, t: model(x, t, c_E), x_0[i * group:(i * group + len(ps))], steps,
                                   return_trajectory=True)
            r_all += distill.distill_reward(model, traj, c_E, c_D).tolist()
            videos = model.decode(traj[0][-1], frame0)
            motion += moved_pixels(videos, MOTION_LEVEL).tolist()
            for v, p in zip(videos, ps):
                r = reward.read_video(v)           # read once for both judges (None: each judges it invalid)
                j = reward.judge_task(r, p.task.text)
                task.append(j.yes)
                r_task.append(score(j))
                r_cons.append(score(reward.judge_consistency(r)))
    groups = [slice(j * group, (j + 1) * group) for j in range(n)]
    ids = torch.arange(n).repeat_interleave(group)
    rewards = {"task": torch.tensor(r_task), "consistency": torch.tensor(r_cons), "distill": torch.tensor(r_all)}
    judges = {k: w for k, w in RANK_WEIGHTS.items() if k != "distill"}
    A = {"A_judges": rl.advantages(rewards, judges, ids, "gdpo", 5.0),
         "A_wmsd": rl.advantages(rewards, RANK_WEIGHTS, ids, "gdpo", 5.0)}
    still = -np.array(motion)
    mixed = [g for g in groups if None not in task[g] and 0 < sum(task[g]) < group]
    rho_still, still_positive = _within(r_all, still, groups)
    res = {"condition": condition, "n": n, "group": group, "seed": seed, "steps": steps, "mixed_groups": len(mixed),
           "rho_still": rho_still, "still_positive": still_positive, "rho_task": _within(r_all, task, mixed)[0]}
    for name, x in (("r_task", r_task), ("r_cons", r_cons)):
        res[f"rho_still_of_{name}"], res[f"still_positive_of_{name}"] = _within(x, still, groups)
        res[f"rho_task_of_{name}"] = _within(x, task, mixed)[0]
    for name, a in A.items():
        res[f"still_push_of_{name}"] = pull(a, still, ids)
        res[f"task_push_of_{name}"] = pull(a, [np.nan if y is None else float(y) for y in task], ids)
    mean_r = lambda g, solved: np.mean([r for r, y in zip(r_all[g], task[g]) if y == solved])
    higher = [mean_r(g, True) > mean_r(g, False) for g in mixed]
    per_rollout = {"r_distill": r_all, "motion": motion, "task": task, "r_task": r_task, "r_cons": r_cons}
    return res | {"solving_higher": float(np.mean(higher)) if mixed else float("nan")} | per_rollout | {
        k: a.tolist() for k, a in A.items()}


def pointing(model, condition: str, n: int = 200, error_rate: float = DEFAULT_ERROR_RATE) -> dict:
    """A base with Relate (--relate): where its heads land in the first frame given each bench pair's prompt.
    Share of pairs whose head 0 lands within 1 px (max-norm) of the task's agent sprite (pairs with a sprite agent)
    and whose head 1 lands within 1 px of the task's target sprite (pairs with a sprite target) -- the two heads
    train.pointing_loss supervises; with --point_weight 0 any head may do either, so 'any' takes the best head."""
    if not getattr(model.cfg, "relate", False):
        raise ValueError("--pointing reads Relate's heads: give a checkpoint pretrained with --relate")
    pairs = world.bench_pairs(error_rate)[:n]
    with torch.no_grad():
        _, xy = model.relate_attention(model.condition(np.stack([p.frame0 for p in pairs]),
                                                       prompts_for(pairs, condition)))
    px = ((xy + 1) * (model.cfg.size - 1) / 2).numpy()                                  # (n, heads, 2) in pixels
    hits = {"agent": [], "target": [], "agent_any": [], "target_any": []}
    for p, h in zip(pairs, px):
        where = {s.name: np.array([s.x, s.y]) for s in p.scene.sprites}
        for role, name, head in (("agent", p.task.agent, 0), ("target", p.task.target, 1)):
            if name in where:
                d = np.abs(h - where[name]).max(-1)                                      # (heads,)
                hits[role].append(d[head] <= 1)
                hits[role + "_any"].append(d.min() <= 1)
    return {k: float(np.mean(v)) for k, v in hits.items()} | {"n_agent": len(hits["agent"]),
                                                              "n_target": len(hits["target"])}


RELATE_PROBES = ("forced", "zeroed")


@contextlib.contextmanager
def _patched(obj, name: str, value):
    """obj.name is `value` inside the with block; on exit the instance attribute goes and the class's is back."""
    setattr(obj, name, value)
    try:
        yield
    finally:
        delattr(obj, name)


def relate_probe(model, pairs: list, mode: str):
    """Do a --relate base's U-Net read Relate's heads? (docs/given-t.md, "Do the U-Nets of (f) and (e) read the heads?")
    While active, Relate is altered for `pairs`, the bench pairs being evaluated, in order and in one batch (as
    models.generate conditions up to 200 prompts at once). "forced": heads 0 and 1 attend uniformly over the 3x3
    centre of the pair's true agent and target sprite, so they point in every pair; a head whose role names no
    sprite (the camera) keeps its own attention. "zeroed": Relate's channels (offsets and maps) are all zero.
    A context manager; the model is restored on exit. Bad input raises ValueError here, before the with block."""
    if not getattr(model.cfg, "relate", False):
        raise ValueError("--relate_probe alters Relate's heads: give a checkpoint pretrained with --relate")
    if mode not in RELATE_PROBES:
        raise ValueError(f"unknown relate probe {mode!r}; choose from {', '.join(RELATE_PROBES)}")
    S, relate = model.cfg.size, model.relate
    maps = torch.full((len(pairs), 2, S * S), float("nan"))            # the oracle's attention; NaN = keep own
    for i, p in enumerate(pairs):
        where = {s.name: (s.x, s.y) for s in p.scene.sprites}
        for head, name in ((0, p.task.agent), (1, p.task.target)):
            if name in where:
                m = torch.zeros(S, S)
                x, y = where[name]
                m[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2] = 1
                maps[i, head] = (m / m.sum()).flatten()
    own_attend, own_forward = relate.attend, relate.forward

    def forced_attend(pooled, frame0, coords):
        a, _ = own_attend(pooled, frame0, coords)
        if len(a) != len(pairs):
            raise RuntimeError(f"relate_probe holds maps for {len(pairs)} pairs, Relate got a batch of {len(a)}")
        keep = maps[..., 0].isnan()                                    # (n, 2)
        a = a.clone()
        a[:, :2] = torch.where(keep[..., None], a[:, :2], maps.to(a))
        return a, torch.einsum("bhp,cp->bhc", a, coords.flatten(1))

    def zeroed_forward(pooled, frame0, coords):
        return torch.zeros_like(own_forward(pooled, frame0, coords))

    if mode == "forced":
        return _patched(relate, "attend", forced_attend)
    return _patched(relate, "forward", zeroed_forward)


def format_table(res: dict, title: str = "") -> str:
    rows = [f"{title}condition={res['condition']} n={res['n']} seed={res['seed']} error_rate={res['error_rate']} "
            f"steps={res['steps']}" + (f" guidance={res['guidance']:g}" if res.get("guidance", 1) != 1 else ""),
            "| judgment    | score | successes/valid | failures |", "|---|---|---|---|"]
    for k in (*KEYS, "avg"):
        s = res["successes"][k]
        rows.append(f"| {k:11s} | {res[k]:.3f} | {s if isinstance(s, int) else round(s, 1)}/{res['valid'][k]} | "
                    f"{res['failures'][k]} ({100 * res['failures'][k] / max(res['n'], 1):.1f}%) |")
    for name, (_, _, label) in JOINT.items():
        if name in res:   # results saved before a joint score existed lack it
            rows.append(f"{label}: {res[name]:.3f} ({res['successes'][name]}/{res['valid'][name]})")
    rows += fig7_lines(res)
    if res["kinds"]:   # not known on a real-image bench
        rows.append("task by kind: " + ", ".join(f"{g} {s}/{v}" for g, (s, v) in res["kinds"].items()))
    if res["by_vlm_error"]:   # not known on a real-image bench
        rows.append("task by the toy VLM's D: "
                    + ", ".join(f"{g} {s}/{v}" for g, (s, v) in res["by_vlm_error"].items()))
    if "pick" in res:    # bench.py --pick
        rows.append(f"PickScore against T (mean over the videos): {res['pick']:.3f}")
    if "still" in res:   # results saved before the count existed lack it
        rows.append(f"still videos (no pixel moved > {STILL_LEVEL} levels from the first frame): {res['still']:.3f} "
                    f"({round(res['still'] * res['n'])}/{res['n']})")
    if res.get("faults"):
        rows.append("consistency failed by (videos): " + ", ".join(f"{k} {v}" for k, v in res["faults"].items()))
    rows.append(f"sampling {res['seconds']:.1f} s ({res['seconds_per_video']:.3f} s/video), "
                f"judging {res['judge_seconds']:.1f} s")
    return "\n".join(rows)


def strip(videos: np.ndarray, rows: int = 8) -> np.ndarray:
    """One video per row, frames left to right: uint8 (rows * H, F * W, 3)."""
    return np.concatenate([np.concatenate(list(vid), axis=1) for vid in videos[:rows]], axis=0)


def save_strip(videos: np.ndarray, path: str, rows: int = 8, scale: int = 6) -> None:
    """A PNG of strip(videos), each pixel scaled up `scale` times. A real model's videos (larger than the toy's
    16 px, longer than 12 frames) are shown at their own size, 12 frames evenly spaced."""
    from PIL import Image
    F, H = videos.shape[1], videos.shape[2]
    scale = max(1, scale * world.H // H)
    img = strip(videos[:, np.linspace(0, F - 1, min(F, 12)).round().astype(int)], rows)
    models.make_parent(path)
    Image.fromarray(img).resize((img.shape[1] * scale, img.shape[0] * scale), Image.NEAREST).save(path)


def side_by_side(left: np.ndarray, right: np.ndarray, line: int = 2) -> np.ndarray:
    """Two batches of videos (n, F, H, W, 3) -> (n, F, H, 2W + line, 3): left, a white line `line` px wide, right."""
    sep = np.full((*left.shape[:3], line, 3), 255, np.uint8)
    return np.concatenate([left, sep, right], axis=3)


def mean_sd(xs) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for one value) over seeds."""
    xs = np.asarray(list(xs), float)
    return float(xs.mean()), float(xs.std(ddof=1)) if len(xs) > 1 else 0.0


def fmt(xs, digits: int = 3) -> str:
    """Mean ± sd over seeds as one string, e.g. "0.200 ± 0.141"."""
    m, sd = mean_sd(xs)
    return f"{m:.{digits}f} ± {sd:.{digits}f}"


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed), imported only when a picture is drawn."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def figure(panels: int, width: float = 5.2):
    """A row of `panels` matplotlib axes (Agg backend: no display needed); returns (plt, fig, axes)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, panels, figsize=(width * panels, 3.6), squeeze=False)
    return plt, fig, list(axes[0])


def save_figure(plt, fig, path: str) -> None:
    """Write fig to path as a PNG and free it."""
    fig.tight_layout()
    models.make_parent(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def curve_band(ax, runs: list[list[dict]], key: str, label: str, marker: str = "o", color: str | None = None) -> None:
    """Mean over seeds of eval curves (lists of {step, key}) with a min-max band."""
    steps = sorted(set.intersection(*[{e["step"] for e in r} for r in runs]))
    vals = np.array([[next(e[key] for e in r if e["step"] == s) for s in steps] for r in runs])
    line, = ax.plot(steps, vals.mean(0), marker=marker, ms=3, label=label, color=color)
    if len(runs) > 1:
        ax.fill_between(steps, vals.min(0), vals.max(0), color=line.get_color(), alpha=0.15)


def output_path_error(path: str, flag: str, directory: bool = False, suffix: str = "") -> str | None:
    """What is wrong with `path` as where `flag` (e.g. "--png") writes, or None: checked before any work, so that
    none is lost at the end. directory=True: a folder, created if missing. Otherwise a file (ending in `suffix` if
    one is given), its missing folders created when it is written (models.make_parent).
    Either way the nearest folder that exists must be writable, and nothing on the way may be a file."""
    full = os.path.abspath(path)
    if os.path.exists(full) and os.path.isdir(full) != directory:
        kind, want = ("file", "directory") if directory else ("directory", "file")
        return f"{flag} {path!r} is a {kind}, not a {want}"
    if suffix and not directory and not full.lower().endswith(suffix):
        return f"{flag} {path!r} must end in {suffix}"
    near = full if os.path.isdir(full) else os.path.dirname(full)
    while not os.path.exists(near):
        near = os.path.dirname(near)
    if not os.path.isdir(near):
        return f"{flag} {path!r}: {near!r} is a file, so nothing can be made inside it"
    if not os.access(near, os.W_OK | os.X_OK):
        return f"{flag} {path!r}: no permission to write in {near!r}"
    return None


def file_digest(path: str) -> str:
    """The first 16 hex digits of a file's SHA-256: which base checkpoint a run started from (the key of report.py's
    run reuse and of train.py's --eval_cache)."""
    import hashlib
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()[:16]


def read_run(run_dir: str) -> dict:
    """A finished or running train.py run: an rl run's evaluations (step, task, agent, consistency, avg, still) from
    rl.jsonl, the share of still training rollouts at each Executor step ("steps": {step, still}; rl.jsonl's per-step
    `still` count over its batch, logged since stop 78), and the fixed rows (base given T, Demonstrator) from
    rl_summary.json when the run finished. A distill run of one --variant (distill.jsonl) gives its evaluations and,
    once finished, its Demonstrator row; it logs no rollouts' stillness. "prompt": the Executor's; "bench": toy,
    crowded (train.py --eval_crowded) or the --eval_dataset file, None until the run has finished. A ValueError names
    a line that is not JSON, a distill run of several variants, or a run with no evaluation yet."""
    path = os.path.join(run_dir, "rl.jsonl")
    distill = not os.path.isfile(path) and os.path.isfile(os.path.join(run_dir, "distill.jsonl"))
    if distill:
        path = os.path.join(run_dir, "distill.jsonl")
    elif not os.path.isfile(path):
        raise FileNotFoundError(f"no rl.jsonl (nor a distill run's distill.jsonl) in {run_dir!r}")
    records = []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError as e:
                raise ValueError(f"{path} line {i} is not JSON ({e}): a run cut off while writing it?") from None
    variants = sorted({r["variant"] for r in records if "variant" in r})
    if len(variants) > 1:
        raise ValueError(f"{path} holds the curves of {len(variants)} variants ({', '.join(variants)}): give a "
                         f"distill run of one --variant")
    evals = [r for r in records if r.get("eval")]
    if not evals:
        raise ValueError(f"{path} holds no bench evaluation yet (a run evaluates every --eval_every steps)")
    steps = [{"step": r["step"], "still": r["still"] / len(r["A"])} for r in records
             if not r.get("eval") and "still" in r and r.get("A")]
    summ = os.path.join(run_dir, "distill_summary.json" if distill else "rl_summary.json")
    summary = json.load(open(summ)) if os.path.isfile(summ) else {}
    if distill:     # written whole at the end: the Demonstrator row, the Executor's prompt and the bench
        fixed = {DEMO_ROW: summary["demonstrator"]} if "demonstrator" in summary else {}
        prompt, bench = summary.get("executor_prompt", "task"), summary.get("bench", "toy")
    else:
        args = summary.get("args", {})
        # a real-image bench's Demonstrator row is named for its file's D (train.py): read it as DEMO_ROW too
        fixed = {k.replace(given_d("file"), given_d("toy")): v for k, v in summary.get("table", {}).items()}
        prompt = args.get("executor_prompt", "task")
        bench = args.get("eval_dataset") or ("crowded" if args.get("eval_crowded") else "toy")
    return {"evals": evals, "steps": steps, "fixed": fixed, "prompt": prompt, "bench": bench if summary else None}


def rolling_still(steps: list[dict], window: int = 10) -> list[dict]:
    """read_run's per-step still shares as a trailing mean over `window` Executor steps (one batch of 32 is noisy):
    [{step, still}], the first window - 1 steps left out; [] for a run with fewer steps (or none logged)."""
    if len(steps) < window:
        return []
    s = np.array([r["still"] for r in steps])
    means = np.convolve(s, np.ones(window) / window, mode="valid")
    return [{"step": r["step"], "still": float(m)} for r, m in zip(steps[window - 1:], means)]


def compare_items(items: list[str]) -> dict:
    """--compare's LABEL=RUN_DIR[,RUN_DIR...] items -> {label: [run dirs]} (compare_runs' `runs`); an item without
    a label or a dir, or a label given twice, is a ValueError that names it."""
    runs = {}
    for item in items:
        label, eq, dirs = item.partition("=")
        if not (eq and label and all(dirs.split(","))):
            raise ValueError(f"{item!r} lacks a label, its '=' or a run dir")
        if label in runs:
            raise ValueError(f"the label {label!r} is given twice")
        runs[label] = dirs.split(",")
    return runs


def compare_runs(runs: dict, path: str | None = None) -> str:
    """Curves of several runs (read_run: rl, or distill of one variant) on one figure -- task and consistency vs
    step, the Demonstrator as a dashed line (the paper's Fig. 5 layout), a third panel for the collapse to still
    videos where the runs logged it (the share of still training rollouts, a trailing mean over 10 steps,
    rolling_still), a PickScore panel where every run recorded it (train.py --pick: Fig. 4 left's second panel) --
    and a markdown table of start, peak and end. `runs` maps a label to a run dir, or to a list of run dirs (one per
    seed): then each curve is the mean over seeds with a min-max band (curve_band), each cell mean ± sd, and the
    peak is the mean curve's. Runs evaluated on different benches are refused."""
    groups = {label: [read_run(d) for d in ([ds] if isinstance(ds, str) else ds)] for label, ds in runs.items()}
    benches = {r["bench"] for rs in groups.values() for r in rs} - {None}
    if len(benches) > 1:
        raise ValueError(f"the runs were evaluated on different benches ({', '.join(sorted(benches))}; train.py "
                         "--eval_crowded or --eval_dataset): their curves do not compare")
    stills = {label: [rolling_still(r["steps"]) for r in rs] for label, rs in groups.items()}
    keys = ("task", "consistency", *(("pick",) if all("pick" in e for rs in groups.values() for r in rs
                                                      for e in r["evals"]) else ()))

    def cell(xs):
        if any(x is None for x in xs):   # a run from before the still count was logged
            return "–"
        return f"{xs[0]:.3f}" if len(xs) == 1 else fmt(xs)

    rows = ["| run | task @0 | task peak (step) | task @end | consistency @end | agent @end | still videos @end | "
            "still training rollouts, last 10 steps |" + (" PickScore @end |" if "pick" in keys else ""),
            "|---|---|---|---|---|---|---|---|" + ("---|" if "pick" in keys else "")]
    for label, rs in groups.items():
        evs = [r["evals"] for r in rs]
        steps = sorted(set.intersection(*[{e["step"] for e in ev} for ev in evs]))
        if not steps:
            raise ValueError(f"the runs of {label!r} share no evaluated step (seeds of one setting evaluate alike)")
        mean_task = {s: np.mean([next(e["task"] for e in ev if e["step"] == s) for ev in evs]) for s in steps}
        peak = max(steps, key=lambda s: mean_task[s])
        end = [ev[-1] for ev in evs]
        last = [rolled[-1]["still"] if rolled else None for rolled in stills[label]]
        rows.append(f"| {label} | {cell([ev[0]['task'] for ev in evs])} | {mean_task[peak]:.3f} ({peak}) | "
                    f"{cell([e['task'] for e in end])} | {cell([e['consistency'] for e in end])} | "
                    f"{cell([e['agent'] for e in end])} | {cell([e.get('still') for e in end])} | {cell(last)} |"
                    + (f" {cell([e['pick'] for e in end])} |" if "pick" in keys else ""))
    if path:
        drawn = [label for label, curves in stills.items() if all(curves)]   # every seed logged its still rollouts
        plt, fig, axes = figure(len(keys) + bool(drawn), width=4.5 if len(keys) + bool(drawn) > 2 else 5.5)
        demo = next((r["fixed"].get(DEMO_ROW) for rs in groups.values() for r in rs if r["fixed"]), None)
        prompts = {r["prompt"] for rs in groups.values() for r in rs}
        given = "T" if prompts == {"task"} else " / ".join(sorted(prompts)) + " (a control)"
        seeds = {len(rs) for rs in groups.values()}
        for ax, key in zip(axes, keys):
            for i, (label, rs) in enumerate(groups.items()):
                curve_band(ax, [r["evals"] for r in rs], key, label, color=f"C{i}")
            if demo and key in demo:
                ax.axhline(demo[key], color="k", ls="--", lw=1,
                           label=f"Demonstrator ({given_d(next(iter(benches), None))})")
            ax.set_xlabel("step")
            ax.set_ylabel(f"{'crowded ' if benches == {'crowded'} else ''}bench "
                          + ("PickScore against T" if key == "pick" else key))
            ax.grid(alpha=0.3)
        if drawn:
            ax = axes[len(keys)]
            for i, label in enumerate(groups):   # the same colour per label as in the other panels
                if label in drawn:
                    curve_band(ax, stills[label], "still", label, marker="", color=f"C{i}")
            ax.set_xlabel("step")
            ax.set_ylabel("still training rollouts (share, mean of 10 steps)")
            ax.set_ylim(-0.02, 1.02)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=7)
        band = "" if seeds == {1} else "; mean over seeds, min-max band"
        fig.suptitle(f"Executor given {given}{band}", fontsize=10)
        save_figure(plt, fig, path)
    return "\n".join(rows)


# The flags each diagnostic reads, beside --threads (the plain evaluation reads all but --group and --executor). main
# refuses any other flag set with it: ignored, it would leave a run other than the one asked for, or no picture.
DIAGNOSTIC_READS = {
    "compare": ("png",),
    "handoff": ("checkpoint", "n", "seed", "error_rate", "steps", "png", "json"),
    "pointing": ("checkpoint", "condition", "n", "error_rate", "relate_probe", "json"),
    "rank_rdistill": ("checkpoint", "condition", "n", "group", "seed", "error_rate", "steps", "json"),
    "gallery": ("checkpoint", "executor", "condition", "n", "seed", "error_rate", "steps", "json", "crowded"),
}


def main(argv=None):
    import train     # its loaders and its rule for the weights' paths (train imports this module, so not at the top)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None, help="model checkpoint (default: the shipped base)")
    p.add_argument("--model", default="toy",
                   choices=models.MODEL_CHOICES,
                   help="toy (--checkpoint) | ltx2 | hunyuan15 (a local diffusers directory, --model_path) | "
                        "ltx2-tiny | hunyuan15-tiny (random weights, for checks) | ltx2-random | hunyuan15-random "
                        "(the real sizes, random weights, on a GPU: the seconds a video)")
    p.add_argument("--model_path", default="", help="--model ltx2 / hunyuan15: the local diffusers directory")
    p.add_argument("--lora", default=None, help="a real model's Executor: the LoRA file train.py wrote "
                   "(<run_dir>/executor_awm.pt); without it the base itself (given D: the Demonstrator)")
    p.add_argument("--judge", default="toy", choices=reward.JUDGE_CHOICES,
                   help="toy (reward.py's judges) | qwen-vl (--judge_path; the bench prompts of Figs. 15-17) | "
                        "qwen-vl-tiny | qwen-vl-random (Qwen3-VL-8B's sizes, random weights, on a GPU)")
    p.add_argument("--judge_path", default="", help="--judge qwen-vl: the local transformers directory")
    p.add_argument("--pick", default="none", choices=train.PICK_CHOICES,
                   help="also score the videos with PickScore against T (reward.PickScore; Fig. 4's quality measure): "
                        "pickscore (--pick_path) | pickscore-tiny (random weights, for checks)")
    p.add_argument("--pick_path", default="", help="--pick pickscore: the local transformers directory")
    p.add_argument("--pick_processor_path", default="", help="--pick pickscore: the local directory of its tokenizer "
                   "and image processor (default: --pick_path)")
    p.add_argument("--dataset", default=None, help="a WorldTasks JSONL file whose first --n rows are the bench "
                   "(the paper's WorldTasks-Bench; conditions task, vlm = its description, empty); default: the "
                   "toy bench")
    p.add_argument("--trained_pairs", default=None, metavar="CKPT",
                   help="instead of the bench: the first --n of the pairs CKPT's train.py run trained on (a toy "
                        "Executor's checkpoint records its --train_pairs, --seed, --error_rate; bench.trained_pairs), "
                        "evaluated with --checkpoint (CKPT itself, or the base on the same pairs): does a model fit "
                        "the pairs it trained on?")
    p.add_argument("--crowded", action="store_true", help="the crowded bench instead (world.crowded_pairs): 200 "
                   "pairs of the same task kinds on scenes of 5 sprites, where every scene the models saw holds 2-4 "
                   "(the toy's test of transfer, Sec. 4.7, App. A.5)")
    p.add_argument("--offload_text", action="store_true", help="a real model: keep its text encoder in CPU memory "
                   "between encodings (less GPU memory, the same videos)")
    p.add_argument("--offload_judge", action="store_true", help="a VLM judge: keep its weights in CPU memory "
                   "between the prompts it judges (less GPU memory, the same judgments)")
    p.add_argument("--height", type=int, default=0, help="a real model: evaluate at this height and --width "
                   "(Table 3's evaluation resolution: LTX-2 512 x 768; models.resolution); 0: its training size")
    p.add_argument("--width", type=int, default=0, help="see --height")
    p.add_argument("--batch", type=int, default=200, help="videos per sampling pass (fewer: less memory)")
    p.add_argument("--condition", choices=CONDITIONS, default="task", help="which prompt the model gets")
    p.add_argument("--n", type=int, default=None, help="bench pairs to evaluate (1..200; default 200, with --gallery "
                   f"6, at most {GALLERY_MAX})")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampling noise")
    p.add_argument("--error_rate", type=float, default=DEFAULT_ERROR_RATE, help="toy VLM's share of wrong descriptions")
    p.add_argument("--steps", type=int, default=10, help="Euler steps")
    p.add_argument("--guidance", type=float, default=1.0, metavar="W",
                   help="classifier-free guidance scale against the empty caption (1: none, the default and what "
                        "training samples with; other W: two forwards a step; flow.guided_field)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--png", default=None, help="write the first 8 videos as a PNG strip here")
    p.add_argument("--videos", default=None, metavar="DIR",
                   help="write every evaluated video into DIR, with videos.jsonl: each video's T, prompt and verdicts "
                        "(a real model's as mp4s at its size and frame rate, through PyAV; the toy's as GIFs)")
    p.add_argument("--gallery", default=None, metavar="PNG",
                   help="draw the first --n bench pairs: the simulator's correct video, the Demonstrator (given the toy "
                        "VLM's D), the base [and --executor] given --condition, with the judges' verdicts")
    p.add_argument("--executor", default=None, metavar="CKPT",
                   help="with --gallery: a toy Executor checkpoint (train.py's executor_*.pt) for the last row")
    p.add_argument("--json", action="store_true", help="end with one line of JSON")
    p.add_argument("--compare", nargs="+", metavar="LABEL=RUN_DIR[,RUN_DIR...]", default=None,
                   help="instead of evaluating: plot and tabulate train.py rl runs, or distill runs of one "
                        "--variant (with --png; a third "
                        "panel, the still training rollouts' share, where the runs logged it); several "
                        "comma-separated dirs under one label are seeds: mean, sd and a min-max band")
    p.add_argument("--handoff", metavar="A,B", default=None,
                   help="instead of one condition: switch the prompt from condition A to B after k of the Euler steps, "
                        "k = 0..steps, and judge each (where in the flow the motion is decided; bench.handoff)")
    p.add_argument("--rank_rdistill", action="store_true",
                   help="instead of one video per pair: --group rollouts per pair given --condition (the Executor's "
                        "prompt), and what r_distill (Eq. 9) ranks high within a group: stillness, or solving the "
                        "task (bench.rank_rdistill)")
    p.add_argument("--group", type=int, default=8, help="with --rank_rdistill: rollouts per pair (train.py's "
                   "--group_size)")
    p.add_argument("--pointing", action="store_true",
                   help="a --relate base: how often its heads land on the task's agent and target given --condition")
    p.add_argument("--relate_probe", choices=RELATE_PROBES, default=None,
                   help="a --relate base, evaluated (or, forced, --pointing) with Relate altered: heads 0 and 1 forced "
                        "onto each pair's true agent and target, or Relate's channels zeroed (bench.relate_probe)")
    p.add_argument("--keyed_on", choices=KEYED_ON, default=None,
                   help="what a model keys its motion on: evaluate it on each pair (of --trained_pairs, or the bench) "
                        "moved (the same sprites elsewhere, where the pair's plan no longer solves T) or retasked "
                        "(the same first frame, another task), and say how often it still makes the pair's own "
                        "motion or solves its task (bench.moved_pairs, retasked_pairs, keyed_scores); or arranged: "
                        "each task on 6 new places of its sprites where it is feasible, and how often it is solved "
                        "there (bench.arranged_pairs; a --train_arrangements run's tasks, each once)")
    a = p.parse_args(argv)
    mode = next((m for m in DIAGNOSTIC_READS if getattr(a, m) not in (None, False)), None)
    ignored = [k for k, v in vars(a).items() if v != p.get_default(k) and k not in (mode, "threads")   # refused
               and (k == "group" if mode is None else k not in DIAGNOSTIC_READS[mode])]
    a.real = a.model != "toy" or a.judge != "toy" or bool(a.dataset)     # the real path: train.py's loaders
    if a.real and (a.compare or a.handoff is not None or a.rank_rdistill or a.pointing or a.relate_probe or a.gallery
                   or a.keyed_on):
        p.error("--compare, --handoff, --rank_rdistill, --pointing, --relate_probe, --keyed_on and --gallery are toy "
                "diagnostics: not with --model, --judge or --dataset")
    if a.gallery and (a.compare or a.handoff is not None or a.rank_rdistill or a.pointing or a.relate_probe or a.png):
        p.error("--gallery draws videos of the bench: not with --compare, --handoff, --rank_rdistill, --pointing, "
                "--relate_probe or --png")
    for flag in ("png", "gallery"):
        if getattr(a, flag) and (bad := output_path_error(getattr(a, flag), f"--{flag}", suffix=".png")):
            p.error(bad)
    if a.videos and (bad := output_path_error(a.videos, "--videos", directory=True)):
        p.error(bad)
    if a.videos and os.path.exists(os.path.join(a.videos, VIDEO_INDEX)):
        p.error(f"--videos {a.videos!r} already holds {VIDEO_INDEX}, an earlier bench's videos: give another folder")
    if a.executor and not a.gallery:
        p.error("--executor is --gallery's Executor row; to evaluate a toy checkpoint give it as --checkpoint")
    if a.n is None:
        a.n = 6 if a.gallery else 200
    if a.gallery and a.n > GALLERY_MAX:
        p.error(f"--gallery draws at most {GALLERY_MAX} pairs, got --n {a.n}")
    if a.n < 1:
        p.error(f"--n must be >= 1, got {a.n}")
    if a.n > 200 and not a.dataset and not a.trained_pairs:     # a run's pairs: as many as it trained on
        p.error(f"--n must lie in 1..200 (the toy bench), got {a.n}")
    if a.batch < 1:
        p.error(f"--batch must be >= 1, got {a.batch}")
    if a.threads < 1:
        p.error(f"--threads must be >= 1, got {a.threads}")
    if a.model in REAL_MODELS and not a.model_path:
        p.error(f"--model {a.model} needs --model_path (a local diffusers directory; nothing is downloaded)")
    if models.cannot_run_here(a.model, a.judge):
        p.error(models.cannot_run_here(a.model, a.judge))
    if a.judge == "qwen-vl" and not a.judge_path:
        p.error("--judge qwen-vl needs --judge_path (a local directory of the VLM; nothing is downloaded)")
    if a.pick == "pickscore" and not a.pick_path:
        p.error("--pick pickscore needs --pick_path (a local directory of PickScore; nothing is downloaded)")
    paths = train.Args(model=a.model, model_path=a.model_path, judge=a.judge, judge_path=a.judge_path, pick=a.pick,
                       pick_path=a.pick_path, pick_processor_path=a.pick_processor_path)     # the weights' flags
    for name, readers, chosen in train.unread_flags(paths):
        p.error(f"--{name} is read with {readers} only: {chosen} would ignore it")     # a path no loader reads
    if a.offload_judge and a.judge == "toy":
        p.error("--offload_judge is for a VLM judge's weights (--judge qwen-vl / qwen-vl-tiny / qwen-vl-random)")
    if a.offload_text and a.model == "toy":
        p.error("--offload_text is for a real model's text encoder (--model ltx2 / hunyuan15, -tiny, -random)")
    if (a.height > 0) != (a.width > 0) or min(a.height, a.width) < 0:
        p.error(f"--height and --width go together, both > 0, got {a.height} x {a.width}")
    if a.height and a.model == "toy":
        p.error("--height and --width are for a real model: the toy's U-Net is 16 x 16")
    if a.lora and a.model == "toy":
        p.error("--lora loads a real model's Executor; a toy Executor checkpoint has its LoRA merged: --checkpoint")
    if a.model != "toy" and a.checkpoint:
        p.error("--checkpoint is a toy model file; a real model is --model_path (+ --lora for its Executor)")
    if a.crowded and a.dataset:
        p.error("--crowded is a toy bench and --dataset another: give one")
    if a.trained_pairs and (a.real or a.crowded):
        p.error("--trained_pairs evaluates a toy model on a toy run's training pairs instead of the bench: not with "
                "--crowded, --dataset, --model or --judge")
    if a.keyed_on and a.error_rate != DEFAULT_ERROR_RATE:
        p.error("--error_rate sets the bench's D: --keyed_on's pairs have the error-free D of their own plans")
    if a.trained_pairs and a.error_rate != DEFAULT_ERROR_RATE:
        p.error("--error_rate sets the bench's D: the trained pairs' D are the run's own, at its --error_rate")
    if a.dataset and a.condition not in ("task", "vlm", "empty"):
        p.error(f"--condition {a.condition} needs the toy bench's scenes; a --dataset bench has task, vlm, empty")
    if not 0 <= a.error_rate <= 1:
        p.error(f"--error_rate must lie in [0, 1], got {a.error_rate}")
    if a.steps < 1:
        p.error(f"--steps must be >= 1, got {a.steps}")
    if not (np.isfinite(a.guidance) and a.guidance >= 0):      # nan and inf would sample nan videos
        p.error(f"--guidance must be a finite number >= 0 (1: none, 0: the empty caption alone), got {a.guidance}")
    if a.guidance != 1 and (a.handoff is not None or a.rank_rdistill or a.pointing or a.gallery):
        p.error("--guidance applies to one evaluation: not with --handoff, --rank_rdistill, --pointing or --gallery")
    if a.guidance != 1 and a.condition == "empty":     # v(c_u) + w (v(c) - v(c_u)) with c = c_u is v(c_u)
        p.error("--guidance pushes the prompt's field away from the empty caption's: with --condition empty they are "
                "one field, so it would change nothing")
    if a.group < 2:
        p.error(f"--group must be >= 2 (a rank needs two rollouts), got {a.group}")
    if a.relate_probe and (a.handoff is not None or a.rank_rdistill or (a.pointing and a.relate_probe != "forced")):
        p.error("--relate_probe alters one evaluation (or, forced, --pointing): not with --handoff, --rank_rdistill, "
                "or --pointing with zeroed (the heads still look where they did; only their channels are gone)")
    if a.handoff is not None:
        conds = a.handoff.split(",")
        bad = [c for c in conds if c not in CONDITIONS]
        if len(conds) != 2 or bad:
            p.error(f"--handoff wants A,B with A and B among {', '.join(CONDITIONS)}; got {a.handoff!r}")
    for k in ignored:     # after the checks above, which say more
        if k in DIAGNOSTIC_READS:
            p.error(f"--{mode} and --{k} are two different diagnostics: give one")
        p.error(f"--{k} is not read by --{mode}: it would be ignored" if mode else
                "--group is read by --rank_rdistill only: without it, it would be ignored")
    prompts = set(a.handoff.split(",")) if a.handoff is not None else {a.condition}
    if a.error_rate != DEFAULT_ERROR_RATE and not a.gallery and (a.dataset or not prompts & set(VLM_CONDITIONS)):
        chosen = f"--handoff {a.handoff}" if a.handoff is not None else f"--condition {a.condition}"
        p.error("--error_rate sets the toy VLM's errors in its D: " + (
            "a --dataset bench's D is its file's, so it would be ignored" if a.dataset else
            f"it is read with --condition (or --handoff) {' or '.join(VLM_CONDITIONS)}, or --gallery (its "
            f"Demonstrator row), only: {chosen} would ignore it"))
    if a.compare:
        try:
            print(compare_runs(compare_items(a.compare), a.png))
        except (ValueError, FileNotFoundError) as e:
            print(f"error: --compare: {e} (give LABEL=RUN_DIR[,RUN_DIR...] pairs of rl runs or distill runs of one "
                  "--variant; several dirs are seeds of one setting)", file=sys.stderr)
            sys.exit(2)
        return
    models.use_cpu(a.threads)
    judge = pairs = executor = pick = None
    try:
        pick = train.make_pick(paths)
        if a.real:       # the loaders train.py uses
            run = train.Args(model=a.model, model_path=a.model_path, judge=a.judge, judge_path=a.judge_path,
                             init=a.checkpoint or "", offload_text=a.offload_text, offload_judge=a.offload_judge)
            model, judge = train.load_base(run), train.make_judge(run)
            if a.lora:
                run = models.load_lora(model, a.lora, add=True).get("args", {})
                print(f"Executor: {a.lora}, {sum('lora_' in k for k in model.state_dict())} LoRA weights loaded "
                      f"(rank {run.get('lora_rank', '?')}, {run.get('steps', '?')} steps of --model "
                      f"{run.get('model', '?')})")
            if a.dataset:
                pairs = train.dataset_pairs(a.dataset, model, a.n, "--n", (a.width, a.height) if a.height else None)
        else:
            model, _ = models.load_checkpoint(a.checkpoint)
            if a.executor:
                executor = models.load_checkpoint(a.executor)[0].eval()
            if a.trained_pairs:
                pairs, a.error_rate, a.run = trained_pairs(a.trained_pairs, a.n)
    except (FileNotFoundError, ValueError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    model.eval()
    if a.gallery:
        rows = gallery(model, executor, a.condition, a.n, a.seed, a.error_rate, a.steps, a.gallery, a.crowded)
        for r in rows:
            print(f"{r['label']}: " + ", ".join(f"{k} {sum(bool(j[k].yes) for j in r['judgments'])}/{a.n}"
                                                  for k in KEYS))
        print(f"wrote {a.gallery}")
        if a.json:   # each row's verdicts per pair: True, False or None (no judgment)
            print(json.dumps({"pairs": a.n, "seed": a.seed, "rows": [
                {"label": r["label"], **{k: [j[k].yes for j in r["judgments"]] for k in KEYS}} for r in rows]}))
        return
    if a.crowded:
        pairs = world.crowded_pairs(a.error_rate)
    if a.keyed_on:          # the pairs moved or retasked; each new pair evaluated, its original kept beside it
        pairs = (pairs or world.bench_pairs(a.error_rate))[:a.n]
        if a.keyed_on == "arranged":    # the bench's tasks on one scene each, drawn from seed 0; a run's from its own
            run = getattr(a, "run", None) or {"arrangements": 1, "seed": 0,
                                               "scenes": world.bench_scene_keys(a.crowded)}
            try:
                a.made = arranged_pairs(pairs, run["arrangements"], run["seed"], run["scenes"])
            except ValueError as e:
                print(f"error: --keyed_on arranged: {e}", file=sys.stderr)
                sys.exit(2)
            a.left_out, a.n = [], len(a.made)        # every new place evaluated
            print(f"--keyed_on arranged: {ARRANGED} new places of each of the {len(a.made) // ARRANGED} tasks of "
                  f"the {len(pairs)} pairs")
        else:
            a.made = (moved_pairs if a.keyed_on == "moved" else retasked_pairs)(pairs)
            kept = {id(p) for p, _ in a.made}
            a.left_out = [p.task.text for p in pairs if id(p) not in kept]
            print(f"--keyed_on {a.keyed_on}: {len(a.made)} of {len(pairs)} pairs" +
                  (f"; none for {', '.join(a.left_out)}" if a.left_out else ""))
        if not a.made:
            print(f"error: --keyed_on {a.keyed_on}: none of the {len(pairs)} pairs can be {a.keyed_on}",
                  file=sys.stderr)
            sys.exit(2)
        pairs = [q for _, q in a.made]
    if a.real:
        with contextlib.ExitStack() as size:
            if a.height:       # Table 3's evaluation resolution
                try:
                    size.enter_context(models.resolution(model, a.height, a.width))
                except ValueError as e:
                    print(f"error: --height, --width: {e}", file=sys.stderr)
                    sys.exit(2)
            _run_one(a, model, judge, pairs, pick)
        return
    probe = contextlib.nullcontext()
    if a.relate_probe:
        try:
            probe = relate_probe(model, (pairs or world.bench_pairs(a.error_rate))[:a.n], a.relate_probe)
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
    with probe:
        _run_one(a, model, pairs=pairs, pick=pick)


def _run_one(a, model, judge=None, pairs=None, pick=None) -> None:
    """main's single-checkpoint diagnostics and evaluation, once the model is loaded (and probed); `judge` a
    reward.VLMJudge and `pairs` a real-image bench (--judge, --dataset), else the toy ones; `pick` a
    reward.PickScore (--pick)."""
    if a.handoff is not None:
        conds = a.handoff.split(",")
        res = handoff(model, *conds, n=a.n, seed=a.seed, error_rate=a.error_rate, steps=a.steps)
        res["checkpoint"] = a.checkpoint or "shipped base"
        own = [i for i, y in enumerate(res["task_per_pair"][-1]) if y]   # the pairs A alone solves
        print(f"| switch t_k | task | agent | consistency | solved | kept: of the {len(own)} pairs {conds[0]} alone "
              f"solves | Eq. 4 at t_k on {conds[0]}'s trajectories |")
        print("|---|---|---|---|---|---|---|")
        for k, t in enumerate(res["switch"]):
            d = f"{res['discrepancy'][k]:.4f}" if k < len(res["discrepancy"]) else "-"
            kept = sum(bool(res["task_per_pair"][k][i]) for i in own)
            print(f"| {t:.1f} | {res['task'][k]:.3f} | {res['agent'][k]:.3f} | {res['consistency'][k]:.3f} | "
                  f"{res['solved'][k]:.3f} | {kept}/{len(own)} | {d} |")
        if a.png:
            plot_handoff(res, a.png)
            print(f"wrote {a.png}")
        if a.json:
            print(json.dumps(res))
        return
    if a.pointing:
        try:
            res = pointing(model, a.condition, a.n, a.error_rate)
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        print(f"{a.checkpoint or 'shipped base'} given {a.condition}, {a.n} bench pairs: head 0 on the agent "
              f"{res['agent']:.3f} (best head {res['agent_any']:.3f}, {res['n_agent']} pairs), head 1 on the target "
              f"{res['target']:.3f} (best head {res['target_any']:.3f}, {res['n_target']} pairs)")
        if a.json:
            print(json.dumps(res))
        return
    if a.rank_rdistill:
        res = rank_rdistill(model, a.condition, a.n, a.group, a.seed, a.error_rate, a.steps)
        res["checkpoint"] = a.checkpoint or "shipped base"
        print(f"{res['checkpoint']}: {a.n} pairs x {a.group} rollouts given {a.condition}, noise seed {a.seed}; "
              f"r_distill against the toy VLM's D")
        print(f"within-group Spearman(r_distill, -motion): {res['rho_still']:.3f}, above 0 in "
              f"{res['still_positive']:.0%} of groups")
        print(f"within-group Spearman(r_distill, task yes): {res['rho_task']:.3f} over the {res['mixed_groups']} "
              f"groups with both outcomes; the solving rollouts' mean r_distill is the higher in "
              f"{res['solving_higher']:.0%} of them")
        for name in ("r_task", "r_cons"):
            print(f"Spearman({name}, -motion): {res['rho_still_of_' + name]:.3f} (above 0 in "
                  f"{res['still_positive_of_' + name]:.0%} of groups); Spearman({name}, task yes): "
                  f"{res['rho_task_of_' + name]:.3f}")
        print("the advantages (gdpo, train.py's default weights), their correlation with the group-standardised "
              "-motion and task yes:")
        for name, what in (("A_judges", "the judges alone"), ("A_wmsd", "the judges + r_distill")):
            print(f"  {what}: {res['still_push_of_' + name]:.3f}, {res['task_push_of_' + name]:.3f}")
        if a.json:
            print(json.dumps(res))
        return
    res, videos, pairs = evaluate(model, a.condition, a.n, a.seed, a.error_rate, a.steps, judge, a.batch, pairs,
                                  a.guidance, pick, verdicts=bool(a.videos))
    verdicts = res.pop("verdicts", None)
    if a.keyed_on:
        res.update(keyed_on=a.keyed_on, left_out=a.left_out, **keyed_scores(a.keyed_on, videos, a.made))
    res["bench"] = a.dataset or ("crowded" if a.crowded else
                                 f"trained:{a.trained_pairs}" if a.trained_pairs else "toy")
    if a.real:
        name = a.model + (f" + {a.lora}" if a.lora else "") if a.model != "toy" else a.checkpoint or "shipped base"
        res.update(checkpoint=name, judge=a.judge, dataset=a.dataset)
        title = f"model={name} judge={a.judge} bench={res['bench']} "
    else:
        res.update(checkpoint=a.checkpoint or "shipped base", relate_probe=a.relate_probe)
        title = (f"checkpoint={res['checkpoint']} " + (f"relate_probe={a.relate_probe} " if a.relate_probe else "")
                 + ("bench=crowded " if a.crowded else "")
                 + (f"bench=the pairs {a.trained_pairs} trained on " if a.trained_pairs else "")
                 + (f"keyed_on={a.keyed_on} " if a.keyed_on else ""))
    print(format_table(res, title))
    if a.keyed_on == "moved":
        print(f"on the moved scenes: the pair's own motion P in {res['trained_motion']:.3f} of the videos, the motion "
              f"T needs there P' in {res['needed_motion']:.3f}, unread {res['unread']:.3f}")
    elif a.keyed_on == "retasked":
        print(f"given the new task T': the pair's own task T solved in {res['trained_task']:.3f} of the videos")
    elif a.keyed_on == "arranged":
        print(f"on {ARRANGED} new places of each of {res['tasks']} tasks' sprites: task {res['task']:.3f}")
    if a.png:
        save_strip(videos, a.png)
        print(f"wrote {a.png}")
    if a.videos:          # a real model's frame rate (LTX-2's is its own; HunyuanVideo-1.5's pipeline writes 24)
        fps = getattr(model, "fps", 24.0) if a.model != "toy" else None
        rows = [{"task": p.task.text, "prompt": prompt, "verdicts": {k: verdicts[k][i] for k in KEYS}}  # null: none
                for i, (p, prompt) in enumerate(zip(pairs, prompts_for(pairs, a.condition)))]
        index = save_videos(a.videos, videos, rows, fps)
        print(f"wrote {len(videos)} videos and {index}")
    if a.json:
        print(json.dumps(res))


if __name__ == "__main__":
    main()
