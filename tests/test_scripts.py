"""Smoke runs of the entry scripts with tiny budgets, and their handling of bad input."""
import contextlib
import json
import os
import types

import numpy as np
import pytest
import torch
from PIL import Image

from conftest import ROOT, exit_2, run


def test_distill_stage_smoke(tiny_ckpt, tmp_path):
    r = run("train.py", "--stage", "distill", "--variant", "off,on,dmd,paired", "--init", tiny_ckpt, "--steps", "2",
            "--batch", "3", "--eval_every", "2", "--eval_n", "3", "--train_pairs", "6", "--sample_steps", "2",
            "--log_every", "1", "--run_dir", str(tmp_path))
    assert r.returncode == 0, r.stderr
    summary = json.load(open(tmp_path / "distill_summary.json"))
    assert set(summary["variants"]) == {"off", "on", "dmd", "paired"}
    assert all([e["step"] for e in ev] == [0, 2] for ev in summary["variants"].values())
    for f in ("fig4_left.png", "rollouts_on.gif", "executor_dmd.pt"):
        assert (tmp_path / f).exists(), f
    assert "[dmd] step    2/2" in r.stdout


@pytest.mark.parametrize("trainer,extra", [("awm", []), ("flow-grpo", ["--alternate", "2"])])
def test_rl_stage_smoke(tiny_ckpt, tmp_path, trainer, extra):
    """Alg. 1 end to end with a tiny budget: the default stage (what `train.py --toy` runs); and Alg. 2."""
    r = run("train.py", "--toy", "--trainer", trainer, "--init", tiny_ckpt, "--steps", "2", "--group_size", "2",
            "--tasks_per_step", "2", "--eval_every", "2", "--eval_n", "3", "--train_pairs", "4", "--sample_steps", "2",
            "--inner_epochs", "2", "--run_dir", str(tmp_path), *extra)
    assert r.returncode == 0, r.stderr
    assert "step    2/2" in r.stdout and "ETA" in r.stdout and "| WMSD" in r.stdout
    assert "the Executor: Fig. 7, task score by task type (over 5% of the bench): " in r.stdout      # 3 pairs: all
    if extra:
        assert "Demonstrator round" in r.stdout and "| trained Demonstrator phi" in r.stdout
    summary = json.load(open(tmp_path / "rl_summary.json"))
    assert [e["step"] for e in summary["evals"]] == [0, 2]
    assert all(0 <= e["still"] <= 1 for e in summary["evals"]) and "| still |" in r.stdout
    for f in ("rl_curve.png", "rollouts_rl.gif", f"executor_{trainer}.pt", "rl.jsonl"):
        assert (tmp_path / f).exists(), f
    steps = [json.loads(line) for line in open(tmp_path / "rl.jsonl") if '"eval"' not in line]
    assert len(steps) == 2 and all(s["r_distill"] <= 0 for s in steps if "r_distill" in s)


def test_bench_smoke_json(tiny_ckpt):
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--condition", "oracle", "--n", "4", "--steps", "2", "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    for k in ("task", "agent", "consistency", "avg"):
        assert 0.0 <= res[k] <= 1.0
        assert k in res["valid"] and k in res["successes"]
    assert res["n"] == 4 and res["seconds"] > 0
    assert "| task" in r.stdout


def test_bench_writes_every_video_with_its_task_prompt_and_verdicts(tiny_ckpt, tmp_path, capsys, monkeypatch):
    """bench.py --videos DIR: each evaluated video as a file (the toy's: a GIF of its 6 frames at 128 px), and
    videos.jsonl, a row a video in the bench's order with T, the prompt given and the verdicts the table counts. A
    folder that already holds an index is refused before any work, and so is --videos beside a diagnostic."""
    import bench
    import world
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--condition", "vlm", "--n", "3", "--steps", "2", "--json",
            "--videos", str(tmp_path / "v"))
    assert r.returncode == 0 and f"wrote 3 videos and {tmp_path / 'v' / 'videos.jsonl'}" in r.stdout, r.stderr
    res = json.loads(r.stdout.splitlines()[-1])
    rows = [json.loads(line) for line in open(tmp_path / "v" / "videos.jsonl")]
    pairs = world.bench_pairs(bench.DEFAULT_ERROR_RATE)[:3]
    assert [(r["video"], r["task"], r["prompt"]) for r in rows] == [
        (f"{i:03d}.gif", p.task.text, d) for i, (p, d) in enumerate(zip(pairs, bench.prompts_for(pairs, "vlm")))]
    for k in bench.KEYS:                      # the table's successes, video by video
        assert sum(r["verdicts"][k] is True for r in rows) == res["successes"][k]
    evaluate = bench.evaluate      # each video's own verdicts, in order: a pattern the table's counts cannot hide
    monkeypatch.setattr(bench, "evaluate", lambda *a, **k: (lambda res, v, p: (
        {**res, "verdicts": {key: [True, False, None] for key in bench.KEYS}}, v, p))(*evaluate(*a, **k)))
    bench.main(["--checkpoint", tiny_ckpt, "--n", "3", "--steps", "2", "--videos", str(tmp_path / "w")])
    assert [json.loads(line)["verdicts"] for line in open(tmp_path / "w" / "videos.jsonl")] == [
        {key: v for key in bench.KEYS} for v in (True, False, None)]
    monkeypatch.undo()
    gif = Image.open(tmp_path / "v" / "000.gif")
    assert gif.n_frames == world.F and gif.size == (8 * world.W, 8 * world.H) and "verdicts" not in res
    assert "already holds videos.jsonl" in exit_2(bench.main, ["--n", "2", "--videos", str(tmp_path / "v")], capsys)
    assert "is a file, not a directory" in exit_2(bench.main, ["--videos", str(tmp_path / "v" / "000.gif")], capsys)
    assert "--videos is not read by --handoff" in exit_2(bench.main, ["--handoff", "task,vlm", "--videos", "x"], capsys)


def test_trained_pairs_are_the_pairs_the_run_trained_on(tiny_ckpt, tmp_path, capsys):
    """bench.py --trained_pairs CKPT evaluates --checkpoint on the first --n of the pairs CKPT's run trained on
    (train.toy_pairs at the run's --train_pairs, --seed and --error_rate, as its checkpoint records them; its
    --train_arrangements, or 1 for a run from before that flag), with their own D, as many as the run had (past the
    bench's 200); and refuses a checkpoint that trained on no pairs, more pairs than it had, and flags that would choose
    another bench or other D."""
    import dataclasses

    import bench
    import models
    import train
    import world
    model = models.load_checkpoint(tiny_ckpt)[0]
    ckpt = str(tmp_path / "executor_on.pt")
    models.save_checkpoint(model, ckpt, {"stage": "distill", "variant": "on", "args": dataclasses.asdict(
        train.Args(stage="distill", train_pairs=8, seed=3, error_rate=0.9))})
    want = world.train_pairs(8, seed=4, error_rate=0.9)[:5]
    assert [p.d_vlm for p in want] != [p.d_vlm for p in world.train_pairs(8, seed=4, error_rate=0.3)[:5]]
    bench.main(["--checkpoint", tiny_ckpt, "--trained_pairs", ckpt, "--condition", "vlm", "--n", "5", "--steps", "2",
                "--json", "--videos", str(tmp_path / "v")])
    out = capsys.readouterr().out
    res = json.loads(out.splitlines()[-1])
    assert res["bench"] == f"trained:{ckpt}" and res["error_rate"] == 0.9 and res["n"] == 5
    assert f"bench=the pairs {ckpt} trained on" in out
    rows = [json.loads(line) for line in open(tmp_path / "v" / "videos.jsonl")]
    assert [(r["task"], r["prompt"]) for r in rows] == [(p.task.text, p.d_vlm) for p in want]
    assert "was not trained on the toy VLM's pairs (stage pretrain)" in exit_2(
        bench.main, ["--trained_pairs", tiny_ckpt], capsys)
    assert "--n 9 is more than the 8 pairs" in exit_2(bench.main, ["--trained_pairs", ckpt, "--n", "9"], capsys)
    for extra, named in (({"model": "ltx2-tiny"}, "--model ltx2-tiny"),
                         ({"dataset": "wt.jsonl"}, "--dataset wt.jsonl")):
        real = str(tmp_path / "real.pt")     # an rl run on a real model's pairs, or on a WorldTasks file's
        models.save_checkpoint(model, real, {"stage": "rl", "args": {**dataclasses.asdict(train.Args()), **extra}})
        assert f"was not trained on the toy VLM's pairs ({named})" in exit_2(
            bench.main, ["--trained_pairs", real, "--n", "2"], capsys)
    sft = str(tmp_path / "executor_sft.pt")
    models.save_checkpoint(model, sft, {"stage": "distill", "variant": "sft", "args": dataclasses.asdict(train.Args())})
    assert "is the +SFT baseline" in exit_2(bench.main, ["--trained_pairs", sft, "--n", "2"], capsys)
    old = str(tmp_path / "old.pt")      # a checkpoint from before a flag its pairs depend on
    models.save_checkpoint(model, old, {"stage": "rl", "args": {"train_pairs": 8, "seed": 3, "error_rate": 0.9}})
    assert "does not record its run's --train_crowded" in exit_2(bench.main, ["--trained_pairs", old, "--n", "2"],
                                                                  capsys)
    older = str(tmp_path / "older.pt")     # from before --train_arrangements: each task on one scene
    models.save_checkpoint(model, older, {"stage": "rl", "args": {"train_pairs": 8, "seed": 3, "error_rate": 0.9,
                                                                   "train_crowded": False}})
    assert [(p.task.text, p.d_vlm) for p in bench.trained_pairs(older, 5)[0]] == [(p.task.text, p.d_vlm) for p in want]
    assert "--n 201 is more than the 8 pairs" in exit_2(bench.main, ["--trained_pairs", ckpt, "--n", "201"], capsys)
    assert "not with --crowded" in exit_2(bench.main, ["--trained_pairs", ckpt, "--crowded"], capsys)
    assert "the trained pairs' D are the run's own" in exit_2(
        bench.main, ["--trained_pairs", ckpt, "--condition", "vlm", "--error_rate", "0.1"], capsys)
    assert "--trained_pairs is not read by --gallery" in exit_2(
        bench.main, ["--trained_pairs", ckpt, "--gallery", str(tmp_path / "g.png")], capsys)


