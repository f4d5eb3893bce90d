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
          (world.instruction_form; the prompt of the README's positive control, train.py --executor_prompt)
  oracle_instruction  the error-free description in the task's form (the README's second control: c_E carries
          the right motion while the Demonstrator's D is still wrong 30% of the time)
Each video is judged by reward.py on Task / Agent / Consistency (always against the task T). A score is
successes / valid judgments; failures (no judgment possible) are counted, as in Tab. 4. Avg is the mean of the
three scores; its successes/valid sum the per-video mean over videos with all three judgments valid. `solved`
(ours, not a paper column) is the share of videos that solve the task *and* are plausible: the task judge reads only
the end state, so a smear that reaches the goal passes it. `by_agent` (ours too) is the share solved by the addressed
agent alone (task and agent both yes), what Fig. 10's training task reward asks: the end state also passes a video in
which a bystander moves the goal to the agent.

  python bench.py --condition oracle --n 200 --seed 0            # the shipped base, error-free descriptions
  python bench.py --checkpoint runs/x.pt --condition task --json  # last line: one JSON object
  python bench.py --compare "WMSD=runs" "no anchor=runs/b" --png cmp.png   # curves + table of finished rl runs
  python bench.py --compare "WMSD=runs/s0,runs/s1" --png cmp.png        # seeds of one setting: mean, min-max band
  python bench.py --handoff task,vlm --png h.png   # prompt A for the first k Euler steps, then B: where is it decided?
  python bench.py --rank_rdistill --n 100 --seed 1   # within a group of rollouts given T, what r_distill favours
  python bench.py --report results            # the whole reproduction report (README "Reproduction report")
  python bench.py --report /tmp/r --quick     # the same plumbing with tiny runs, in a few minutes
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time

import numpy as np
import torch

import distill
import flow
import models
import reward
import world

DEFAULT_ERROR_RATE = 0.3  # the toy VLM's share of wrong descriptions; chosen so the "+VLM" row lands in 0.45-0.70
KEYS = ("task", "agent", "consistency")
DEMO_ROW = "Base + VLM (Demonstrator, toy VLM's D)"  # the Demonstrator's row in train.py's rl_summary.json table


CONDITIONS = ("task", "vlm", "oracle", "vague", "empty", "goal", "instruction", "oracle_instruction")


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
    # read only the field the condition names: a real-image pair (train.load_pairs) has a task and a D, no oracle
    field = {"task": lambda p: p.task.text, "vlm": lambda p: p.d_vlm, "oracle": lambda p: p.d_oracle,
             "empty": lambda p: ""}[condition]
    return [field(p) for p in pairs]


# score_table's joint scores (ours, not paper columns): name -> (judgment, judgment, what format_table prints)
JOINT = {"solved": ("task", "consistency", "solved by a plausible video (task and consistency both yes)"),
         "by_agent": ("task", "agent", "solved by the addressed agent alone (task and agent both yes; "
                                       "Fig. 10's training task reward)")}


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
    return family_scores(pairs, judgments, "task", lambda p: "D wrong" if p.error else "D right")


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


def agent_type_scores(pairs: list, judgments: list[dict]) -> dict:
    """Agent score per agent type (paper Fig. 7 right): a sprite vs the first-person camera."""
    return family_scores(pairs, judgments, "agent",
                         lambda p: "first-person view" if p.task.agent == world.FIRST_PERSON else "sprite")


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
               families=family_scores(pairs, judgments), agent_types=agent_type_scores(pairs, judgments),
               by_vlm_error=vlm_error_scores(pairs, judgments), faults=consistency_faults(judgments))
    return res, videos, pairs


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
    plt, fig, (ax, ax2) = _plot(2, width=4.6)
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
    _save(plt, fig, path)


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