def test_keyed_on_moves_or_retasks_each_pair_by_its_rules_and_reads_the_motion(tiny_ckpt, tmp_path, capsys,
                                                                                monkeypatch):
    """bench.py --keyed_on: moved_plan takes a new place of a pair's sprites where T is feasible, its plan P is valid
    but no longer solves T and T's new plan P' moves otherwise, and moved_pairs draws one; other_tasks gives the same
    frame each other task T' where neither plan solves the other's task, and retasked_pairs draws one; each rule
    restated here on draws where each of its reasons occurs. shown_displacement reads a simulated video's motion
    back exactly (camera too), and None where the mover is gone; keyed_scores on simulated executions; arranged_pairs
    takes each task once (a --train_arrangements run's pairs come M to a task) to world.arrangements' new places,
    drawn from the run's seed (the bench's: 0) away from every scene it trained on; the command line, and its
    refusals."""
    import bench
    import reward
    import world
    pairs = world.bench_pairs(0.0)[:6]
    simulated = lambda scene, plan: world.render(scene, world.simulate(scene, plan))    # noqa: E731
    solves = lambda video, task: reward.judge_all(video, task.text)["task"].yes is True  # noqa: E731
    for p in world.bench_pairs(0.0)[:40]:   # the reading, on the simulator's videos (the camera's among them)
        assert np.array_equal(bench.shown_displacement(simulated(p.scene, p.plan_oracle), p.scene, p.plan_oracle),
                              bench.displacement(p.plan_oracle))
    assert any(p.plan_oracle.mover == -1 for p in world.bench_pairs(0.0)[:40])
    gone = simulated(pairs[0].scene, pairs[0].plan_oracle).copy()
    gone[-1] = gone[-1, 0, 0]                                    # the last frame all background: nothing to read
    assert bench.shown_displacement(gone, pairs[0].scene, pairs[0].plan_oracle) is None
    p = next(p for p in world.bench_pairs(0.0) if p.task.kind == "move_to")
    rng, reasons = np.random.default_rng(1), set()
    for _ in range(1000):   # moved_plan's rule, restated, on new places of the first move_to pair's sprites
        xy = rng.integers(1, world.W - 1, size=(len(p.scene.sprites), 2))
        scene = world.Scene([world.Sprite(s.colour, s.shape, int(x), int(y)) for s, (x, y) in
                             zip(p.scene.sprites, xy)], p.scene.background)
        sols = world.solutions(scene, p.task)
        why = ("infeasible" if not sols else "P invalid" if not world.plan_is_valid(scene, p.plan_oracle) else
               "P' is P" if np.abs(bench.displacement(world.canonical_solution(sols))
                                   - bench.displacement(p.plan_oracle)).max() <= 1 else
               "P solves T" if solves(simulated(scene, p.plan_oracle), p.task) else "")
        reasons.add(why)
        q = bench.moved_plan(p, scene)
        assert q == (None if why else world.canonical_solution(sols)), why
    assert reasons == {"infeasible", "P invalid", "P' is P", "P solves T", ""}
    moved = bench.moved_pairs(pairs, tries=3000)
    assert 3 <= len(moved) <= len(pairs)
    for p, q in moved:
        assert q.task == p.task and q.scene.names() == p.scene.names() and world.spaced(
            np.array([[s.x, s.y] for s in q.scene.sprites]))
        assert world.scene_key(q.scene) != world.scene_key(p.scene) and q.d_vlm == world.describe(q.scene,
                                                                                                  q.plan_oracle)
        assert np.array_equal(q.frame0, simulated(q.scene, q.plan_oracle)[0])
        assert world.plan_is_valid(q.scene, p.plan_oracle) and not solves(simulated(q.scene, p.plan_oracle), p.task)
        assert solves(simulated(q.scene, q.plan_oracle), p.task)
        assert np.abs(bench.displacement(q.plan_oracle) - bench.displacement(p.plan_oracle)).max() > 1
    for which, own, new in (("trained_motion", 1.0, 0.0), ("needed_motion", 0.0, 1.0)):
        videos = [simulated(q.scene, p.plan_oracle) for p, q in moved]          # P done on the moved scenes
        assert bench.keyed_scores("moved", np.stack(videos), moved)[which] == own
        videos = [simulated(q.scene, q.plan_oracle) for p, q in moved]          # P', what T needs there
        assert bench.keyed_scores("moved", np.stack(videos), moved)[which] == new
    reasons = set()
    for p in world.bench_pairs(0.0)[:12]:   # other_tasks' rule, restated, on every task of the first 12 scenes
        chosen = dict((t.text, q) for t, q in bench.other_tasks(p))
        for t in world.candidate_tasks(p.scene):
            sols = world.solutions(p.scene, t)
            why = ("T" if t.text == p.task.text else "infeasible" if not sols else
                   "P' solves T" if solves(simulated(p.scene, world.canonical_solution(sols)), p.task) else
                   "P solves T'" if solves(simulated(p.scene, p.plan_oracle), t) else "")
            reasons.add(why)
            assert chosen.get(t.text) == (None if why else world.canonical_solution(sols)), why
    assert reasons == {"T", "infeasible", "P' solves T", "P solves T'", ""}
    retasked = bench.retasked_pairs(pairs)
    assert len(retasked) == len(pairs)
    for p, q in retasked:
        assert q.scene is p.scene and q.frame0 is p.frame0 and q.task.text != p.task.text
        assert not solves(simulated(p.scene, q.plan_oracle), p.task) and not solves(simulated(p.scene, p.plan_oracle),
                                                                                  q.task)
        assert solves(simulated(p.scene, q.plan_oracle), q.task)
    done = lambda plan_of: np.stack([simulated(p.scene, plan_of(p, q)) for p, q in retasked])    # noqa: E731
    assert bench.keyed_scores("retasked", done(lambda p, q: p.plan_oracle), retasked)["trained_task"] == 1.0
    assert bench.keyed_scores("retasked", done(lambda p, q: q.plan_oracle), retasked)["trained_task"] == 0.0
    arranged = bench.arranged_pairs(pairs, 2, 3, world.bench_scene_keys())     # each task once: pairs 0, 2 and 4
    assert [p for p, _ in arranged] == [pairs[i] for i in (0, 2, 4) for _ in range(bench.ARRANGED)]
    rng, avoid = np.random.default_rng([3, 8]), set(world.bench_scene_keys())       # drawn from (seed, 8)
    assert [q.scene for _, q in arranged] == [q.scene for p in pairs[::2]
                                              for q in world.arrangements(p, bench.ARRANGED, rng, avoid)]
    assert bench.keyed_scores("arranged", np.zeros(len(arranged)), arranged) == {"tasks": 3}
    import dataclasses
    import models
    import train
    ckpt = str(tmp_path / "executor_on.pt")     # a run of 2 tasks on 4 places each
    models.save_checkpoint(models.load_checkpoint(tiny_ckpt)[0], ckpt, {"stage": "distill", "variant": "on", "args":
                           dataclasses.asdict(train.Args(train_pairs=8, train_arrangements=4, seed=3, error_rate=0))})
    bench.main(["--checkpoint", tiny_ckpt, "--trained_pairs", ckpt, "--keyed_on", "arranged", "--n", "8", "--steps",
                "2", "--condition", "vlm", "--json", "--videos", str(tmp_path / "a")])
    out = capsys.readouterr().out
    res = json.loads(out.splitlines()[-1])
    assert res["keyed_on"] == "arranged" and res["n"] == 12 and res["tasks"] == 2 and 0 <= res["task"] <= 1
    assert "--keyed_on arranged: 6 new places of each of the 2 tasks of the 8 pairs" in out
    own = train.toy_pairs(train.Args(train_pairs=8, train_arrangements=4, seed=3, error_rate=0))
    want = bench.arranged_pairs(own, 4, 3, world.bench_scene_keys() | {world.scene_key(p.scene) for p in own})
    rows = [json.loads(line) for line in open(tmp_path / "a" / "videos.jsonl")]
    assert [(r["task"], r["prompt"]) for r in rows] == [(q.task.text, q.d_vlm) for _, q in want]
    bench.main(["--checkpoint", tiny_ckpt, "--keyed_on", "arranged", "--n", "2", "--steps", "2", "--json",
                "--condition", "oracle", "--videos", str(tmp_path / "b")])      # the bench's first 2, from seed 0
    want = bench.arranged_pairs(world.bench_pairs(0.0)[:2], 1, 0, world.bench_scene_keys())
    rows = [json.loads(line) for line in open(tmp_path / "b" / "videos.jsonl")]
    assert [r["prompt"] for r in rows] == [q.d_oracle for _, q in want] and json.loads(
        capsys.readouterr().out.splitlines()[-1])["n"] == 12
    with monkeypatch.context() as m:
        m.setattr(world, "arrangements", lambda *a: (_ for _ in ()).throw(ValueError("no new place")))
        assert "--keyed_on arranged: no new place" in exit_2(
            bench.main, ["--checkpoint", tiny_ckpt, "--keyed_on", "arranged", "--n", "2"], capsys)
    bench.main(["--checkpoint", tiny_ckpt, "--keyed_on", "retasked", "--n", "3", "--steps", "2", "--json",
                "--videos", str(tmp_path / "v")])
    out = capsys.readouterr().out
    res = json.loads(out.splitlines()[-1])
    assert res["keyed_on"] == "retasked" and res["n"] == 3 and 0 <= res["trained_task"] <= 1
    assert "--keyed_on retasked: 3 of 3 pairs" in out and "the pair's own task T solved in" in out
    rows = [json.loads(line) for line in open(tmp_path / "v" / "videos.jsonl")]
    assert [r["task"] for r in rows] == [q.task.text for _, q in bench.retasked_pairs(world.bench_pairs(0.3)[:3])]
    assert "--keyed_on is not read by --handoff" in exit_2(bench.main, ["--keyed_on", "moved", "--handoff",
                                                                        "task,vlm"], capsys)
    assert "--keyed_on and --gallery are toy diagnostics" in exit_2(
        bench.main, ["--keyed_on", "moved", "--model", "ltx2-tiny"], capsys)
    assert "--keyed_on's pairs have the error-free D" in exit_2(
        bench.main, ["--keyed_on", "moved", "--condition", "vlm", "--error_rate", "0.1"], capsys)
    monkeypatch.setattr(bench, "moved_pairs", lambda pairs: [])      # no pair with a scene to move to
    assert "--keyed_on moved: none of the 2 pairs can be moved" in exit_2(
        bench.main, ["--checkpoint", tiny_ckpt, "--keyed_on", "moved", "--n", "2"], capsys)


def test_bench_is_deterministic(tiny_ckpt):
    a = run("bench.py", "--checkpoint", tiny_ckpt, "--n", "3", "--steps", "2", "--json", "--seed", "1")
    b = run("bench.py", "--checkpoint", tiny_ckpt, "--n", "3", "--steps", "2", "--json", "--seed", "1")
    strip = lambda r: {k: v for k, v in json.loads(r.stdout.splitlines()[-1]).items() if "seconds" not in k}
    assert strip(a) == strip(b)


@pytest.mark.skipif(not os.path.exists(os.path.join(ROOT, "checkpoints", "base.pt")), reason="no shipped base")
def test_bench_on_the_shipped_base():
    r = run("bench.py", "--condition", "task", "--n", "2", "--steps", "2", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.splitlines()[-1])["checkpoint"] == "shipped base"


@pytest.mark.skipif(not os.path.exists(os.path.join(ROOT, "checkpoints", "base.pt")), reason="no shipped base")
def test_evaluate_samples_the_bench_with_its_guidance(shipped):
    """bench.evaluate(guidance=w) judges the videos models.generate samples with guidance w (the shipped base, whose
    velocity reads the prompt, so that guidance changes them)."""
    import numpy as np

    import bench
    import models
    base = shipped
    res, videos, pairs = bench.evaluate(base, "task", n=2, steps=2, guidance=3.0)
    prompts = bench.prompts_for(pairs, "task")
    assert res["guidance"] == 3.0
    assert np.array_equal(videos, models.generate(base, np.stack([p.frame0 for p in pairs]), prompts, steps=2, seed=0,
                                                  guidance=3.0))
    assert not np.array_equal(videos, bench.evaluate(base, "task", n=2, steps=2)[1])


def test_help_lists_every_flag_with_its_doc():
    r = run("train.py", "--help")
    assert r.returncode == 0 and "--beta_d" in r.stdout and "Eq. 12" in r.stdout and "--resume" in r.stdout
    assert run("bench.py", "--help").returncode == 0