def rank_rdistill(model, condition: str = "task", n: int = 100, group: int = 8, seed: int = 1,
                  error_rate: float = DEFAULT_ERROR_RATE, steps: int = 10, chunk: int = 25) -> dict:
    """What does r_distill's group-relative advantage reward? (a diagnostic of ours, not a paper experiment)

    For each of the first n bench pairs, `group` ODE rollouts of `model` given `condition` (the Executor's prompt
    c_E), from noise seed `seed` as the rl stage draws a group; for each rollout r_distill (Eq. 9,
    distill.distill_reward) against the Demonstrator given the toy VLM's D, its motion (pixel-frames whose colour
    differs from frame 0 by more than 32 levels in some channel) and the task judgment. Rewards only rank rollouts
    within a group (Eq. 10's advantages), so every statistic is taken within each group, then averaged over groups:
    Spearman(r_distill, -motion); Spearman(r_distill, task yes) over the groups with both outcomes and every
    judgment valid; and in those, whether the solving rollouts' mean r_distill lies above the failing ones'.
    Returns the statistics and the per-rollout "r_distill", "motion", "task" lists (pair-major)."""
    pairs = world.bench_pairs(error_rate)[:n]
    x_0 = models.seeded_noise(model, n * group, seed)
    r_all, motion, task = [], [], []
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
            moved = np.abs(videos[:, 1:].astype(int) - videos[:, :1]).max(-1) > 32
            motion += moved.sum((1, 2, 3)).tolist()
            task += [reward.judge_task(v, p.task.text).yes for v, p in zip(videos, ps)]
    groups = [slice(j * group, (j + 1) * group) for j in range(n)]
    rho_still = np.array([_spearman(r_all[g], -np.array(motion[g])) for g in groups])
    mixed = [g for g in groups if None not in task[g] and 0 < sum(task[g]) < group]
    rho_task = [_spearman(r_all[g], task[g]) for g in mixed]
    mean_r = lambda g, solved: np.mean([r for r, y in zip(r_all[g], task[g]) if y == solved])
    higher = [mean_r(g, True) > mean_r(g, False) for g in mixed]
    ok = ~np.isnan(rho_still)
    return {"condition": condition, "n": n, "group": group, "seed": seed, "steps": steps,
            "rho_still": float(rho_still[ok].mean()) if ok.any() else float("nan"),   # nan: no group varies
            "still_positive": float((rho_still[ok] > 0).mean()) if ok.any() else float("nan"),
            "rho_task": float(np.mean(rho_task)) if mixed else float("nan"), "mixed_groups": len(mixed),
            "solving_higher": float(np.mean(higher)) if mixed else float("nan"),
            "r_distill": r_all, "motion": motion, "task": task}


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
    """Do a --relate base's U-Net read Relate's heads? (README, "Do the U-Nets of (f) and (e) read the heads?")
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
            f"steps={res['steps']}",
            "| judgment    | score | successes/valid | failures |", "|---|---|---|---|"]
    for k in (*KEYS, "avg"):
        s = res["successes"][k]
        rows.append(f"| {k:11s} | {res[k]:.3f} | {s if isinstance(s, int) else round(s, 1)}/{res['valid'][k]} | "
                    f"{res['failures'][k]} ({100 * res['failures'][k] / max(res['n'], 1):.1f}%) |")
    for name, (_, _, label) in JOINT.items():
        if name in res:   # results saved before a joint score existed lack it
            rows.append(f"{label}: {res[name]:.3f} ({res['successes'][name]}/{res['valid'][name]})")
    fam = ", ".join(f"{f} {s}/{v}" for f, (s, v) in res["families"].items())
    rows.append(f"task by family: {fam}")
    rows.append("task by the toy VLM's D: " + ", ".join(f"{g} {s}/{v}" for g, (s, v) in res["by_vlm_error"].items()))
    if res.get("faults"):
        rows.append("consistency failed by (videos): " + ", ".join(f"{k} {v}" for k, v in res["faults"].items()))
    rows.append(f"sampling {res['seconds']:.1f} s ({res['seconds_per_video']:.3f} s/video), "
                f"judging {res['judge_seconds']:.1f} s")
    return "\n".join(rows)


def strip(videos: np.ndarray, rows: int = 8) -> np.ndarray:
    """One video per row, frames left to right: uint8 (rows * H, F * W, 3)."""
    return np.concatenate([np.concatenate(list(vid), axis=1) for vid in videos[:rows]], axis=0)


def save_strip(videos: np.ndarray, path: str, rows: int = 8, scale: int = 6) -> None:
    """A PNG of strip(videos), each pixel scaled up `scale` times."""
    from PIL import Image
    img = strip(videos, rows)
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
    summary = json.load(open(summ)) if os.path.isfile(summ) else {}
    return {"evals": evals, "fixed": summary.get("table", {}),
            "prompt": summary.get("args", {}).get("executor_prompt", "task")}


def compare_runs(runs: dict, path: str | None = None) -> str:
    """Curves of several rl runs on one figure -- task and consistency vs step, the Demonstrator as a dashed line
    (the paper's Fig. 5 layout) -- and a markdown table of start, peak and end. `runs` maps a label to a run dir, or
    to a list of run dirs (one per seed): then each curve is the mean over seeds with a min-max band (curve_band),
    each cell mean ± sd, and the peak is the mean curve's."""
    groups = {label: [read_run(d) for d in ([ds] if isinstance(ds, str) else ds)] for label, ds in runs.items()}

    def cell(xs):
        return f"{xs[0]:.3f}" if len(xs) == 1 else fmt(xs)

    rows = ["| run | task @0 | task peak (step) | task @end | consistency @end | agent @end |", "|---|---|---|---|---|---|"]
    for label, rs in groups.items():
        evs = [r["evals"] for r in rs]
        steps = sorted(set.intersection(*[{e["step"] for e in ev} for ev in evs]))
        mean_task = {s: np.mean([next(e["task"] for e in ev if e["step"] == s) for ev in evs]) for s in steps}
        peak = max(steps, key=lambda s: mean_task[s])
        end = [ev[-1] for ev in evs]
        rows.append(f"| {label} | {cell([ev[0]['task'] for ev in evs])} | {mean_task[peak]:.3f} ({peak}) | "
                    f"{cell([e['task'] for e in end])} | {cell([e['consistency'] for e in end])} | "
                    f"{cell([e['agent'] for e in end])} |")
    if path:
        plt, fig, axes = _plot(2, width=5.5)
        demo = next((r["fixed"].get(DEMO_ROW) for rs in groups.values() for r in rs if r["fixed"]), None)
        prompts = {r["prompt"] for rs in groups.values() for r in rs}
        given = "T" if prompts == {"task"} else " / ".join(sorted(prompts)) + " (a control)"
        seeds = {len(rs) for rs in groups.values()}
        for ax, key in zip(axes, ("task", "consistency")):
            for label, rs in groups.items():
                curve_band(ax, [r["evals"] for r in rs], key, label)
            if demo:
                ax.axhline(demo[key], color="k", ls="--", lw=1, label="Demonstrator (toy VLM's D)")
            ax.set_xlabel("step")
            ax.set_ylabel(f"bench {key}")
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=7)
        band = "" if seeds == {1} else "; mean over seeds, min-max band"
        fig.suptitle(f"Executor given {given}{band}", fontsize=10)
        _save(plt, fig, path)
    return "\n".join(rows)