def test_bad_input_gives_one_clear_error(tmp_path, capsys):
    import bench
    import train
    r = run("bench.py", "--condition", "bogus")
    assert r.returncode == 2 and "invalid choice: 'bogus'" in r.stderr
    assert "--handoff wants A,B" in exit_2(bench.main, ["--handoff", "task,bogus"], capsys)
    assert "--pointing and --rank_rdistill are two different diagnostics" in exit_2(
        bench.main, ["--pointing", "--rank_rdistill"], capsys)
    assert "--png is not read by --pointing: it would be ignored" in exit_2(
        bench.main, ["--pointing", "--png", tmp_path / "p.png"], capsys)
    assert "--group is read by --rank_rdistill only" in exit_2(bench.main, ["--group", "4"], capsys)
    r = run("train.py", "--stage", "bogus")
    assert r.returncode == 2 and "invalid choice: 'bogus'" in r.stderr
    for argv, msg in ((["--steps", "0"], "--steps must be >= 1"), (["--variant", "on,bogus"], "unknown 'bogus'"),
                      (["--stage", "distill", "--variant", "on,off,on"], "--variant: 'on' given twice"),
                      (["--trainer", "ppo"], "--trainer: unknown 'ppo'"),
                      (["--group_size", "1"], "--group_size must be >= 2"), (["--beta_d", "-0.1"], "--beta_d must be >= 0"),
                      (["--lr", "-1"], "--lr must be > 0"), (["--ghuber_power", "0"], "--ghuber_power must be > 0"),
                      (["--beta_d", "nan"], "--beta_d must be a finite number"),
                      (["--stage", "pretrain", "--pretrain_lr", "inf"], "--pretrain_lr must be a finite number"),
                      (["--seed", "-1"], "--seed must be >= 0"), (["--noise_level", "-0.7"], "--noise_level must be >= 0"),
                      (["--stage", "distill", "--variant", "off,on", "--out", "x.pt"], "--out names one checkpoint"),
                      (["--stage", "pretrain", "--resume"], "--resume continues an rl or distill run"),
                      (["--stage", "distill", "--variant", "off,on", "--resume"],
                       "--resume continues a distill run of one --variant"),
                      (["--stage", "pretrain", "--point_weight", "0.1"], "it needs --relate"),
                      (["--stage", "pretrain", "--p_task_words", "1.5"], "--p_task_words must lie in [0, 1]"),
                      (["--stage", "pretrain", "--relate", "--point_goal_only"], "it needs --point_weight > 0"),
                      (["--stage", "pretrain", "--relate_text"],
                       "--relate_text gives Relate its own text encoder: it needs --relate")):
        assert msg in exit_2(train.parse_args, argv, capsys), argv    # the flag checks, no run started
    assert "pretrained with --relate" in exit_2(bench.main, ["--pointing", "--n", "2"], capsys)
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"garbage")
    r = run("bench.py", "--checkpoint", str(bad), "--n", "2")
    assert r.returncode == 2 and "corrupt" in r.stderr and "Traceback" not in r.stderr
    assert "does not exist" in exit_2(bench.main, ["--checkpoint", tmp_path / "missing.pt", "--n", "2"], capsys)
    assert "is a directory, not a checkpoint file" in exit_2(bench.main, ["--checkpoint", tmp_path, "--n", "2"], capsys)
    g = tmp_path / "g.png"
    for argv, msg in ((["--gallery", g, "--n", "13"], "--gallery draws at most 12 pairs"),
                      (["--executor", bad], "--executor is --gallery's Executor row"),
                      (["--gallery", g, "--handoff", "task,vlm"], "--gallery draws videos of the bench: not with"),
                      (["--gallery", g, "--png", tmp_path / "s.png"], "--gallery draws videos of the bench: not with"),
                      (["--gallery", g, "--model", "ltx2-tiny"], "toy diagnostics"),
                      (["--gallery", g, "--executor", bad], "corrupt")):
        assert msg in exit_2(bench.main, argv, capsys), argv
    assert not g.exists()
    no_gpu = not torch.cuda.is_available()
    for argv, msg in ((["--n", "0"], "--n must be >= 1"), (["--n", "201"], "--n must lie in 1..200"),
                      (["--batch", "0"], "--batch must be >= 1"), (["--model", "ltx2"], "--model ltx2 needs --model_path"),
                      *([(["--model", "hunyuan15-random"], "it needs a CUDA GPU"),
                         (["--judge", "qwen-vl-random"], "it needs a CUDA GPU")] if no_gpu else []),
                      (["--judge", "qwen-vl"], "--judge qwen-vl needs --judge_path"),
                      (["--model_path", tmp_path], "--model_path is read with --model ltx2 or hunyuan15 (real weights)"
                                                   " only: --model toy would ignore it"),
                      (["--model", "ltx2-tiny", "--model_path", tmp_path], "--model ltx2-tiny would ignore it"),
                      (["--judge_path", tmp_path], "--judge_path is read with --judge qwen-vl (real weights) only: "
                                                   "--judge toy would ignore it"),
                      (["--judge", "qwen-vl-tiny", "--judge_path", tmp_path], "--judge qwen-vl-tiny would ignore"),
                      (["--pick", "pickscore"], "--pick pickscore needs --pick_path"),
                      (["--pick_path", tmp_path], "--pick_path is read with --pick pickscore (real weights) only: "
                                                  "--pick none would ignore it"),
                      (["--pick", "pickscore-tiny", "--pick_processor_path", tmp_path], "--pick pickscore-tiny would"),
                      (["--pick", "clip"], "invalid choice: 'clip'"),
                      (["--offload_judge"], "--offload_judge is for a VLM judge's weights"),
                      (["--offload_text"], "--offload_text is for a real model's text encoder"),
                      (["--height", "32", "--width", "32"], "--height and --width are for a real model"),
                      (["--height", "32"], "--height and --width go together, both > 0, got 32 x 0"),
                      (["--lora", bad], "--lora loads a real model's Executor"),
                      (["--model", "ltx2-tiny", "--checkpoint", bad], "--checkpoint is a toy model file"),
                      (["--dataset", tmp_path / "d.jsonl", "--condition", "oracle"], "needs the toy bench's scenes"),
                      (["--crowded", "--dataset", tmp_path / "d.jsonl"], "--crowded is a toy bench and --dataset"),
                      (["--crowded", "--pointing"], "--crowded is not read by --pointing"),
                      (["--error_rate", "1.5"], "--error_rate must lie in [0, 1]"),
                      (["--steps", "0"], "--steps must be >= 1"), (["--guidance", "-1"], "--guidance must be a finite"),
                      (["--guidance", "nan"], "--guidance must be a finite number >= 0"),
                      (["--guidance", "inf"], "--guidance must be a finite number >= 0"),
                      (["--threads", "0"], "--threads must be >= 1"),
                      (["--guidance", "2", "--handoff", "task,vlm"], "--guidance applies to one evaluation"),
                      (["--rank_rdistill", "--group", "1"], "--group must be >= 2"),
                      (["--handoff", "task,vlm", "--rank_rdistill"], "two different diagnostics"),
                      (["--relate_probe", "zeroed", "--handoff", "task,vlm"], "--relate_probe alters one evaluation"),
                      (["--handoff", "task,vlm,oracle"], "--handoff wants A,B")):
        # --n 2 first: a check that let its value through evaluates two pairs and the test fails soon after
        assert msg in exit_2(bench.main, ["--n", "2", *argv], capsys), argv


def test_output_paths_are_checked_before_any_work(tmp_path, capsys, monkeypatch):
    """Where a script writes -- train.py's --run_dir, --eval_cache, --out; bench.py's --png, --gallery; report.py's
    OUT_DIR -- is checked with the flags, not found wrong after the work (a traceback at the end, the run lost).
    Missing folders on the way are made when the file is written."""
    import bench
    import report
    import train
    f, d = tmp_path / "f", tmp_path / "d"
    f.write_text("")
    d.mkdir()
    for argv, msg in ((["--run_dir", f], "--run_dir '%s' is a file, not a directory" % f),
                      (["--run_dir", f / "x"], "'%s' is a file, so nothing can be made inside it" % f),
                      (["--eval_cache", f], "--eval_cache '%s' is a file" % f),
                      (["--stage", "distill", "--out", d], "--out '%s' is a directory, not a file" % d)):
        assert msg in exit_2(train.parse_args, [str(a) for a in argv], capsys), argv
    for argv, msg in ((["--png", d], "--png '%s' is a directory" % d), (["--png", tmp_path / "x.jpg"], "end in .png"),
                      (["--gallery", f / "g.png"], "is a file, so nothing can be made inside it")):
        assert msg in exit_2(bench.main, ["--n", "2", *map(str, argv)], capsys), argv
    assert "OUT_DIR '%s' is a file" % f in exit_2(report.main, [str(f), "--quick"], capsys)
    assert bench.output_path_error(str(tmp_path / "new" / "run"), "--run_dir", directory=True) is None
    monkeypatch.setattr(os, "access", lambda path, mode: False)      # as for a folder of someone else's, not root's
    assert "no permission to write in '%s'" % tmp_path in bench.output_path_error(str(tmp_path / "a" / "x.png"), "--png")
    monkeypatch.undo()
    bench.save_strip(torch.zeros(2, 3, 16, 16, 3, dtype=torch.uint8).numpy(), str(tmp_path / "a" / "b" / "s.png"))
    assert (tmp_path / "a" / "b" / "s.png").exists()


def test_each_bench_condition_prompts_with_its_own_text():
    """bench.prompts_for: T, the toy VLM's D (the plan it describes, wrong where it erred), the error-free D (the
    solution's), a vague caption of the solution's motion, the empty prompt, T's words as a goal caption; the
    instruction and direction forms rewrite those Ds. Every condition bench.py offers is here."""
    import bench
    import world
    pairs = world.bench_pairs(0.3)[:40]
    assert any(p.error for p in pairs)
    want = {"task": lambda p: p.task.text, "vlm": lambda p: world.describe(p.scene, p.plan_vlm),
            "oracle": lambda p: world.describe(p.scene, p.plan_oracle),
            "vague": lambda p: world.vague_caption(p.scene, p.plan_oracle), "empty": lambda p: "",
            "goal": lambda p: world.goal_caption(p.task),
            "instruction": lambda p: world.instruction_form(world.describe(p.scene, p.plan_vlm)),
            "oracle_instruction": lambda p: world.instruction_form(world.describe(p.scene, p.plan_oracle)),
            "oracle_direction": lambda p: world.direction_form(world.describe(p.scene, p.plan_oracle))}
    assert sorted(want) == sorted(bench.CONDITIONS)
    for condition, prompt in want.items():
        assert bench.prompts_for(pairs, condition) == [prompt(p) for p in pairs], condition


def test_gallery_draws_the_videos_the_bench_judges(tiny_ckpt, tmp_path):
    import numpy as np
    from PIL import Image
    import bench
    import models
    model, _ = models.load_checkpoint(tiny_ckpt)
    rows = bench.gallery(model, model, "oracle", n=3, seed=1, steps=2, path=str(tmp_path / "g.png"))
    assert [r["label"] for r in rows] == ["simulator: the error-free D", "Demonstrator: base given the toy VLM's D",
                                          "base given the error-free D", "Executor given the error-free D"]
    # the first row is the simulator executing the error-free D, which the judges pass
    assert all(j[k].yes for j in rows[0]["judgments"] for k in bench.KEYS)
    # every other row is the videos evaluate() generates and judges for those pairs, from the same noise
    for r, cond in zip(rows[1:], ("vlm", "oracle", "oracle")):
        res, videos, _ = bench.evaluate(model, cond, 3, seed=1, steps=2)
        assert np.array_equal(r["videos"], videos), cond
        assert sum(bool(j["task"].yes) for j in r["judgments"]) == res["successes"]["task"]
        assert res["still"] == bench.still_videos(videos) / 3 and res["still"] > 0     # a share of the videos
    no_executor = bench.gallery(model, n=3, seed=1, steps=2)
    assert [r["label"] for r in no_executor][2:] == ["base given T"]    # no Executor row, and the base given T
    w, h = Image.open(tmp_path / "g.png").size
    assert w > 500 and h > 300
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--gallery", str(tmp_path / "cli.png"), "--n", "2", "--steps", "2",
            "--seed", "1", "--json")
    assert r.returncode == 0 and (tmp_path / "cli.png").stat().st_size > 1000, r.stderr
    assert "simulator: the error-free D: task 2/2, agent 2/2, consistency 2/2" in r.stdout
    out = json.loads(r.stdout.splitlines()[-1])
    assert out["rows"][2] == {"label": "base given T", **{k: [j[k].yes for j in no_executor[2]["judgments"][:2]]
                                                          for k in bench.KEYS}}


def test_crowded_evaluates_and_draws_the_crowded_benchs_pairs(tiny_ckpt, tmp_path):
    """bench.py --crowded judges and draws world.crowded_pairs (5 sprites a scene), not the bench's pairs."""
    import numpy as np
    from PIL import Image
    import bench
    import models
    import world
    model, _ = models.load_checkpoint(tiny_ckpt)
    crowded = world.crowded_pairs(bench.DEFAULT_ERROR_RATE)
    res, videos, _ = bench.evaluate(model, "task", 3, seed=1, steps=2, pairs=crowded)
    assert all(len(world.read_sprites(v[0])) == 5 for v in videos)
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--crowded", "--n", "3", "--steps", "2", "--seed", "1", "--json",
            "--png", str(tmp_path / "c.png"))
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.splitlines()[-1])
    assert out["bench"] == "crowded" and "bench=crowded" in r.stdout
    assert {k: out[k] for k in ("successes", "kinds", "still")} == {k: res[k] for k in ("successes", "kinds", "still")}
    bench.save_strip(videos, str(tmp_path / "want.png"))
    assert np.array_equal(np.asarray(Image.open(tmp_path / "c.png")), np.asarray(Image.open(tmp_path / "want.png")))
    bench.save_strip(bench.evaluate(model, "task", 3, seed=1, steps=2)[1], str(tmp_path / "toy.png"))
    assert not np.array_equal(np.asarray(Image.open(tmp_path / "c.png")), np.asarray(Image.open(tmp_path / "toy.png")))
    rows = bench.gallery(model, n=2, seed=1, steps=2, path=str(tmp_path / "want_g.png"), crowded=True)
    assert np.array_equal(rows[0]["videos"], [world.render(p.scene, world.simulate(p.scene, p.plan_oracle))
                                              for p in crowded[:2]])
    assert np.array_equal(rows[2]["videos"], videos[:2])      # the base given T: the videos evaluate judged
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--gallery", str(tmp_path / "g.png"), "--crowded", "--n", "2",
            "--steps", "2", "--seed", "1", "--json")
    assert r.returncode == 0, r.stderr
    assert np.array_equal(np.asarray(Image.open(tmp_path / "g.png")), np.asarray(Image.open(tmp_path / "want_g.png")))