# ================================================================================================================
# the reproduction report: every experiment below, over seeds, into one folder of tables and figures
# ================================================================================================================

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
}
BETAS = {"beta_0": 0.0, "beta_0.01": 0.01, "beta_0.1": 0.1, "wmsd": 1.0}
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


def file_digest(path: str) -> str:
    """The first 16 hex digits of a file's SHA-256: which base checkpoint a report run started from."""
    import hashlib
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()[:16]


def finished_run(d: str, stage: str, cmd: list, base: str) -> bool:
    """Whether run dir d holds a finished run of this command from this base checkpoint (then the report reuses
    it; a rebuilt base, or changed flags, means the run is done again)."""
    import os
    done = os.path.join(d, "report_cmd.json")
    if not (os.path.isfile(done) and os.path.isfile(os.path.join(d, SUMMARY[stage]))):
        return False
    rec = json.load(open(done))
    return rec["cmd"] == cmd and rec.get("base") == base


def run_experiments(out: str, seeds: list[int], budget: str, jobs: int = 2, init: str = "") -> dict:
    """Run every (experiment, seed) of EXPERIMENTS that `out`/runs does not already hold finished with the same
    command, `jobs` at a time (each train.py with 2 // jobs threads). Returns {(name, seed): run_dir}. A run that
    fails stops the report with its log's last lines; finished runs are kept, so a rerun picks up where it
    stopped. The runs share one --eval_cache: the base's own evaluations are computed once, not in every run."""
    import os
    import subprocess
    from concurrent.futures import ThreadPoolExecutor
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
    start, finished = time.time(), []

    def one(item):
        name, seed, d, cmd = item
        os.makedirs(d, exist_ok=True)
        t0 = time.time()
        with open(os.path.join(d, "log.txt"), "w") as log:
            rc = subprocess.run(cmd + ["--threads", str(max(1, 2 // jobs))], stdout=log, stderr=subprocess.STDOUT).returncode
        if rc != 0:
            tail = open(os.path.join(d, "log.txt")).read().splitlines()[-8:]
            raise RuntimeError(f"run {name} seed {seed} failed (exit {rc}); {d}/log.txt ends:\n" + "\n".join(tail))
        json.dump({"cmd": cmd[2:], "base": base, "minutes": (time.time() - t0) / 60},
                  open(os.path.join(d, "report_cmd.json"), "w"))
        finished.append(name)
        print(f"report: [{len(finished)}/{len(todo)}] {name} seed {seed} done in {(time.time() - t0) / 60:.1f} min "
              f"({(time.time() - start) / 60:.1f} min so far)", flush=True)

    with ThreadPoolExecutor(jobs) as pool:
        for f in [pool.submit(one, item) for item in todo]:
            f.result()
    return dirs


def mean_sd(xs) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for one value) over seeds."""
    xs = np.asarray(list(xs), float)
    return float(xs.mean()), float(xs.std(ddof=1)) if len(xs) > 1 else 0.0


def fmt(xs, digits: int = 3) -> str:
    m, sd = mean_sd(xs)
    return f"{m:.{digits}f} ± {sd:.{digits}f}"


def table4_cell(results: list[dict], key: str) -> str:
    """Tab. 4's cell over seeds: mean score (successes / valid summed over seeds; failure rate)."""
    succ = sum(r["successes"][key] for r in results)
    valid = sum(r["valid"][key] for r in results)
    n = sum(r["n"] for r in results)
    score = succ / valid if valid else float("nan")
    s = f"{succ:g}" if key != "avg" else f"{succ:.1f}"
    return f"{score:.3f} ({s}/{valid}; {100 * (n - valid) / max(n, 1):.1f}%)"


def _plot(panels: int, width: float = 5.2):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, panels, figsize=(width * panels, 3.6), squeeze=False)
    return plt, fig, list(axes[0])


def _save(plt, fig, path: str) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def curve_band(ax, runs: list[list[dict]], key: str, label: str) -> None:
    """Mean over seeds of eval curves (lists of {step, key}) with a min-max band."""
    steps = sorted(set.intersection(*[{e["step"] for e in r} for r in runs]))
    vals = np.array([[next(e[key] for e in r if e["step"] == s) for s in steps] for r in runs])
    line, = ax.plot(steps, vals.mean(0), marker="o", ms=3, label=label)
    if len(runs) > 1:
        ax.fill_between(steps, vals.min(0), vals.max(0), color=line.get_color(), alpha=0.15)


def write_report(out: str, dirs: dict, seeds: list[int], n: int, init: str = "") -> str:
    """Every table and figure of the report (README "The reproduction report") from finished runs: evaluates the final checkpoints (bench noise seed =
    the run's seed) and reads the logged curves. Writes out/report.md and out/*.png; returns the markdown."""
    import os
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
    # Fig. 4 left: self-distillation variants (and SFT) vs step
    dist = [json.load(open(os.path.join(dirs[("distill", s)], "distill_summary.json"))) for s in seeds]
    plt, fig, (ax,) = _plot(1, 6)
    for v in dist[0]["variants"]:
        curve_band(ax, [d["variants"][v] for d in dist], "task", v)
    ax.axhline(mean_sd(d["demonstrator"]["task"] for d in dist)[0], color="k", ls="--", lw=1, label="Demonstrator")
    ax.set(xlabel="step", ylabel="bench task (Executor given T)", title="Fig. 4 left: self-distillation variants")
    ax.legend(fontsize=7)
    _save(plt, fig, os.path.join(out, "fig4_left.png"))
    lines += ["", "## Fig. 4 left: self-distillation variants", "", "![](fig4_left.png)", "",
              "| variant | task @0 | task @end | consistency @end |", "|---|---|---|---|"]
    for v in dist[0]["variants"]:
        lines.append(f"| {v} | {fmt(d['variants'][v][0]['task'] for d in dist)} | "
                     f"{fmt(d['variants'][v][-1]['task'] for d in dist)} | "
                     f"{fmt(d['variants'][v][-1]['consistency'] for d in dist)} |")
    # Fig. 4 right: task score vs beta_d
    curves = {name: [read_run(dirs[(name, s)]) for s in seeds] for name in EXPERIMENTS if name != "distill"}
    plt, fig, (ax,) = _plot(1, 5)
    for what, pick in (("end", lambda ev: ev[-1]["task"]), ("peak", lambda ev: max(e["task"] for e in ev))):
        ms = [mean_sd(pick(r["evals"]) for r in curves[name]) for name in BETAS]
        ax.errorbar(list(BETAS.values()), [m for m, _ in ms], [sd for _, sd in ms], marker="o", capsize=3,
                    label=f"task @{what}")
    ax.set_xscale("symlog", linthresh=0.01)
    ax.set(xlabel="β_d (anchor weight)", ylabel="bench task (Executor given T)", title="Fig. 4 right: anchor weight")
    ax.legend(fontsize=7)
    _save(plt, fig, os.path.join(out, "fig4_right.png"))
    lines += ["", "## Fig. 4 right: task score vs the anchor weight β_d", "", "![](fig4_right.png)", "",
              "| β_d | task peak | task @end | consistency @end |", "|---|---|---|---|"]
    for name, b in BETAS.items():
        lines.append(f"| {b:g} | {fmt(max(e['task'] for e in r['evals']) for r in curves[name])} | "
                     f"{fmt(r['evals'][-1]['task'] for r in curves[name])} | "
                     f"{fmt(r['evals'][-1]['consistency'] for r in curves[name])} |")
    # Fig. 5: the four training settings
    demo = [r["fixed"][DEMO_ROW] for r in curves["wmsd"]]
    plt, fig, axes = _plot(2)
    for ax, key in zip(axes, ("task", "consistency")):
        for name, label in FIG5.items():
            curve_band(ax, [r["evals"] for r in curves[name]], key, label)
        ax.axhline(mean_sd(d[key] for d in demo)[0], color="k", ls="--", lw=1, label="Demonstrator (toy VLM's D)")
        ax.set(xlabel="step", ylabel=f"bench {key} (Executor given T)")
    axes[0].legend(fontsize=7)
    axes[0].set_title("Fig. 5: training settings")
    _save(plt, fig, os.path.join(out, "fig5.png"))
    lines += ["", "## Fig. 5: training settings", "", "![](fig5.png)", "",
              "| setting | task @0 | task peak | task @end | agent @end | consistency @end |", "|---|---|---|---|---|---|"]
    for name, label in FIG5.items():
        rs = curves[name]
        lines.append(f"| {label} | {fmt(r['evals'][0]['task'] for r in rs)} | "
                     f"{fmt(max(e['task'] for e in r['evals']) for r in rs)} | "
                     + " | ".join(fmt(r["evals"][-1][k] for r in rs) for k in ("task", "agent", "consistency")) + " |")
    lines.append(f"| Demonstrator (toy VLM's D) | | | {fmt(d['task'] for d in demo)} | {fmt(d['agent'] for d in demo)} | "
                 f"{fmt(d['consistency'] for d in demo)} |")
    # Fig. 7: per task family and per agent type
    groups = {"Base (T)": rows["Base (T)"], "Demonstrator": rows["Base + VLM (the Demonstrator: the toy VLM's D)"],
              "WMSD (T)": rows["WMSD (T)"]}
    plt, fig, axes = _plot(2)
    lines += ["", "## Fig. 7: task score per task family, agent score per agent type", "", "![](fig7.png)", "",
              "| model | " + " | ".join(f"task: {f}" for f in rows["Base (T)"][0]["families"]) + " | " +
              " | ".join(f"agent: {a}" for a in rows["Base (T)"][0]["agent_types"]) + " |",
              "|---|" + "---|" * (len(rows["Base (T)"][0]["families"]) + len(rows["Base (T)"][0]["agent_types"]))]
    for ax, part, key in zip(axes, ("families", "agent_types"), ("task", "agent")):
        names = list(rows["Base (T)"][0][part])
        for i, (label, rs) in enumerate(groups.items()):
            ms = [mean_sd(r[part][g][0] / max(r[part][g][1], 1) for r in rs) for g in names]
            ax.bar(np.arange(len(names)) + 0.27 * (i - 1), [m for m, _ in ms], 0.27, yerr=[sd for _, sd in ms],
                   capsize=2, label=label)
        sizes = [rows["Base (T)"][0][part][g][1] for g in names]
        ax.set_xticks(np.arange(len(names)), [f"{g}\n(n={k})" for g, k in zip(names, sizes)])
        ax.set(ylabel=f"bench {key} score", ylim=(0, 1.05))
    axes[0].legend(fontsize=7)
    _save(plt, fig, os.path.join(out, "fig7.png"))
    for label, rs in groups.items():
        cells = [fmt(r[part][g][0] / max(r[part][g][1], 1) for r in rs)
                 for part in ("families", "agent_types") for g in rs[0][part]]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    sizes = ", ".join(f"{g} {v}" for part in ("families", "agent_types")
                      for g, (_, v) in rows["Base (T)"][0][part].items())
    lines.append(f"\nSubgroup sizes (valid judgments, seed {seeds[0]}): {sizes}.")
    # Fig. 8: with and without the consistency reward
    a, b = (finals[(name, seeds[0])][1][:6] for name in ("wmsd", "no_cons"))
    sep = np.full((*a.shape[:3], 1, 3), 255, np.uint8)         # a white column between the two videos of a row
    save_strip(np.concatenate([a, sep, b], axis=3), os.path.join(out, "fig8.png"), rows=6, scale=5)
    lines += ["", "## Fig. 8: with and without the consistency reward", "",
              f"Frames of the first 6 bench videos (seed {seeds[0]}), left WMSD, right WMSD without r_cons:", "",
              "![](fig8.png)", "", "| | task | agent | consistency |", "|---|---|---|---|"]
    for name, label in (("wmsd", "WMSD"), ("no_cons", "without the consistency reward")):
        rs = [finals[(name, s)][0] for s in seeds]
        lines.append(f"| {label} | " + " | ".join(fmt(r[k] for r in rs) for k in KEYS) + " |")
    # beyond the paper: the Executor's gain over the Demonstrator vs the toy VLM's error rate
    plt, fig, (ax,) = _plot(1, 5)
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
    _save(plt, fig, os.path.join(out, "error_rate.png"))
    md = "\n".join(lines) + "\n"
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write(md)
    return md


REPORT_FILES = ("report.md", "fig4_left.png", "fig4_right.png", "fig5.png", "fig7.png", "fig8.png", "error_rate.png")


def report(out: str, seeds: list[int], quick: bool, jobs: int = 2, init: str = "") -> None:
    import os
    os.makedirs(out, exist_ok=True)
    start = time.time()
    dirs = run_experiments(out, seeds, "quick" if quick else "full", jobs, init)
    md = write_report(out, dirs, seeds, 6 if quick else 200, init)
    minutes = (time.time() - start) / 60
    run_minutes = sum(json.load(open(os.path.join(d, "report_cmd.json")))["minutes"] for d in dirs.values())
    with open(os.path.join(out, "report.md"), "a") as f:
        f.write(f"\nWritten by `python bench.py --report {out}{' --quick' if quick else ''} --seeds "
                f"{' '.join(map(str, seeds))} --jobs {jobs}`: {len(dirs)} runs whose own wall times sum to "
                f"{run_minutes:.1f} min ({jobs} at a time, {max(1, 2 // jobs)} thread(s) each, on {os.cpu_count()} "
                f"CPU cores); this invocation took {minutes:.1f} min (runs already finished are reused).\n")
    print(md)
    print(f"wrote {', '.join(os.path.join(out, f) for f in REPORT_FILES)} in {minutes:.1f} min")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None, help="model checkpoint (default: the shipped base)")
    p.add_argument("--condition", choices=CONDITIONS, default="task", help="which prompt the model gets")
    p.add_argument("--n", type=int, default=200, help="bench pairs to evaluate (1..200)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sampling noise")
    p.add_argument("--error_rate", type=float, default=DEFAULT_ERROR_RATE, help="toy VLM's share of wrong descriptions")
    p.add_argument("--steps", type=int, default=10, help="Euler steps")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--png", default=None, help="write the first 8 videos as a PNG strip here")
    p.add_argument("--json", action="store_true", help="end with one line of JSON")
    p.add_argument("--compare", nargs="+", metavar="LABEL=RUN_DIR[,RUN_DIR...]", default=None,
                   help="instead of evaluating: plot and tabulate finished train.py rl runs (with --png); several "
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
    p.add_argument("--report", metavar="OUT_DIR", default=None,
                   help="instead of evaluating: run every experiment of the reproduction report over --seeds (or "
                        "reuse finished runs in OUT_DIR/runs) and write its tables and figures to OUT_DIR")
    p.add_argument("--quick", action="store_true", help="with --report: tiny runs that check the plumbing")
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="with --report: training seeds (default 0 1 2; "
                   "--quick: 0 1)")
    p.add_argument("--jobs", type=int, default=2, help="with --report: runs at a time (each gets 2 // jobs threads)")
    a = p.parse_args(argv)
    if a.report:
        if a.jobs < 1:
            p.error(f"--jobs must be >= 1, got {a.jobs}")
        if a.checkpoint:
            try:
                models.load_checkpoint(a.checkpoint)
            except (FileNotFoundError, ValueError) as e:
                print(f"error: {e}", file=sys.stderr)
                sys.exit(2)
        torch.set_num_threads(a.threads)
        try:
            report(a.report, a.seeds or ([0, 1] if a.quick else [0, 1, 2]), a.quick, a.jobs, a.checkpoint or "")
        except RuntimeError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(1)
        return
    if a.compare:
        try:
            runs = {label: dirs.split(",") for label, dirs in (item.split("=", 1) for item in a.compare)}
            print(compare_runs(runs, a.png))
        except (ValueError, FileNotFoundError) as e:
            print(f"error: --compare: {e} (give LABEL=RUN_DIR[,RUN_DIR...] pairs of finished rl runs; several dirs "
                  "are seeds of one setting)", file=sys.stderr)
            sys.exit(2)
        return
    if not 1 <= a.n <= 200:
        p.error(f"--n must lie in 1..200, got {a.n}")
    if not 0 <= a.error_rate <= 1:
        p.error(f"--error_rate must lie in [0, 1], got {a.error_rate}")
    if a.steps < 1:
        p.error(f"--steps must be >= 1, got {a.steps}")
    if a.group < 2:
        p.error(f"--group must be >= 2 (a rank needs two rollouts), got {a.group}")
    if a.handoff is not None and a.rank_rdistill:
        p.error("--handoff and --rank_rdistill are two different diagnostics: give one")
    if a.relate_probe and (a.handoff is not None or a.rank_rdistill or (a.pointing and a.relate_probe != "forced")):
        p.error("--relate_probe alters one evaluation (or, forced, --pointing): not with --handoff, --rank_rdistill, "
                "or --pointing with zeroed (the heads still look where they did; only their channels are gone)")
    if a.handoff is not None:
        conds = a.handoff.split(",")
        bad = [c for c in conds if c not in CONDITIONS]
        if len(conds) != 2 or bad:
            p.error(f"--handoff wants A,B with A and B among {', '.join(CONDITIONS)}; got {a.handoff!r}")
    torch.set_num_threads(a.threads)
    try:
        model, _ = models.load_checkpoint(a.checkpoint)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    model.eval()
    probe = contextlib.nullcontext()
    if a.relate_probe:
        try:
            probe = relate_probe(model, world.bench_pairs(a.error_rate)[:a.n], a.relate_probe)
        except ValueError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
    with probe:
        _run_one(a, model)


def _run_one(a, model) -> None:
    """main's single-checkpoint diagnostics and evaluation, once the model is loaded (and probed)."""
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
        if a.json:
            print(json.dumps(res))
        return
    res, videos, _ = evaluate(model, a.condition, a.n, a.seed, a.error_rate, a.steps)
    res.update(checkpoint=a.checkpoint or "shipped base", relate_probe=a.relate_probe)
    probed = f"relate_probe={a.relate_probe} " if a.relate_probe else ""
    print(format_table(res, f"checkpoint={res['checkpoint']} {probed}"))
    if a.png:
        save_strip(videos, a.png)
        print(f"wrote {a.png}")
    if a.json:
        print(json.dumps(res))


if __name__ == "__main__":
    main()