def test_compare_runs_on_fake_runs(tmp_path):
    import PIL.Image

    import bench
    for name, tasks in (("a", [0.1, 0.3, 0.2]), ("b", [0.1, 0.0, 0.05])):
        d = tmp_path / name
        d.mkdir()
        lines = [{"eval": True, "step": 10 * i, "task": t, "agent": 0.5, "consistency": 0.9, "avg": 0.5}
                 for i, t in enumerate(tasks)] + [{"step": 1, "loss": 0.1}]
        if name == "a":   # a run that logged its still rollouts (since stop 78): 0 of 4 at steps 1, 2, then 2 of 4
            lines[-2]["still"] = 0.25
            lines[-1:] = [{"step": k, "still": 0 if k <= 2 else 2, "A": [0.0] * 4} for k in range(1, 13)]
        (d / "rl.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    json.dump({"table": {"Base + VLM (Demonstrator, toy VLM's D)": {"task": 0.6, "consistency": 0.9}}},
              open(tmp_path / "a" / "rl_summary.json", "w"))
    table = bench.compare_runs({"A": str(tmp_path / "a"), "B": str(tmp_path / "b")}, str(tmp_path / "cmp.png"))
    assert "| A | 0.100 | 0.300 (10) | 0.200 |" in table and "| B | 0.100 | 0.100 (0) | 0.050 |" in table
    # still videos at the end and the still training rollouts' share over the last 10 steps (3..12: 2 of 4 each);
    # B logged neither
    rows = table.splitlines()
    assert rows[2].endswith("| 0.500 | 0.250 | 0.500 |") and rows[3].endswith("| – | – |")
    rolled = bench.rolling_still(bench.read_run(str(tmp_path / "a"))["steps"])
    assert [(r["step"], round(r["still"], 3)) for r in rolled] == [(10, 0.4), (11, 0.45), (12, 0.5)]
    assert PIL.Image.open(tmp_path / "cmp.png").size[0] > 1400      # three panels: the still share is drawn
    bench.compare_runs({"B": str(tmp_path / "b")}, str(tmp_path / "two.png"))
    assert PIL.Image.open(tmp_path / "two.png").size[0] < 1300      # two: nothing logged to draw
    # runs that recorded PickScore at each evaluation (train.py --pick; Fig. 4 left's second panel): its column at
    # the end and its panel; beside a run without it, neither
    for name, picks in (("c", [20.0, 21.0, 22.5]), ("d", [20.0, 20.5, 19.0])):
        (tmp_path / name).mkdir()
        (tmp_path / name / "rl.jsonl").write_text("".join(json.dumps(
            {"eval": True, "step": 10 * i, "task": 0.1, "agent": 0.5, "consistency": 0.9, "avg": 0.5, "pick": v})
            + "\n" for i, v in enumerate(picks)))
    rows = bench.compare_runs({"C": str(tmp_path / "c"), "D": str(tmp_path / "d")}, str(tmp_path / "pick.png"))
    rows = rows.splitlines()
    assert rows[0].endswith("| PickScore @end |") and rows[2].endswith("| 22.500 |") and rows[3].endswith("| 19.000 |")
    assert PIL.Image.open(tmp_path / "pick.png").size[0] > 1400      # task, consistency and PickScore
    assert "PickScore" not in bench.compare_runs({"B": str(tmp_path / "b"), "C": str(tmp_path / "c")})
    # a run on a real-image bench (train.py --eval_dataset): its Demonstrator row, named for the file's D, is read as
    # the Demonstrator's; its bench is the file, refused beside the toy bench's runs
    json.dump({"args": {"eval_dataset": "wt_bench.jsonl"}, "table": {
        "Base + VLM (Demonstrator, the bench file's D)": {"task": 0.4, "consistency": 0.8, "pick": 21.0}}},
        open(tmp_path / "c" / "rl_summary.json", "w"))
    got = bench.read_run(str(tmp_path / "c"))
    assert got["bench"] == "wt_bench.jsonl" and got["fixed"][bench.DEMO_ROW]["pick"] == 21.0
    with pytest.raises(ValueError, match=r"different benches \(toy, wt_bench.jsonl; "):
        bench.compare_runs({"A": str(tmp_path / "a"), "C": str(tmp_path / "c")})
    # two seeds of one setting: cells are mean ± sd, the peak is the mean curve's (0.15 at step 10: (0.3 + 0.0) / 2)
    table = bench.compare_runs({"A+B": [str(tmp_path / "a"), str(tmp_path / "b")]}, str(tmp_path / "band.png"))
    assert "| A+B | 0.100 ± 0.000 | 0.150 (10) | 0.125 ± 0.106 | 0.900 ± 0.000 |" in table
    r = run("bench.py", "--compare", f"A={tmp_path / 'a'},{tmp_path / 'b'}", "--png", str(tmp_path / "cli.png"))
    assert r.returncode == 0 and "0.125 ± 0.106" in r.stdout and (tmp_path / "cli.png").stat().st_size > 1000
    r = run("bench.py", "--compare", f"A={tmp_path / 'missing'}")
    assert r.returncode == 2 and "no rl.jsonl (nor a distill run's distill.jsonl)" in r.stderr
    assert bench.compare_items(["A=x", "B=y,z"]) == {"A": ["x"], "B": ["y", "z"]}
    for items, why in ((["runs"], "'runs' lacks a label"), (["=runs"], "'=runs' lacks"),
                       (["A="], "'A=' lacks"), (["A=x,"], "'A=x,' lacks"), (["A=x", "A=y"], "'A' is given twice")):
        with pytest.raises(ValueError, match=why):
            bench.compare_items(items)
    r = run("bench.py", "--compare", str(tmp_path / "a"))
    assert r.returncode == 2 and "lacks a label, its '=' or a run dir" in r.stderr
    # a distill run of one variant (its curve, its Demonstrator once finished, its bench), and of two (refused)
    d = tmp_path / "sft"
    d.mkdir()
    lines = [{"eval": True, "variant": "paired", "step": 10 * i, "task": t, "agent": 0.5, "consistency": 0.9,
              "avg": 0.5, "still": 0.0} for i, t in enumerate([0.2, 0.6])]
    (d / "distill.jsonl").write_text("".join(json.dumps(r) + "\n" for r in [lines[0], {"variant": "paired", "step": 1,
                                                                                      "loss": 0.1}, lines[1]]))
    assert bench.read_run(str(d))["bench"] is None and bench.read_run(str(d))["fixed"] == {}    # not finished
    json.dump({"demonstrator": {"task": 0.6, "consistency": 0.9}, "variants": {}, "executor_prompt": "task",
               "bench": "crowded"}, open(d / "distill_summary.json", "w"))
    got = bench.read_run(str(d))
    assert [e["task"] for e in got["evals"]] == [0.2, 0.6] and got["steps"] == [] and got["bench"] == "crowded"
    assert got["fixed"] == {bench.DEMO_ROW: {"task": 0.6, "consistency": 0.9}}
    assert "| SFT | 0.200 | 0.600 (10) | 0.600 |" in bench.compare_runs({"SFT": str(d)}, str(tmp_path / "sft.png"))
    with pytest.raises(ValueError, match="evaluated on different benches"):       # a's summary: the bench
        bench.compare_runs({"A": str(tmp_path / "a"), "SFT": str(d)})
    bench.compare_runs({"B": str(tmp_path / "b"), "SFT": str(d)})                  # b is unfinished: no bench known
    (d / "distill.jsonl").write_text((d / "distill.jsonl").read_text() + json.dumps({**lines[0], "variant": "on"}))
    with pytest.raises(ValueError, match=r"the curves of 2 variants \(on, paired\)"):
        bench.read_run(str(d))
    # a run not yet evaluated, one cut off mid-line, seeds that share no evaluated step: a message, not max()'s
    for name, text in (("new", '{"step": 1, "loss": 0.1}\n'), ("cut", '{"step": 1, "loss": 0.1}\n{"step": 2, "lo'),
                       ("odd", '{"eval": true, "step": 5, "task": 0.1}\n')):
        (tmp_path / name).mkdir()
        (tmp_path / name / "rl.jsonl").write_text(text)
    for runs, msg in (({"N": str(tmp_path / "new")}, "holds no bench evaluation yet"),
                      ({"C": str(tmp_path / "cut")}, "rl.jsonl line 2 is not JSON"),
                      ({"A+O": [str(tmp_path / "a"), str(tmp_path / "odd")]}, "share no evaluated step")):
        with pytest.raises(ValueError, match=msg):
            bench.compare_runs(runs)


def test_handoff_switches_the_prompt_at_the_grid_time(tiny_ckpt, tmp_path):
    """bench.handoff's sampler: switching at t = 0 is B's ODE, at t = 1 A's, in between neither; the endpoints of
    handoff() score as evaluate() does with the same noise."""
    import numpy as np
    import torch

    import bench
    import flow
    import models
    import world
    model, _ = models.load_checkpoint(tiny_ckpt)
    pairs = world.bench_pairs(0.3)[:3]
    frame0 = np.stack([p.frame0 for p in pairs])
    c_a = model.condition(frame0, bench.prompts_for(pairs, "task"))
    c_b = model.condition(frame0, bench.prompts_for(pairs, "oracle"))
    x_0 = torch.randn(3, *model.latent_shape(), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        only = {"a": flow.sample_ode(lambda x, t: model(x, t, c_a), x_0, 4),
                "b": flow.sample_ode(lambda x, t: model(x, t, c_b), x_0, 4)}
        sw = {s: flow.sample_ode(bench.switched_field(model, c_a, c_b, s), x_0, 4) for s in (0.0, 0.5, 1.0)}
    assert torch.equal(sw[0.0], only["b"]) and torch.equal(sw[1.0], only["a"])
    assert not torch.equal(sw[0.5], only["a"]) and not torch.equal(sw[0.5], only["b"])
    decoded, decode = [], model.decode               # the final states handoff() judges, one per switch time
    model.decode = lambda x_1, f0: decoded.append(x_1) or decode(x_1, f0)
    try:
        res = bench.handoff(model, "task", "oracle", n=3, seed=0, steps=2)
    finally:
        del model.decode
    noise = models.seeded_noise(model, 3, 0)         # evaluate()'s
    with torch.no_grad():                            # the switch at t = 0 is B's ODE, at t = 1 A's
        for k, c in ((0, c_b), (2, c_a)):
            assert torch.equal(decoded[k], flow.sample_ode(lambda x, t: model(x, t, c), noise, 2))
    assert res["switch"] == [0.0, 0.5, 1.0] and len(res["discrepancy"]) == 2 and res["discrepancy"][0] > 0
    for k, cond in ((0, "oracle"), (2, "task")):
        ev = bench.evaluate(model, cond, n=3, seed=0, steps=2)[0]
        assert all(res[key][k] == ev[key] for key in ("task", "agent", "consistency", "solved"))
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--handoff", "task,oracle", "--n", "3", "--steps", "2", "--json",
            "--png", str(tmp_path / "h.png"))
    assert r.returncode == 0, r.stderr
    assert "| 0.5 |" in r.stdout and "kept: of the" in r.stdout and (tmp_path / "h.png").stat().st_size > 1000
    assert json.loads(r.stdout.splitlines()[-1])["task"] == res["task"]


def test_relate_probe_forces_the_heads_or_zeroes_relate_and_then_restores_it(tiny_ckpt):
    """bench.relate_probe: forced, heads 0 and 1 land on every pair's agent and target sprite; zeroed, the velocity
    no longer depends on Relate's weights; on exit the model is as it was. A base without Relate is a clear error."""
    import dataclasses

    import numpy as np
    import torch

    import bench
    import models
    import world
    torch.manual_seed(0)
    m = models.make_model("toy", width=16, emb_dim=32, text_dim=32, relate=True).eval()
    for p in m.parameters():                        # off the zero-initialised layers, so the U-Net reads Relate
        p.data.add_(0.05 * torch.randn_like(p))
    pairs = world.bench_pairs(0.3)[:12]
    before = bench.pointing(m, "task", n=12)
    assert before["agent"] < 1 and before["n_target"] > 0
    with bench.relate_probe(m, pairs, "forced"):
        forced = bench.pointing(m, "task", n=12)
        with pytest.raises(RuntimeError, match="maps for 12 pairs"):
            bench.pointing(m, "task", n=5)
    assert forced["agent"] == forced["target"] == 1.0
    assert bench.pointing(m, "task", n=12) == before
    with pytest.raises(ValueError, match="unknown relate probe 'sideways'; choose from forced, zeroed"):
        bench.relate_probe(m, pairs, "sideways")                   # refused on the call, before any with block
    # heads 0 and 1 forced onto each other's sprite: each role is found by a head, not by the head that pointing
    # reads for it (head 0 the agent, head 1 the target)
    names = lambda p: {s.name for s in p.scene.sprites}  # noqa: E731
    swapped = [dataclasses.replace(p, task=dataclasses.replace(p.task, agent=p.task.target, target=p.task.agent))
               if {p.task.agent, p.task.target} <= names(p) else p for p in pairs]
    n_swapped = sum(s is not p for s, p in zip(swapped, pairs))
    with bench.relate_probe(m, swapped, "forced"):
        crossed = bench.pointing(m, "task", n=12)
    assert n_swapped > 0 and crossed["agent_any"] == crossed["target_any"] == 1.0
    for role in ("agent", "target"):
        assert crossed[role] == pytest.approx(1 - n_swapped / crossed[f"n_{role}"])
    c = m.condition(np.stack([p.frame0 for p in pairs]), bench.prompts_for(pairs, "task"))
    x, t = torch.randn(12, *m.latent_shape(), generator=torch.Generator().manual_seed(0)), torch.full((12,), 0.5)
    with torch.no_grad():
        as_is = m(x, t, c)
        with bench.relate_probe(m, pairs, "zeroed"):
            zeroed = m(x, t, c)
            m.relate.q[-1].bias.add_(1.0)
            assert torch.equal(m(x, t, c), zeroed)
        assert not torch.allclose(m(x, t, c), zeroed) and not torch.allclose(as_is, zeroed)
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--relate_probe", "forced", "--n", "2")
    assert r.returncode == 2 and "pretrained with --relate" in r.stderr
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--relate_probe", "zeroed", "--pointing")
    assert r.returncode == 2 and "--pointing with zeroed" in r.stderr


def test_rank_rdistill_ranks_within_groups_the_rollouts_it_draws(tiny_ckpt):
    """bench.rank_rdistill: Spearman against hand-made ranks (ties shared), and its per-rollout r_distill, motion and
    task judgment are those of the group's own rollouts, recomputed here from the same noise."""
    import numpy as np
    import torch

    import bench
    import distill
    import flow
    import models
    import reward
    import world
    assert bench._spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert bench._spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    tied = np.corrcoef([0, 1, 2, 3], [0.5, 0.5, 2.5, 2.5])[0, 1]   # the two ties share ranks 0.5 and 2.5
    assert bench._spearman([1, 2, 3, 4], [0, 0, 1, 1]) == pytest.approx(tied)
    assert np.isnan(bench._spearman([1, 2, 3], [5, 5, 5]))
    model, _ = models.load_checkpoint(tiny_ckpt)
    res = bench.rank_rdistill(model, "task", n=3, group=4, seed=1, steps=2, chunk=2)
    assert len(res["r_distill"]) == len(res["motion"]) == len(res["task"]) == 12
    p = world.bench_pairs(0.3)[0]      # the first pair's group, rows 0..3: its D is wrong, not the error-free D
    assert p.error and p.d_vlm != p.d_oracle
    frame0 = np.stack([p.frame0] * 4)
    c_E, c_D = model.condition(frame0, [p.task.text] * 4), model.condition(frame0, [p.d_vlm] * 4)
    with torch.no_grad():
        traj = flow.sample_ode(lambda x, t: model(x, t, c_E), models.seeded_noise(model, 12, 1)[:4], 2,
                               return_trajectory=True)
        r = distill.distill_reward(model, traj, c_E, c_D)
        videos = model.decode(traj[0][-1], frame0)
    assert np.allclose(res["r_distill"][:4], r.numpy(), rtol=1e-4, atol=0), (res["r_distill"][:4], r)
    moved = (np.abs(videos[:, 1:].astype(int) - videos[:, :1]).max(-1) > 32).sum((1, 2, 3))
    assert res["motion"][:4] == moved.tolist()
    assert res["task"][:4] == [reward.judge_task(v, p.task.text).yes for v in videos]
    assert np.allclose(res["r_task"][:4], [reward.judge_task(v, p.task.text).score for v in videos], equal_nan=True)
    assert np.allclose(res["r_cons"][:4], [reward.judge_consistency(v).score for v in videos], equal_nan=True)
    import rl
    import train
    defaults = train.Args()            # the advantages are those of train.py's default rewards and aggregation
    assert bench.RANK_WEIGHTS == {"task": defaults.lambda_task, "consistency": defaults.lambda_cons,
                                  "distill": defaults.lambda_distill}
    assert (defaults.adv_agg, defaults.adv_clip) == ("gdpo", 5.0)
    rewards = {"task": torch.tensor(res["r_task"]), "consistency": torch.tensor(res["r_cons"]),
               "distill": torch.tensor(res["r_distill"])}
    ids = torch.arange(3).repeat_interleave(4)
    A = rl.advantages(rewards, bench.RANK_WEIGHTS, ids, "gdpo", 5.0).numpy()
    assert np.allclose(res["A_wmsd"], A, atol=1e-6) and not np.allclose(A, 0)
    rewards.pop("distill")
    assert np.allclose(res["A_judges"], rl.advantages(rewards, bench.RANK_WEIGHTS, ids, "gdpo", 5.0), atol=1e-6)
    assert res["still_push_of_A_wmsd"] == bench.pull(torch.tensor(A), -np.array(res["motion"]), ids)
    # by hand: y standardised within groups is (1, -1) and (0, 0), a group where y is constant
    assert bench.pull(torch.tensor([1., -1, 1, -1]), [2, 0, 5, 5], torch.tensor([0, 0, 1, 1])) == pytest.approx(0.5)
    rho = [bench._spearman(res["r_distill"][g:g + 4], -np.array(res["motion"][g:g + 4])) for g in (0, 4, 8)]
    rho = [x for x in rho if not np.isnan(x)]       # a group whose rollouts all move alike has no rank order
    assert np.allclose([res["rho_still"], res["still_positive"]],
                       [np.mean(rho), np.mean(np.array(rho) > 0)] if rho else [np.nan] * 2, equal_nan=True)
    tasks = [res["task"][g:g + 4] for g in (0, 4, 8)]     # rho_task ranks within groups with both outcomes
    assert res["mixed_groups"] == sum(None not in y and 0 < sum(y) < 4 for y in tasks)
    r = run("bench.py", "--checkpoint", tiny_ckpt, "--rank_rdistill", "--n", "2", "--group", "3", "--steps", "2",
            "--json")
    assert r.returncode == 0, r.stderr
    assert "Spearman(r_distill, -motion)" in r.stdout and "the judges + r_distill: " in r.stdout
    assert json.loads(r.stdout.splitlines()[-1])["group"] == 3
    r = run("bench.py", "--rank_rdistill", "--group", "1")
    assert r.returncode == 2 and "--group must be >= 2" in r.stderr
    r = run("bench.py", "--guidance", "-1")
    assert r.returncode == 2 and "--guidance must be a finite number >= 0" in r.stderr


def test_pretraining_that_teaches_relate_to_point_and_the_probe_that_reads_it(tmp_path):
    ckpt = str(tmp_path / "relate.pt")
    r = run("train.py", "--stage", "pretrain", "--relate", "--p_goal", "0.5", "--point_weight", "0.1",
            "--pretrain_steps", "2", "--pretrain_batch", "4", "--width", "8", "--log_every", "1", "--out", ckpt,
            "--run_dir", str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert "| pointing " in r.stdout
    assert all("pointing_loss" in json.loads(line) for line in open(tmp_path / "pretrain.jsonl"))
    r = run("bench.py", "--checkpoint", ckpt, "--pointing", "--condition", "goal", "--n", "20", "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout.splitlines()[-1])
    assert 0 <= res["agent"] <= res["agent_any"] <= 1 and res["n_agent"] > 0 and res["n_target"] > 0


class _Reached(Exception):
    """Raised by a stub where bench.main's work starts: the flags were accepted."""


def test_error_rate_is_read_with_the_prompts_made_from_the_toy_vlms_d_only(capsys):
    """bench.VLM_CONDITIONS against the code: the bench's prompts under every other condition are the same at any
    --error_rate (the scenes and tasks do not depend on it), under those two they differ; so bench.py refuses
    --error_rate where no prompt reads it, as it refuses any flag that would be ignored."""
    import bench
    clean, noisy = bench.world.bench_pairs(0.0), bench.world.bench_pairs(0.5)
    for c in bench.CONDITIONS:
        same = bench.prompts_for(clean, c) == bench.prompts_for(noisy, c)
        assert same == (c not in bench.VLM_CONDITIONS), c
    for argv, words in ((["--error_rate", "0.5"], "--condition task would ignore it"),
                        (["--condition", "oracle_instruction", "--error_rate", "0"], "read with --condition (or "
                         "--handoff) vlm or instruction, or --gallery (its Demonstrator row), only"),
                        (["--handoff", "task,oracle", "--error_rate", "0.1"], "--handoff task,oracle would ignore it"),
                        (["--dataset", "d.jsonl", "--condition", "vlm", "--error_rate", "0.1"],
                         "a --dataset bench's D is its file's")):
        assert words in exit_2(bench.main, argv, capsys), argv


def test_guidance_changes_nothing_given_the_empty_caption_and_is_refused_there(capsys):
    """Classifier-free guidance against the empty caption (flow.guided_field) leaves the empty caption's own videos as
    they are, at any w: the shipped base's samples are the same bit for bit; so bench.py refuses --guidance with
    --condition empty, and takes it with a caption."""
    import bench
    model = bench.models.load_checkpoint(bench.models.SHIPPED_BASE)[0].eval()
    pairs = bench.world.bench_pairs(0.3)[:2]
    frame0 = np.stack([p.frame0 for p in pairs])
    videos = [bench.models.generate(model, frame0, prompts, steps=2, seed=0, guidance=w)
              for prompts in (["", ""], bench.prompts_for(pairs, "task")) for w in (1, 3)]
    assert np.array_equal(videos[0], videos[1]) and not np.array_equal(videos[2], videos[3])
    assert "with --condition empty they are one field" in exit_2(bench.main, ["--condition", "empty", "--guidance", "3"],
                                                                 capsys)


@pytest.mark.parametrize("mode", [None, *__import__("bench").DIAGNOSTIC_READS])
def test_each_bench_diagnostic_reads_the_flags_it_accepts_and_refuses_the_rest(mode, tmp_path, monkeypatch, capsys):
    """bench.DIAGNOSTIC_READS as main enforces it: every flag, set to a valid non-default value beside the diagnostic
    (None: the plain evaluation), either reaches the diagnostic and changes what it is called with (or which file is
    loaded), or is refused with exit 2. (--png and --json, read after the call, are seen by the diagnostics' runs.)"""
    import bench
    import train
    calls = []

    def stub(name, then=None):
        def f(*a, **k):
            calls.append((name, a, k))
            if then is None:
                raise _Reached
            return then
        return f

    model = types.SimpleNamespace(eval=lambda: model)
    monkeypatch.setattr(bench.models, "load_checkpoint", stub("load", (model, {})))
    monkeypatch.setattr(train, "load_base", stub("load_base"))                 # the real path's loader
    monkeypatch.setattr(train, "make_pick", stub("make_pick", "a PickScore"))   # --pick's loader
    monkeypatch.setattr(bench, "relate_probe", stub("relate_probe", contextlib.nullcontext()))
    monkeypatch.setattr(bench, "trained_pairs", stub("trained_pairs", (["a trained pair"], 0.0, {})))   # its loader
    for name in ("evaluate", "handoff", "pointing", "rank_rdistill", "gallery", "compare_runs"):
        monkeypatch.setattr(bench, name, stub(name))
    value = {"checkpoint": ["x.pt"], "model": ["ltx2-tiny"], "model_path": ["/p"], "lora": ["l.pt"],
             "judge": ["qwen-vl-tiny"], "judge_path": ["/j"], "pick": ["pickscore-tiny"], "pick_path": ["/k"],
             "pick_processor_path": ["/k2"], "dataset": ["d.jsonl"], "offload_text": [],
             "offload_judge": [], "batch": ["5"], "condition": ["vlm"], "n": ["3"], "seed": ["2"],
             "error_rate": ["0.1"], "steps": ["3"], "guidance": ["2"], "png": [tmp_path / "p.png"],
             "gallery": [tmp_path / "g.png"],
             "executor": ["e.pt"], "json": [], "compare": ["A=r"], "handoff": ["task,vlm"], "rank_rdistill": [],
             "group": ["4"], "pointing": [], "relate_probe": ["forced"], "crowded": [],
             "trained_pairs": ["t.pt"]}
    own = [f"--{mode}", *value[mode]] if mode else []

    def called(argv):
        calls.clear()
        with pytest.raises(_Reached):
            bench.main([str(a) for a in argv])
        return list(calls)
    plain = called(own)
    reads = bench.DIAGNOSTIC_READS.get(mode, [k for k in value if k not in (*bench.DIAGNOSTIC_READS, "group",
                                                                           "executor")])
    for k in value:
        if k == mode or (mode is None and k in bench.DIAGNOSTIC_READS):      # (those others are modes of their own)
            continue
        base = own
        if k == "error_rate" and mode in (None, "pointing", "rank_rdistill"):
            base = [*own, "--condition", "vlm"]         # the toy VLM's errors reach only the prompts made from its D
        if k in ("model_path", "judge_path", "pick_path", "pick_processor_path") and mode is None:   # read only with
            base = {"model_path": ["--model", "ltx2", "--model_path", "/q"],                 # real weights: set,
                    "judge_path": ["--judge", "qwen-vl", "--judge_path", "/i"],             # then changed
                    "pick_path": ["--pick", "pickscore", "--pick_path", "/m"],
                    "pick_processor_path": ["--pick", "pickscore", "--pick_path", "/m"]}[k]
        argv = [*base, f"--{k}", *value[k]]
        if k in ("lora", "offload_text") and mode is None:
            argv = ["--model", "ltx2-tiny", *argv]       # a real model's flags, with a real model
        if k == "offload_judge" and mode is None:
            argv = ["--judge", "qwen-vl-tiny", *argv]    # a VLM judge's, with a VLM judge
        if k not in reads:
            exit_2(bench.main, argv, capsys)
        elif k not in ("png", "json"):
            assert called(argv) != (plain if base is own else called(base)), k
