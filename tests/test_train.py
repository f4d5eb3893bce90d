"""train.py's rl stage as a long-running job: resume after kill -9, torchrun with 2 processes, faults (a judge that
raises, a NaN), atomic state writes, and bad input."""
import ast
import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time
import types

import numpy as np
import pytest
import torch

import bench
import train
from conftest import ROOT, exit_2, run

TINY_ANY = ["--toy", "--eval_every", "2", "--eval_n", "4", "--train_pairs", "8", "--sample_steps", "3",
            "--threads", "1"]                                                  # flags the distill and rl stages read
TINY = [*TINY_ANY, "--group_size", "2", "--tasks_per_step", "2", "--save_every", "1"]   # and the rl stage's own flags
REAL_ROLLOUT = train.distill.rollout     # the one tests spy on, unwrapped


def _metrics(path):
    """Every logged record without its wall-clock fields."""
    out = []
    for line in open(path):
        r = json.loads(line)
        out.append({k: v for k, v in r.items()
                    if not k.endswith("_s") and k not in ("step_seconds", "rollouts_per_s", "seconds")})
    return out


def test_kill_9_then_resume_gives_the_uninterrupted_metrics(tiny_ckpt, tmp_path):
    args = [*TINY, "--init", tiny_ckpt, "--steps", "4"]
    ref = run("train.py", *args, "--run_dir", str(tmp_path / "ref"))
    assert ref.returncode == 0, ref.stderr
    d = tmp_path / "killed"
    p = subprocess.Popen([sys.executable, "train.py", *args, "--run_dir", str(d)], cwd=ROOT,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and p.poll() is None:   # kill it once a state past step 1 is on disk
        if (d / "state.pt").exists() and torch.load(d / "state.pt", weights_only=True)["step"] >= 2:
            break
        time.sleep(0.05)
    if p.poll() is not None:
        pytest.fail("the run ended before it could be killed")
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    res = run("train.py", *args, "--run_dir", str(d), "--resume")
    assert res.returncode == 0, res.stderr
    assert "resumed" in res.stdout
    assert _metrics(d / "rl.jsonl") == _metrics(tmp_path / "ref" / "rl.jsonl")
    a = torch.load(d / "state.pt", weights_only=True)["lora"]
    b = torch.load(tmp_path / "ref" / "state.pt", weights_only=True)["lora"]
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_resumed_alg2_run_brings_back_phi_with_the_executor(tiny_ckpt, tmp_path):
    """--resume under --alternate 2: phi's LoRA and optimizer come back beside the Executor's, so 2 steps and then
    --resume to 4 end where 4 steps do (steps 2 and 4 are phi's rounds; step 3's Executor learns from phi)."""
    def state(name, steps, resume=False):
        args = _args(tiny_ckpt, tmp_path / name, steps=steps, alternate=2)
        args.resume = resume
        train.rl_stage(args)
        return torch.load(tmp_path / name / "state.pt", weights_only=True)

    whole = state("whole", 4)
    state("halves", 2)
    halves = state("halves", 4, resume=True)
    for key in ("lora", "demo_lora"):
        assert whole[key].keys() == halves[key].keys() and whole[key]
        assert all(torch.equal(whole[key][k], halves[key][k]) for k in whole[key]), key


def test_two_processes_make_the_one_process_update(tiny_ckpt, tmp_path):
    # lambda_distill 0: the 3-step tiny base ignores its text, so r_distill is ~1e-8 and its within-group spread is
    # float rounding, which group normalisation would blow up; the judges' scores are exact. The anchor (the same
    # Demonstrator velocities) is still on, and so are the sharded draws and the gradient averaging.
    args = [*TINY, "--init", tiny_ckpt, "--steps", "2", "--eval_every", "10", "--lambda_distill", "0"]
    one = run("train.py", *args, "--run_dir", str(tmp_path / "one"))
    assert one.returncode == 0, one.stderr
    two = run("-m", "torch.distributed.run", "--nproc_per_node", "2", "train.py", *args, "--run_dir",
              str(tmp_path / "two"))
    assert two.returncode == 0, two.stderr
    m1, m2 = _metrics(tmp_path / "one" / "rl.jsonl"), _metrics(tmp_path / "two" / "rl.jsonl")
    steps1, steps2 = [m for m in m1 if "A" in m], [m for m in m2 if "A" in m]
    assert len(steps1) == len(steps2) == 2
    for s1, s2 in zip(steps1, steps2):
        assert torch.allclose(torch.tensor(s1["A"]), torch.tensor(s2["A"]), atol=1e-5)   # same advantages
        assert abs(s1["r_task"] - s2["r_task"]) < 1e-6
    a = torch.load(tmp_path / "one" / "state.pt", weights_only=True)["lora"]
    b = torch.load(tmp_path / "two" / "state.pt", weights_only=True)["lora"]
    assert max((a[k] - b[k]).abs().max().item() for k in a) < 1e-5                      # same LoRA update
    assert any(a[k].abs().max() > 0 for k in a if "lora_B" in k)                         # ... and it did move


def test_a_batch_shards_into_equal_contiguous_shares_or_is_refused(monkeypatch):
    """train._shard: process r of w takes rows [r n/w, (r+1) n/w); a batch that does not divide is a clear error,
    not a shard that drops rollouts."""
    monkeypatch.setattr(train, "_world", lambda: 3)
    monkeypatch.setattr(train, "_rank", lambda: 2)
    assert train._shard(12) == (8, 4)
    with pytest.raises(ValueError, match=r"rollouts per step \(8\) must be divisible by the number of processes \(3\)"):
        train._shard(8)


def _args(tiny_ckpt, tmp_path, **kw):
    """The tiny run's Args (its rl stage's flags, unless kw names another stage), with kw's flags."""
    tiny = TINY if kw.get("stage", "rl") == "rl" else TINY_ANY
    return train.parse_args([*tiny, "--init", tiny_ckpt, "--run_dir", str(tmp_path),
                             *sum(([f"--{k}", str(v)] for k, v in kw.items()), [])])


def _one_step(tiny_ckpt, tmp_path, **kw):
    """One rl_step (or, with alternate, one Demonstrator round) from a fresh LoRA on the tiny base, 2 tasks x a group
    of 4; returns (its record, the LoRA gradients of its update, the generator's state after it, the batch sizes
    the network saw)."""
    args = _args(tiny_ckpt, tmp_path, group_size=4, **kw)
    model = train.models.load_checkpoint(tiny_ckpt)[0]
    torch.manual_seed(0)
    train.models.add_lora(model, args.lora_rank, args.lora_alpha)
    for name, p in model.named_parameters():    # B != 0: a Demonstrator round's anchor to the base has a gradient
        if "lora_B" in name:
            p.data.normal_(0, 0.01)
    params = train.models.lora_parameters(model)
    opt = torch.optim.Adam(params, lr=args.lr)
    sizes, forward = [], model.forward
    model.forward = lambda x, t, c: sizes.append(x.shape[0]) or forward(x, t, c)
    frame0, tasks, descs = train._batch(train.world.bench_pairs(0.3), [0, 1])
    gen = torch.Generator().manual_seed(0)
    step = train.demonstrator_round if args.alternate else train.rl_step
    rec = step(1, model, opt, params, args, train.rl_config(args), frame0, tasks, descs, gen)
    return rec, [p.grad.clone() for p in params], gen.get_state(), sizes


@pytest.mark.parametrize("flags", [{}, {"trainer": "flow-grpo", "inner_epochs": 2}, {"trainer": "nft"},
                                   {"executor_update": "off"}, {"alternate": 1}],
                         ids=["awm", "flow-grpo", "nft", "off-policy", "demonstrator-round"])
def test_micro_batches_make_the_one_pass_update(tiny_ckpt, tmp_path, flags):
    # lambda_distill 0 for the same reason as in the two-process test (the off-policy rounds read no r_distill);
    # r_distill itself is compared below
    flags = flags if flags.get("executor_update") == "off" else {"lambda_distill": 0, **flags}
    one, grad1, gen1, s1 = _one_step(tiny_ckpt, tmp_path, **flags)
    mb, grad3, gen3, s3 = _one_step(tiny_ckpt, tmp_path, micro_batch=3, **flags)
    assert max(s3) <= 3 * 2 < max(s1)                       # passes of at most 3 rollouts (x 2 re-noising times)
    for k in ("A", "r_task", "r_cons", "solved"):
        if k in one:
            assert torch.allclose(torch.tensor(one[k]), torch.tensor(mb[k]), atol=1e-5), k
    assert abs(one["loss"] - mb["loss"]) < 1e-6
    assert all(torch.allclose(a, b, rtol=1e-4, atol=1e-8) for a, b in zip(grad1, grad3))  # the same gradient
    assert one["grad_norm"] > 0
    assert torch.equal(gen1, gen3)                            # the same draws: the next step starts alike


def test_micro_batches_give_the_one_pass_r_distill(tiny_ckpt, tmp_path):
    one, mb = (_one_step(tiny_ckpt, tmp_path, micro_batch=m)[0]["r_distill"] for m in (0, 3))
    assert one < 0 and abs(one - mb) <= 1e-4 * abs(one)


def test_a_failing_judge_is_counted_and_skipped(tiny_ckpt, tmp_path, monkeypatch):
    real, calls = train.reward.judge_task, {"n": 0}

    def flaky(video, task):
        calls["n"] += 1
        if calls["n"] % 3 == 0:
            raise RuntimeError("judge server hung up")
        return real(video, task)

    monkeypatch.setattr(train.reward, "judge_task", flaky)
    train.rl_stage(_args(tiny_ckpt, tmp_path, steps=2))
    recs = [json.loads(line) for line in open(tmp_path / "rl.jsonl") if '"A"' in line]
    assert sum(r["judge_errors"] for r in recs) > 0
    assert all(r["invalid"] >= r["judge_errors"] for r in recs)


def test_rl_step_counts_the_still_rollouts_and_how_far_a_points_to_them(tiny_ckpt, tmp_path, monkeypatch):
    """The collapse monitor in each rl step's record: how many rollouts show nothing moving (bench.still_videos), their
    mean motion, and the advantages' pull towards less motion (bench.pull of A on -motion, within the groups)."""
    real, seen = train._sample_parts, []

    def half_still(*a):
        v = real(*a)
        v[::2] = v[::2, :1]              # every other rollout: its first frame held; the others slide right
        v[1::2] = np.stack([np.roll(v[1::2, 0], 2 * f, axis=2) for f in range(v.shape[1])], 1)
        seen.append(v)
        return v

    plotted, plot = [], train.plot_rl_curve
    monkeypatch.setattr(train, "_sample_parts", half_still)
    monkeypatch.setattr(train, "plot_rl_curve", lambda *a: plotted.append(a[-1]) or plot(*a))
    train.rl_stage(_args(tiny_ckpt, tmp_path, steps=1, eval_every=0))
    rec = next(json.loads(line) for line in open(tmp_path / "rl.jsonl") if '"A"' in line)
    v = seen[0]
    assert rec["still"] == bench.still_videos(v) == len(v) // 2
    groups = torch.arange(len(v)) // 2
    motion = bench.moved_pixels(v, bench.MOTION_LEVEL)
    assert rec["motion"] == pytest.approx(motion.mean())
    assert plotted == [[rec]]            # rl_curve.png's collapse panel reads the step records
    assert rec["still_push"] == pytest.approx(bench.pull(torch.tensor(rec["A"]), -motion, groups))
    assert rec["still_push"] != pytest.approx(bench.pull(torch.tensor(rec["A"]), motion, groups))


def test_a_nan_stops_the_run_naming_step_and_quantity(tiny_ckpt, tmp_path, monkeypatch, capsys):
    """The fault names its step and quantity, the state stays at the last good step, and train.py ends in one line
    with exit status 1 (not 2: the settings were fine)."""
    real, calls = train.distill.distill_reward, {"n": 0}

    def poisoned(*a, **k):
        calls["n"] += 1
        r = real(*a, **k)
        return r * float("nan") if calls["n"] == 2 else r

    monkeypatch.setattr(train.distill, "distill_reward", poisoned)
    err = exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--run_dir", tmp_path, "--steps", "3"], capsys, code=1)
    err = err.strip().splitlines()
    assert len(err) == 1, err
    assert re.match(r"error: step 2: reward r_distill is not finite.*state.pt is intact", err[0]), err
    assert torch.load(tmp_path / "state.pt", weights_only=True)["step"] == 1          # the last good state


def test_state_write_is_atomic(tiny_ckpt, tmp_path, monkeypatch):
    train.rl_stage(_args(tiny_ckpt, tmp_path, steps=1))
    path = tmp_path / "state.pt"
    before = path.read_bytes()

    def dies(obj, f):
        open(f, "wb").write(b"half a checkpoint")
        raise KeyboardInterrupt

    monkeypatch.setattr(train.torch, "save", dies)
    import numpy as np
    with pytest.raises(KeyboardInterrupt):
        train.save_state(str(path), 2, torch.nn.Linear(1, 1), torch.optim.SGD([torch.zeros(1)], lr=1), None, None,
                         np.random.default_rng(0), torch.Generator(), [], {}, train.Args())
    assert path.read_bytes() == before and os.listdir(tmp_path).count("state.pt") == 1
    assert not [f for f in os.listdir(tmp_path) if ".tmp" in f]


def test_task_reward_attributed_trains_on_fig10s_judge(tiny_ckpt, tmp_path, monkeypatch):
    """--task_reward attributed: every rollout's r_task is reward.judge_task_reward's (Fig. 10), not judge_task's."""
    real, seen = train.reward.judge_task_reward, []
    monkeypatch.setattr(train.reward, "judge_task_reward", lambda v, t: seen.append(t) or real(v, t))
    args = _args(tiny_ckpt, tmp_path, steps=1, task_reward="attributed")
    train.rl_stage(args)
    assert len(seen) == args.tasks_per_step * args.group_size


def test_train_steps_sets_the_training_rollouts_apart_from_evaluation(tiny_ckpt, tmp_path, monkeypatch):
    """--train_steps (Sec. 4.6: fewer steps in training than in evaluation) reaches every training rollout -- the ODE
    and SDE samplers of an rl step, the Demonstrator's of the off-policy setting, the distill stage's -- and leaves
    evaluation at --sample_steps (TINY: 3); 0 means --sample_steps for both."""
    flow, seen = train.flow, []
    for name in ("sample_ode", "sample_sde"):
        f = getattr(flow, name)
        monkeypatch.setattr(flow, name, lambda v, x, steps, *a, _f=f, **k: seen.append(steps) or _f(v, x, steps, *a, **k))
    for flags in ({}, {"trainer": "flow-grpo"}, {"executor_update": "off"}):
        seen.clear()
        _one_step(tiny_ckpt, tmp_path, train_steps=2, **flags)
        assert seen and set(seen) == {2}, flags
    seen.clear()
    _one_step(tiny_ckpt, tmp_path, trainer="flow-grpo")
    assert seen and set(seen) == {3}
    seen.clear()
    threads = torch.get_num_threads()
    try:
        train.main([*TINY_ANY, "--init", tiny_ckpt, "--stage", "distill", "--variant", "on", "--steps", "1",
                    "--batch", "3", "--eval_n", "2", "--train_steps", "2", "--run_dir", str(tmp_path / "d")])
    finally:
        torch.set_num_threads(threads)
    assert seen.count(2) == 1 and 3 in seen        # one training rollout of 2 steps; the evaluations at 3


def test_ctrl_c_ends_with_one_line_on_what_is_kept(tmp_path, capsys, monkeypatch):
    """A KeyboardInterrupt in a stage: exit status 130, no traceback, and the line says whether the run dir holds a
    state that --resume continues (the rl stage's or a one-variant distill run's state.pt) or none."""
    def interrupted(args):
        raise KeyboardInterrupt

    def saving(args):                    # this run saves a state, then is interrupted
        (tmp_path / "state.pt").write_bytes(b"")
        raise KeyboardInterrupt

    def ctrl_c(*argv):
        try:
            return exit_2(train.main, [*argv, "--run_dir", tmp_path], capsys, code=130)
        except KeyboardInterrupt:        # escaped train.main: pytest would take it for the user's and stop
            pytest.fail("the interrupt escaped train.main as a traceback")

    monkeypatch.setitem(train.STAGES, "distill", interrupted)
    monkeypatch.setitem(train.STAGES, "rl", interrupted)
    assert "no resumable state was saved" in ctrl_c()
    monkeypatch.setitem(train.STAGES, "rl", saving)
    err = ctrl_c()
    assert "interrupted; %s holds the last state saved" % (tmp_path / "state.pt") in err and "--resume" in err
    monkeypatch.setitem(train.STAGES, "rl", interrupted)
    os.utime(tmp_path / "state.pt", (0, 0))          # an older run's state, not this one's ...
    assert "no resumable state was saved" in ctrl_c()
    assert "holds the last state saved" in ctrl_c("--resume")      # ... unless this run resumed from it
    assert "no resumable state" in ctrl_c("--stage", "distill")

    def keeping(args):                   # --keep_executors saved two Executors, then the run is interrupted
        train.KEPT.extend(["a_step2.pt", "a_step4.pt"])
        raise KeyboardInterrupt

    monkeypatch.setitem(train.STAGES, "distill", keeping)
    assert "no resumable state was saved; a_step4.pt is the Executor of the last evaluation" in ctrl_c(
        "--stage", "distill")
    monkeypatch.setitem(train.STAGES, "distill", interrupted)
    assert "Executor of the last evaluation" not in ctrl_c("--stage", "distill")     # an earlier call's are not named
    monkeypatch.setitem(train.STAGES, "distill", saving)                            # a distill run's state
    assert "holds the last state saved" in ctrl_c("--stage", "distill")


def test_keep_executors_saves_each_evaluations_executor_and_trains_the_same_weights(tiny_ckpt, tmp_path):
    """--keep_executors: the Executor of each evaluation before the last, beside the final one as _step<N>, is the
    Executor a run stopped at that step saves (weights and settings but --steps), bench.py --trained_pairs reads its
    pairs, and the run trains what it trains without the flag. In the distill stage and in the rl stage (the EMA's
    weights there, what the evaluation scores)."""
    def weights(path):
        return train.models.load_checkpoint(str(path))

    def same(a, b):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

    for stage, flags, name in (("distill", ["--variant", "on", "--batch", "3"], "on"),
                               ("rl", ["--group_size", "2", "--tasks_per_step", "2", "--executor_ema", "0.5"], "awm")):
        def train_run(d, steps, *more):
            train.main([*TINY_ANY, "--init", tiny_ckpt, "--stage", stage, *flags, "--steps", str(steps),
                        "--eval_every", "1" if stage == "rl" else "2", *more, "--run_dir", str(tmp_path / d)])
        at = 1 if stage == "rl" else 2
        threads = torch.get_num_threads()
        try:
            train_run(f"{stage}_kept", 2 * at, "--keep_executors")
            named = list(train.KEPT)         # what main's Ctrl-C line would name from
            train_run(f"{stage}_short", at)
            train_run(f"{stage}_plain", 2 * at)
        finally:
            torch.set_num_threads(threads)
        kept = tmp_path / f"{stage}_kept"
        assert sorted(p.name for p in kept.glob("executor_*.pt")) == [f"executor_{name}.pt",
                                                                      f"executor_{name}_step{at}.pt"], stage
        model, meta = weights(kept / f"executor_{name}_step{at}.pt")
        short, short_meta = weights(tmp_path / f"{stage}_short" / f"executor_{name}.pt")
        same(model.state_dict(), short.state_dict())
        assert meta["step"] == at and meta["stage"] == stage and meta["args"]["keep_executors"]
        assert {k: v for k, v in meta["args"].items() if k not in ("steps", "run_dir", "keep_executors")} == {
            k: v for k, v in short_meta["args"].items() if k not in ("steps", "run_dir", "keep_executors")}
        same(weights(kept / f"executor_{name}.pt")[0].state_dict(),
             weights(tmp_path / f"{stage}_plain" / f"executor_{name}.pt")[0].state_dict())
        a = bench.trained_pairs(str(kept / f"executor_{name}_step{at}.pt"), 8)[0]
        b = bench.trained_pairs(str(kept / f"executor_{name}.pt"), 8)[0]
        assert [p.task for p in a] == [p.task for p in b] and all(np.array_equal(p.frame0, q.frame0)
                                                                  for p, q in zip(a, b))
        assert named == [str(kept / f"executor_{name}_step{at}.pt")]


def test_bad_input_one_line_exit_2_nothing_written(tiny_ckpt, tmp_path, capsys):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"garbage")
    out = tmp_path / "never"
    r = run("train.py", "--init", str(bad), "--run_dir", str(out))
    assert r.returncode == 2 and "corrupt" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()
    assert "no state to resume" in exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--run_dir", out, "--resume"], capsys)
    assert "--train_steps must be >= 1" in exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--run_dir", out,
                                                                 "--train_steps", "-1"], capsys)
    assert not out.exists()
    # a state from other settings is refused, not silently continued
    d = tmp_path / "run"
    assert run("train.py", *TINY, "--init", tiny_ckpt, "--steps", "1", "--run_dir", str(d)).returncode == 0
    with pytest.raises(ValueError, match="is a run's state for train.py --resume, not a model"):
        train.models.load_checkpoint(str(d / "state.pt"))    # bench.py --checkpoint runs/state.pt: a likely slip
    err = exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--steps", "2", "--run_dir", d, "--resume", "--beta_d", "0.5"],
                 capsys)
    assert "--beta_d 1.0 (now 0.5)" in err
    # a state from before a setting existed resumes with that setting at its default, and only then
    state = torch.load(d / "state.pt", weights_only=True)
    del state["args"]["state_window"]
    torch.save(state, d / "state.pt")
    err = exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--steps", "2", "--run_dir", d, "--resume",
                              "--state_window", "0.5,1"], capsys)
    assert "--state_window '' (now '0.5,1')" in err, err
    assert run("train.py", *TINY, "--init", tiny_ckpt, "--steps", "2", "--run_dir", str(d), "--resume",
               "--keep_executors").returncode == 0          # a setting that changes no number may change
    err = exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--steps", "2", "--run_dir", d, "--resume"], capsys)
    assert "already reached step 2 of --steps 2" in err       # a finished run: nothing to resume
    # started afresh over a run's state: a finished run's is overwritten; an unfinished one's is refused and kept
    assert train.refuse_to_overwrite(str(d / "state.pt")) is None
    state = torch.load(d / "state.pt", weights_only=True)
    state["args"]["steps"] = 3                                # as if stopped at step 2 of 3
    torch.save(state, d / "state.pt")
    err = exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--steps", "4", "--run_dir", d], capsys)
    assert "holds an unfinished run (its state.pt: step 2 of 3); continue it with --resume" in err, err
    assert torch.load(d / "state.pt", weights_only=True)["args"]["steps"] == 3
    (d / "state.pt").write_bytes(b"garbage")
    r = run("train.py", *TINY, "--init", tiny_ckpt, "--steps", "2", "--run_dir", str(d), "--resume")
    assert r.returncode == 2 and "corrupt" in r.stderr and "Traceback" not in r.stderr
    (d / "state.pt").write_bytes(b"")                   # an empty file: an EOFError with no message
    err = exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--steps", "2", "--run_dir", d, "--resume"], capsys)
    assert "corrupt: EOFError: the file is empty or cut short" in err, err
    # a dataset whose prompt has an unknown agent, or an unknown word, for the toy model
    from PIL import Image
    import world
    p = world.make_pairs(1, seed=0, error_rate=0.0)[0]
    Image.fromarray(p.frame0).save(tmp_path / "f.png")
    for task, desc, msg in (("[purple dragon]: move to the blue circle", p.d_oracle, "unknown agent 'purple dragon'"),
                            (p.task.text, "red square teleports away", "unknown word")):
        (tmp_path / "d.jsonl").write_text(json.dumps({"image": "f.png", "task": p.task.text, "description": p.d_oracle})
                                          + "\n" + json.dumps({"image": "f.png", "task": task, "description": desc}) + "\n")
        err = exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--dataset", tmp_path / "d.jsonl", "--run_dir", out], capsys)
        assert "d.jsonl line 2" in err and msg in err and not out.exists(), err
    # parse_args holds every flag check; called alone, a check that let its bad value through returns (the test fails
    # at once) where train.main would start a run
    no_gpu = not torch.cuda.is_available()
    for argv, msg in ((["--steps", "0"], "--steps must be >= 1"), (["--group_size", "1"], "--group_size must be >= 2"),
                      (["--beta_d", "-1"], "--beta_d must be >= 0"), (["--sampler", "euler"], "--sampler: unknown"),
                      (["--adv_agg", "mean"], "--adv_agg: unknown"),
                      (["--executor_prompt", "story"], "--executor_prompt: unknown"),
                      (["--stage", "pretrain", "--executor_prompt", "instruction"], "toy control"),
                      (["--stage", "distill", "--variant", "on,sft", "--executor_prompt", "instruction"],
                       "toy control"),
                      (["--train_crowded", "--dataset", "tasks.jsonl"], "--train_crowded draws the toy VLM's pairs"),
                      (["--train_crowded", "--model", "ltx2-tiny"], "crowded toy scenes: toy model, no --dataset"),
                      (["--eval_crowded", "--eval_dataset", "bench.jsonl"], "--eval_crowded is a toy bench"),
                      (["--stage", "pretrain", "--eval_crowded"], "--eval_crowded is read with --stage distill and rl only"),
                      (["--state_window", "0.7,0.3"], "--state_window: expected 0 <= LO < HI <= 1"),
                      (["--state_window", "mid"], "--state_window: expected two numbers"),
                      (["--state_window", "0.31,0.39"], "no grid time k/10 lies in [LO, HI)"),
                      (["--beta_d", "0", "--state_window", "0.3,0.7"], "--state_window picks the states"),
                      (["--distill_motion_weight", "0"], "--distill_motion_weight must be > 0"),
                      (["--off_judged"], "--off_judged filters Eq. 3's Demonstrator rollouts: it needs --stage"),
                      (["--stage", "distill", "--variant", "on,dmd", "--off_judged"], "it needs --stage distill with"),
                      (["--stage", "distill", "--off_pool", "-1"], "--off_pool must be >= 0"),
                      (["--off_pool", "4"], "--off_pool pools Eq. 3's Demonstrator rollouts: it needs --stage distill"),
                      (["--task_reward", "fig10"], "--task_reward: unknown"),
                      (["--judge", "qwen-vl-tiny", "--task_reward", "attributed"], "a VLM judge always asks"),
                      (["--model", "ltx2-tiny", "--lora_convs"], "--lora_convs and --lora_embeddings are for the toy"),
                      (["--model", "ltx2-tiny", "--lora_embeddings"], "are for the toy; a real backend"),
                      (["--executor_weights", "half"], "--executor_weights: unknown 'half'; choose from lora, all"),
                      (["--model", "ltx2-tiny", "--executor_weights", "all"], "trains every weight of the toy"),
                      (["--executor_weights", "all", "--alternate", "2"], "neither --alternate"),
                      (["--stage", "distill", "--variant", "on,dmd", "--executor_weights", "all"], "nor --variant dmd"),
                      (["--executor_weights", "all", "--lora_rank", "4"],
                       "--lora_rank is read with --executor_weights lora only: --executor_weights all would ignore"),
                      (["--executor_init", "e.pt"], "--executor_init starts every weight of the Executor from a "
                                                    "saved one: it needs --executor_weights all"),
                      (["--model", "ltx2-tiny", "--toy_gpu"], "--toy_gpu puts the toy model of the rl stage"),
                      (["--stage", "distill", "--toy_gpu"], "--toy_gpu puts the toy model of the rl stage"),
                      *([(["--toy_gpu"], "torch sees no GPU")] if no_gpu else []),
                      (["--micro_batch", "-1"], "--micro_batch must be >= 0"),
                      (["--stage", "distill", "--micro_batch", "4"], "--micro_batch splits the rl stage's"),
                      (["--grad_checkpoint"], "--grad_checkpoint is for a real model's transformer"),
                      (["--offload_text"], "--offload_text is for a real model's text encoder"),
                      (["--executor_ema", "1"], "--executor_ema must lie in [0, 1)"),
                      (["--executor_ema_every", "0"], "--executor_ema_every must be >= 1"),
                      (["--stage", "pretrain", "--executor_ema", "0.9"], "--executor_ema is read with --stage distill"),
                      (["--executor_ema_schedule", "power"], "--executor_ema_schedule sets the decay"),
                      (["--executor_ema", "0.9", "--executor_ema_schedule", "cosine"],
                       "--executor_ema_schedule: unknown"),
                      (["--stage", "distill", "--variant", "paired", "--distill_motion_weight", "10"],
                       "--distill_motion_weight weighs Eq. 4"),
                      (["--model", "ltx2-tiny", "--distill_motion_weight", "2"], "first frame: toy model only"),
                      (["--lambda_task", "0", "--lambda_distill", "0", "--lambda_cons", "0", "--beta_d", "0"],
                       "at least one of --lambda_task, --lambda_distill, --lambda_cons must be > 0, or --beta_d"),
                      (["--alternate", "2", "--executor_update", "off", "--lambda_task", "0", "--lambda_cons", "0"],
                       "at least one of --lambda_task, --lambda_cons must be > 0 (Alg. 2's Demonstrator rounds weigh"),
                      (["--sampler", "sde", "--noise_level", "0"], "--noise_level must be > 0 for SDE rollouts"),
                      (["--trainer", "flow-grpo", "--noise_level", "0"], "--noise_level must be > 0 for SDE"),
                      (["--error_rate", "1.5"], "--error_rate must lie in [0, 1]"),
                      (["--error_rate", "-0.1"], "--error_rate must lie in [0, 1]"),
                      *([(["--model", "ltx2-random"], "it needs a CUDA GPU"),
                         (["--judge", "qwen-vl-random"], "it needs a CUDA GPU")] if no_gpu else []),
                      (["--judge", "qwen-vl"], "--judge qwen-vl needs --judge_path"),
                      (["--eval_height", "32", "--eval_width", "32"], "--eval_height and --eval_width are for a real"),
                      (["--model", "ltx2-tiny", "--eval_height", "32"], "--eval_height and --eval_width go together"),
                      (["--pick", "pickscore", "--lambda_pick", "0.2"], "--pick pickscore needs --pick_path"),
                      (["--lambda_pick", "0.2"], "--lambda_pick weighs PickScore: it needs --pick pickscore"),
                      (["--pick", "clip"], "--pick: unknown 'clip'; choose from none, pickscore, pickscore-tiny"),
                      (["--pick", "pickscore-tiny", "--lambda_pick", "-1"], "--lambda_pick must be >= 0"),
                      (["--stage", "distill", "--judge", "qwen-vl-tiny"], "runs the +SFT baseline alone: --variant"),
                      (["--stage", "distill", "--model", "ltx2-tiny"], "runs the +SFT baseline alone: --variant sft"),
                      (["--stage", "distill", "--model", "ltx2-tiny", "--variant", "on,sft", "--sft_dataset", "f"],
                       "runs the +SFT baseline alone"),
                      (["--stage", "distill", "--model", "ltx2-tiny", "--variant", "sft"], "--sft_dataset FILE;"),
                      (["--stage", "distill", "--variant", "sft", "--sft_dataset", "f"],
                       "--sft_dataset holds a real model's SFT videos; the toy's are the world's"),
                      (["--stage", "distill", "--micro_batch", "2"], "--micro_batch splits the rl stage's rollouts"),
                      (["--distill_reward", "per_step"], "--distill_reward per_step gives each transition"),
                      (["--trainer", "flow-grpo", "--distill_reward", "per_step", "--lambda_distill", "0"],
                       "--distill_reward per_step gives each transition"),
                      (["--demonstrator", "executor", "--alternate", "2"], "--demonstrator executor is the rl stage's"),
                      (["--stage", "distill", "--demonstrator", "executor"], "--demonstrator executor is the rl"),
                      (["--offload_judge"], "--offload_judge is for a VLM judge's weights"),
                      (["--eval_n", "201"], "--eval_n must be at most 200"),
                      (["--p_vague", "0.6", "--p_empty", "0.5"], "must be >= 0 and sum to at most 1"),
                      (["--p_goal", "-0.1"], "must be >= 0 and sum to at most 1"),
                      (["--ema", "1"], "--ema must lie in [0, 1)"),
                      (["--relate", "--point_weight", "-1"], "--point_weight must be >= 0"),
                      (["--lr", "0"], "--lr must be > 0"),
                      (["--stage", "pretrain", "--width", "12"], "--width must be a positive multiple of 8"),
                      (["--stage", "pretrain", "--evidence", "4"], "--evidence must be 0 (off) or an odd window"),
                      (["--stage", "pretrain", "--evidence", "-1"], "--evidence must be 0 (off) or an odd window")):
        err = exit_2(train.parse_args, argv, capsys)
        assert msg in err, (argv, err)


def test_eval_cache_reuses_the_base_evaluation_only_for_the_same_base_and_settings(tiny_ckpt, tmp_path, monkeypatch):
    real, calls = train.evaluate_executor, []
    monkeypatch.setattr(train, "evaluate_executor", lambda m, a, d=False: calls.append(d) or real(m, a, d))
    model = train.models.load_checkpoint(tiny_ckpt)[0]
    a = _args(tiny_ckpt, tmp_path, eval_cache=tmp_path / "cache")
    first = train.base_evaluation(model, a)
    assert train.base_evaluation(model, a) == first and calls == [False]          # read back, not recomputed
    train.base_evaluation(model, a, demonstrator=True)
    train.base_evaluation(model, _args(tiny_ckpt, tmp_path, eval_cache=tmp_path / "cache", eval_n=5))
    assert calls == [False, True, False]                                          # other condition / settings
    other = tmp_path / "other.pt"
    other.write_bytes(open(tiny_ckpt, "rb").read() + b"\0")                       # another base file
    train.base_evaluation(model, _args(str(other), tmp_path, eval_cache=tmp_path / "cache"))
    assert len(calls) == 4 and len(os.listdir(tmp_path / "cache")) == 4
    control = _args(tiny_ckpt, tmp_path, eval_cache=tmp_path / "cache", executor_prompt="instruction", stage="distill")
    train.base_evaluation(model, control)                                         # another Executor prompt
    train.base_evaluation(model, control, demonstrator=True)                      # the same Demonstrator
    assert calls == [False, True, False, False, False] and len(os.listdir(tmp_path / "cache")) == 5
    train.base_evaluation(model, dataclasses.replace(a, eval_crowded=True))     # another bench
    assert calls[5:] == [False] and len(os.listdir(tmp_path / "cache")) == 6
    timing = ("seconds", "seconds_per_video", "judge_seconds")
    assert {k: v for k, v in first.items() if k not in timing} == \
        {k: v for k, v in real(model, a).items() if k not in timing}              # the cached value is the value
    for f in os.listdir(tmp_path / "cache"):   # a cache written before bench.evaluate counted still videos ...
        entry = json.load(open(tmp_path / "cache" / f))
        entry["result"].pop("still")
        json.dump(entry, open(tmp_path / "cache" / f, "w"))
    n = len(calls)
    again = train.base_evaluation(model, a)
    assert "still" in again and len(calls) == n + 1                              # ... is evaluated again
    assert train.base_evaluation(model, a) == again and len(calls) == n + 1     # and rewritten
    for f in os.listdir(tmp_path / "cache"):   # a damaged cache file (by hand: one is written whole) ...
        (tmp_path / "cache" / f).write_text('{"key": {}, "resu')
    fresh = train.base_evaluation(model, a)
    assert len(calls) == n + 2 and {k: v for k, v in fresh.items() if k not in timing} == \
        {k: v for k, v in again.items() if k not in timing}                       # ... is evaluated again
    assert train.base_evaluation(model, a) == fresh and len(calls) == n + 2     # and rewritten


def test_executor_prompt_instruction_trains_and_evaluates_on_d_in_the_task_form(tiny_ckpt, tmp_path, monkeypatch):
    """The positive control's Executor prompt reaches both the training batch and the bench evaluation."""
    pairs = train.world.bench_pairs(0.3)[:4]
    frame0, prompts, descs = train._batch(pairs, [0, 3], "instruction")
    assert prompts == [train.world.instruction_form(pairs[i].d_vlm) for i in (0, 3)]
    assert descs == [pairs[i].d_vlm for i in (0, 3)] and frame0.shape[0] == 2
    assert train._batch(pairs, [0, 3])[1] == [pairs[i].task.text for i in (0, 3)]
    oracle = train._batch(pairs, [0, 3], "oracle_instruction")
    assert oracle[1] == [train.world.instruction_form(pairs[i].d_oracle) for i in (0, 3)]
    assert oracle[2] == descs                                      # the Demonstrator keeps the toy VLM's D
    seen = []
    monkeypatch.setattr(train.bench, "evaluate", lambda m, cond, *a, **k: seen.append(cond) or ({}, None, None))
    model = train.models.load_checkpoint(tiny_ckpt)[0]
    train.evaluate_executor(model, _args(tiny_ckpt, tmp_path, executor_prompt="instruction", stage="distill"))
    train.evaluate_executor(model, _args(tiny_ckpt, tmp_path, executor_prompt="instruction", stage="distill"),
                            demonstrator=True)
    assert seen == ["instruction", "vlm"]


@pytest.mark.parametrize("executor_prompt", ["instruction", "oracle_instruction", "oracle_direction"])
def test_rl_step_gives_the_executor_its_prompt_and_judges_t(tiny_ckpt, tmp_path, monkeypatch, executor_prompt):
    """In a control's rl stage the Executor is conditioned on its prompt (the toy VLM's or the error-free D in the
    task's form, or the error-free D's direction without its duration), the Demonstrator on the toy VLM's D, and the
    judges judge the rollouts against T."""
    args = _args(tiny_ckpt, tmp_path, executor_prompt=executor_prompt)
    model = train.models.load_checkpoint(tiny_ckpt)[0]
    train.models.add_lora(model, args.lora_rank, args.lora_alpha)
    params = train.models.lora_parameters(model)
    opt = torch.optim.Adam(params, lr=args.lr)
    pairs = train.world.bench_pairs(0.3)
    wrong = next(i for i, p in enumerate(pairs) if i and p.d_vlm != p.d_oracle)   # a second pair whose two D differ
    frame0, tasks, descs = train._batch(pairs, [0, wrong])
    prompts = train._batch(pairs, [0, wrong], executor_prompt)[1]
    texts, judged = [], []
    condition, judge = model.condition, train.judge_rollouts
    monkeypatch.setattr(model, "condition", lambda f, t: texts.append(list(t)) or condition(f, t))
    monkeypatch.setattr(train, "judge_rollouts", lambda v, t, *a: judged.append(list(t)) or judge(v, t, *a))
    train.rl_step(1, model, opt, params, args, train.rl_config(args), frame0, tasks, descs, torch.Generator(),
                  prompts=prompts)
    G = args.group_size
    field = "d_vlm" if executor_prompt == "instruction" else "d_oracle"
    form = train.world.direction_form if executor_prompt == "oracle_direction" else train.world.instruction_form
    assert texts[:2] == [[form(getattr(pairs[i], field)) for i in (0, wrong)], descs]
    assert judged == [[t for t in tasks for _ in range(G)]]


def test_each_distinct_image_and_prompt_is_conditioned_once_and_every_rollout_gets_its_own(tiny_ckpt, tmp_path,
                                                                                          monkeypatch):
    """Alg. 1 repeats every (image, T, D) group_size times: train._parts encodes each distinct pair once (a real
    backend's text encoder and VAE are the costly part) and hands every micro-batch the rows of its own rollouts."""
    args = _args(tiny_ckpt, tmp_path, group_size=4, micro_batch=3)
    model = train.models.load_checkpoint(tiny_ckpt)[0]
    pairs = train.world.bench_pairs(0.3)
    frame0, tasks, descs = train._batch(pairs, [0, 1, 2])
    b = train._group_batch(model, frame0, tasks, descs, args, torch.Generator().manual_seed(0), sde=False)
    seen, condition = [], model.condition
    monkeypatch.setattr(model, "condition", lambda f, t: seen.append(list(t)) or condition(f, t))
    parts = train._parts(model, b, args)
    assert seen == [tasks, descs]                                   # 3 rows each, not 12
    assert [p.rows for p in parts] == [slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)]
    for p in parts:
        for key, texts in (("c_E", b.prompts), ("c_D", b.descs)):
            want = condition(b.frame0[p.rows], texts[p.rows])
            got = getattr(p, key)
            assert got.keys() == want.keys() and all(torch.equal(got[k], want[k]) for k in want), key


def test_executor_ema_is_what_is_evaluated_and_saved_and_leaves_training_alone(tiny_ckpt, tmp_path, monkeypatch):
    """--executor_ema d (Tab. 3): ema <- d ema + (1 - d) theta after every --executor_ema_every-th Executor update
    (Alg. 2's rounds train phi and are skipped), from the base's LoRA; the evaluations and the saved Executor are the
    average, and the trained weights -- and so the run's rollouts and updates -- are those of a run without it."""
    e = [torch.zeros(3)]
    train.ema_step(e, [torch.ones(3)], 0.75)
    assert torch.allclose(e[0], torch.full((3,), 0.25))
    real_save, real_eval = train.save_state, train.evaluate_executor

    def run_with(name, resume=False, **kw):
        """Every step's trained LoRA and EMA (as save_state gets them; --save_every 1) and the LoRA each in-run
        evaluation of the Executor sees, by step."""
        states, evals = {}, {}

        def save(path, step, model, *a, **k):
            ema = a[-1] if len(a) == 9 else None
            states[step] = ([p.detach().clone() for p in train.models.lora_parameters(model)],
                            None if ema is None else [x.clone() for x in ema])
            return real_save(path, step, model, *a, **k)

        def evaluate(model, args, *a, **k):
            lora = train.models.lora_parameters(model)
            if lora and not a and not k:               # the Executor in the loop (not phi, not the merged one)
                evals[len(states) + 1] = [p.detach().clone() for p in lora]
            return real_eval(model, args, *a, **k)

        monkeypatch.setattr(train, "save_state", save)
        monkeypatch.setattr(train, "evaluate_executor", evaluate)
        args = _args(tiny_ckpt, tmp_path / name, **kw)
        args.resume = resume
        train.rl_stage(args)
        return states, evals

    def same(xs, ys):
        return all(torch.equal(x, y) for x, y in zip(xs, ys))

    plain, _ = run_with("plain", steps=4)
    avg, evals = run_with("ema", steps=4, executor_ema=0.5, executor_ema_every=2)
    want = [x.clone() for x in avg[1][1]]         # no update at step 1 (every 2nd): still the LoRA at the start
    assert len(want) > 0 and plain[4][1] is None
    assert all(x.abs().max() == 0 for x in want[1::2])                 # lora_B = 0: the average starts at the base
    for step in range(1, 5):
        trained, got = avg[step]
        assert same(trained, plain[step][0]), step                      # training is untouched by the average
        if step % 2 == 0:
            train.ema_step(want, trained, 0.5)
        assert same(got, want), step
    assert sorted(evals) == [2] and same(evals[2], avg[2][1])   # step 4's is the final one, of the saved Executor
    assert not same(want, avg[4][0])                                    # the average is not theta
    # the saved Executor is the base with the average folded in
    model = train.models.load_checkpoint(tiny_ckpt)[0]
    train.models.add_lora(model, 8, 16.0)
    with torch.no_grad():
        for p, w in zip(train.models.lora_parameters(model), want):
            p.copy_(w)
    saved = train.models.load_checkpoint(str(tmp_path / "ema" / "executor_awm.pt"))[0].state_dict()
    merged = train.models.merge_lora(model).state_dict()
    assert saved.keys() == merged.keys() and all(torch.equal(saved[k], merged[k]) for k in saved)
    assert "WMSD (awm, T, EMA 0.5)" in json.load(open(tmp_path / "ema" / "rl_summary.json"))["table"]
    # a resumed run carries the average on: 2 steps, then --resume to 4, ends where the uninterrupted run did
    run_with("halves", steps=2, executor_ema=0.5, executor_ema_every=2)
    resumed, _ = run_with("halves", resume=True, steps=4, executor_ema=0.5, executor_ema_every=2)
    assert same(resumed[4][0], avg[4][0]) and same(resumed[4][1], avg[4][1])
    # Alg. 2 (--alternate 2): step 2 is phi's round and leaves the Executor's average where it was
    alt, _ = run_with("alt", steps=3, executor_ema=0.5, alternate=2)
    assert same(alt[2][1], alt[1][1]) and not same(alt[3][1], alt[2][1])
    want = [x.clone() for x in alt[2][1]]
    train.ema_step(want, alt[3][0], 0.5)
    assert same(alt[3][1], want)
    # --executor_ema_schedule power (Tab. 3's HunyuanVideo-1.5 column): decay 0 at the first update, so the average
    # is the trained weights; then min(d, 1 - 2^(-2/3)) = 0.37 at the second
    assert [train.executor_ema_decay(0.9, "power", j) for j in (0, 30, 31)] == [0.0, 1 - 31 ** (-2 / 3), 0.9]
    assert train.executor_ema_decay(0.9, "constant", 0) == 0.9
    pw, _ = run_with("power", steps=2, executor_ema=0.5, executor_ema_schedule="power")
    assert same(pw[1][1], pw[1][0]) and not same(pw[1][1], avg[1][1])
    want = [x.clone() for x in pw[1][1]]
    train.ema_step(want, pw[2][0], 1 - 2 ** (-2 / 3))
    assert same(pw[2][1], want)


def test_distill_executor_ema_is_what_is_evaluated_kept_and_saved_and_leaves_training_alone(tiny_ckpt, tmp_path,
                                                                                           monkeypatch):
    """--executor_ema in the distill stage: ema <- d ema + (1 - d) theta after every --executor_ema_every-th update,
    from the weights the Executor starts with; the mid-run evaluation, the --keep_executors file, the last
    evaluation and the saved Executor are the average; the trained weights are those of a run without it."""
    real_update, real_eval = train._update, train.evaluate_executor

    def run_with(name, **kw):
        """Every update's trained weights, and the weights each evaluation of the Executor saw (not the base's)."""
        trained, scored = [], []

        def update(step, opt, params, *a, **k):
            out = real_update(step, opt, params, *a, **k)
            trained.append([p.detach().clone() for p in params])
            return out

        def evaluate(model, *a, **k):
            if trained:
                scored.append([p.detach().clone() for p in model.parameters()])
            return real_eval(model, *a, **k)

        monkeypatch.setattr(train, "_update", update)
        monkeypatch.setattr(train, "evaluate_executor", evaluate)
        args = _args(tiny_ckpt, tmp_path / name, stage="distill", variant="off", batch=2, steps=4, eval_every=2,
                     executor_weights="all", lr=0.01, **kw)
        args.keep_executors = True
        train.distill_stage(args)
        load = lambda f: list(train.models.load_checkpoint(str(tmp_path / name / f))[0].parameters())  # noqa: E731
        return trained, scored, load("executor_off_step2.pt"), load("executor_off.pt")

    def same(xs, ys):
        return len(xs) == len(ys) > 0 and all(torch.equal(x, y) for x, y in zip(xs, ys))

    plain, plain_scored, plain_kept, plain_saved = run_with("plain")
    trained, scored, kept, saved = run_with("ema", executor_ema=0.5, executor_ema_every=2)
    assert all(same(a, b) for a, b in zip(trained, plain)) and len(trained) == 4   # training untouched
    assert same(plain_saved, plain[-1]) and same(plain_kept, plain[1])             # without it: the trained weights
    want = list(train.models.load_checkpoint(tiny_ckpt)[0].parameters())           # the start: the base
    train.ema_step(want, trained[1], 0.5)                                          # step 2's update (every 2nd)
    assert same(scored[0], want) and same(kept, want) and not same(want, trained[1])
    train.ema_step(want, trained[3], 0.5)                                          # step 4's
    assert same(scored[1], want) and same(saved, want) and len(scored) == 2
    summary = json.load(open(tmp_path / "ema" / "distill_summary.json"))
    assert summary["executor_ema"] == 0.5 and summary["variants"]["off"][-1]["step"] == 4


@pytest.mark.parametrize("variant, more", [("off", {"executor_ema": 0.5}), ("dmd", {})])
def test_a_distill_run_resumed_ends_where_the_uninterrupted_run_does(tiny_ckpt, tmp_path, monkeypatch, variant, more):
    """A distill run of one variant saves state.pt every --save_every steps: a 4-step run stopped in step 4 (its
    state from step 2, its log to step 3) and resumed with --resume gives the uninterrupted run's log, evaluations,
    weights, optimizer, EMA (Eq. 3's run) and DMD's fake score (App. A.2.1); the state holds the Demonstrator's
    evaluation, so the resumed run does not take it again. A fresh run over the unfinished state is refused, a run of
    several variants saves no state, and another stage's state is not resumed."""
    def run_to(name, steps, resume=False, **kw):
        kw = {"save_every": 1, **kw}
        args = _args(tiny_ckpt, tmp_path / name, stage="distill", steps=steps, batch=2, lr=0.01, **kw)
        return train.distill_stage(dataclasses.replace(args, resume=resume))

    def scores(results):
        return [{k: v for k, v in e.items() if k != "seconds"} for e in results["variants"][variant]]

    whole = run_to("whole", 4, variant=variant, **more)
    real_update = train._update

    def update(step, *a, **k):
        if step == 4:
            raise KeyboardInterrupt
        return real_update(step, *a, **k)

    monkeypatch.setattr(train, "_update", update)
    with pytest.raises(KeyboardInterrupt):
        run_to("halves", 4, variant=variant, save_every=2, **more)
    monkeypatch.setattr(train, "_update", real_update)
    assert torch.load(tmp_path / "halves" / "state.pt", weights_only=True)["step"] == 2
    assert json.loads(open(tmp_path / "halves" / "distill.jsonl").read().splitlines()[-1])["step"] == 3
    with pytest.raises(ValueError, match=r"holds an unfinished run \(its state.pt: step 2 of 4\); continue it"):
        run_to("halves", 4, variant=variant, save_every=2, **more)
    evaluated = _spy(monkeypatch, train, "base_evaluation")
    halves = run_to("halves", 4, resume=True, variant=variant, save_every=2, **more)
    assert not evaluated                              # neither the Demonstrator nor the base at step 0 again
    assert scores(halves) == scores(whole) and [e["step"] for e in scores(whole)] == [0, 2, 4]
    assert halves["demonstrator"] == whole["demonstrator"]
    assert _metrics(tmp_path / "halves" / "distill.jsonl") == _metrics(tmp_path / "whole" / "distill.jsonl")
    a, b = (torch.load(tmp_path / d / "state.pt", weights_only=True) for d in ("halves", "whole"))
    assert a["step"] == b["step"] == 4
    same = lambda x, y: len(x) == len(y) > 0 and all(torch.equal(u, v) for u, v in zip(x, y))  # noqa: E731
    assert a["lora"].keys() == b["lora"].keys() and same(list(a["lora"].values()), list(b["lora"].values()))
    assert same([s["exp_avg_sq"] for s in a["opt"]["state"].values()],
                [s["exp_avg_sq"] for s in b["opt"]["state"].values()])
    if variant == "dmd":                              # the fake score and its optimizer came back too
        assert same(list(a["demo_lora"].values()), list(b["demo_lora"].values()))
        assert same([s["exp_avg"] for s in a["demo_opt"]["state"].values()],
                    [s["exp_avg"] for s in b["demo_opt"]["state"].values()])
    else:                                             # and the Executor's EMA
        assert same(a["ema"], b["ema"]) and a["demo_lora"] is None
    saved = [train.models.load_checkpoint(str(tmp_path / d / f"executor_{variant}.pt"))[0].state_dict()
             for d in ("halves", "whole")]
    assert same(list(saved[0].values()), list(saved[1].values()))
    monkeypatch.undo()
    run_to("two", 1, variant="off,on", save_every=10)          # several variants: no state
    assert (tmp_path / "two" / "distill_summary.json").exists() and not (tmp_path / "two" / "state.pt").exists()
    train.rl_stage(_args(tiny_ckpt, tmp_path / "rl", steps=1))
    with pytest.raises(ValueError, match=r"written with different settings: --stage 'rl' \(now 'distill'\)"):
        run_to("rl", 2, resume=True, variant=variant, **more)


def test_eval_every_defaults_by_stage_and_a_given_value_stands():
    every = lambda *argv: train.parse_args(list(argv)).eval_every  # noqa: E731
    assert every("--toy") == 25 and every("--stage", "rl") == 25
    assert every("--stage", "distill") == 10 and every("--stage", "pretrain") == 10
    assert every("--toy", "--eval_every", "10") == 10 and every("--stage", "distill", "--eval_every", "3") == 3
    with pytest.raises(SystemExit):
        every("--toy", "--eval_every", "-1")


def _reads(path: str, var: str, entry: str) -> set:
    """The attributes of `var` (var.NAME) that function `entry` of the module at `path` reads, itself or through the
    module's functions it calls, transitively: what the code reads, found from its syntax tree, not by running it."""
    funcs = {n.name: n for n in ast.parse(open(os.path.join(ROOT, path)).read()).body
             if isinstance(n, ast.FunctionDef)}
    found, todo, seen = set(), [entry], set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        for node in ast.walk(funcs[name]):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == var:
                found.add(node.attr)
            elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in funcs:
                todo.append(node.func.id)
    return found


def test_read_by_names_the_stages_whose_code_reads_each_flag():
    """train.READ_BY, which parse_args enforces, is what each stage's code reads: a stage that reads a flag the
    table denies it would refuse a working flag; one the table grants a flag it never reads would ignore it."""
    read = {stage: _reads("train.py", "args", fn.__name__) for stage, fn in train.STAGES.items()}
    for f in dataclasses.fields(train.Args):
        assert set(train.READ_BY.get(f.name, train.STAGES)) == {s for s in train.STAGES if f.name in read[s]}, f.name


def test_trainer_reads_names_the_trainers_whose_objective_reads_each_flag():
    """train.TRAINER_READS likewise, against rl.py: the flags rl_config passes as RLConfig fields, and the fields
    each trainer's objective reads (cfg.NAME). A flag the step itself reads whatever the trainer (--adv_clip, the
    advantages' clip, which nft's A_max also reads) is every trainer's."""
    call = next(n for n in ast.walk(ast.parse(open(os.path.join(ROOT, "train.py")).read()))
                if isinstance(n, ast.Call) and getattr(n.func, "attr", None) == "RLConfig")
    flag_of = {kw.arg: next(n.attr for n in ast.walk(kw.value) if isinstance(n, ast.Attribute))
               for kw in call.keywords}                                 # RLConfig field -> train.py flag
    assert set(flag_of) == {f.name for f in dataclasses.fields(train.rl.RLConfig)}
    read = {name: _reads("rl.py", "cfg", fn.__name__) for name, fn in train.rl.OBJECTIVES.items()}
    every = _reads("train.py", "args", "rl_step")
    for field, flag in flag_of.items():
        trainers = train.rl.OBJECTIVES
        objective = {t for t in trainers if field in read[t]}
        assert set(train.TRAINER_READS.get(flag, trainers)) == (set(trainers) if flag in every else objective), flag


def test_nfts_a_max_is_the_advantage_clip_or_5_without_one():
    a_max = lambda *argv: train.rl_config(train.parse_args(["--toy", "--trainer", "nft", *argv])).adv_max  # noqa: E731
    assert (a_max(), a_max("--adv_clip", "2"), a_max("--adv_clip", "0")) == (5, 2, 5)


@pytest.mark.parametrize("flag, wrong, right, msg", [
    (["--width", "64"], ["--stage", "rl"], ["--stage", "pretrain"],
     "--width is read with --stage pretrain only: --stage rl would ignore it"),
    (["--variant", "off"], [], ["--stage", "distill"], "--variant is read with --stage distill only: --stage rl"),
    (["--beta_d", "0"], ["--stage", "distill"], [], "--beta_d is read with --stage rl only: --stage distill"),
    (["--init", "b.pt"], ["--stage", "pretrain"], [], "--init is read with --stage distill and rl only"),
    (["--no-evidence_lead"], [], ["--stage", "pretrain"], "--no-evidence_lead is read with --stage pretrain only"),
    (["--log_every", "5"], [], ["--stage", "distill"], "--log_every is read with --stage pretrain and distill only"),
    (["--nft_beta", "2"], [], ["--trainer", "nft"], "--nft_beta is read with --trainer nft only: --trainer awm"),
    (["--awm_timesteps", "3"], ["--trainer", "grpo"], ["--trainer", "nft"],
     "--awm_timesteps is read with --trainer awm and nft only: --trainer grpo would ignore it"),
    (["--ghuber_power", "0.3"], ["--awm_weighting", "t"], [], "--ghuber_power is read with --awm_weighting ghuber"),
    (["--model_path", "/m"], ["--model", "ltx2-tiny"], ["--model", "ltx2"],
     "--model_path is read with --model ltx2 or hunyuan15 (real weights) only: --model ltx2-tiny would ignore it"),
    (["--model_path", "/m"], [], ["--model", "hunyuan15"], "--model toy would ignore it"),
    (["--judge_path", "/j"], ["--judge", "qwen-vl-tiny"], ["--judge", "qwen-vl"],
     "--judge_path is read with --judge qwen-vl (real weights) only: --judge qwen-vl-tiny would ignore it"),
    (["--judge_path", "/j"], [], ["--judge", "qwen-vl"], "--judge toy would ignore it"),
    (["--pick_path", "/p"], ["--pick", "pickscore-tiny", "--lambda_pick", "0.2"],
     ["--pick", "pickscore", "--lambda_pick", "0.2"],
     "--pick_path is read with --pick pickscore (real weights) only: --pick pickscore-tiny would ignore it"),
    (["--pick_processor_path", "/p"], [], ["--pick", "pickscore", "--pick_path", "/p", "--lambda_pick", "0.2"],
     "--pick_processor_path is read with --pick pickscore (real weights) only: --pick none would ignore it"),
    (["--pick", "pickscore-tiny"], ["--stage", "distill", "--lambda_pick", "0.2"], ["--lambda_pick", "0.2"],
     "--pick is read with --stage rl only: --stage distill would ignore it"),
    (["--noise_level", "0.5"], [], ["--sampler", "sde"], "--noise_level is read with SDE rollouts"),
    (["--noise_level", "0.5"], ["--trainer", "nft"], ["--trainer", "grpo"], "ODE rollouts would ignore it"),
    (["--beta_phi", "0.5"], [], ["--alternate", "2"], "--beta_phi is read with --alternate N"),
    (["--executor_ema_every", "2"], [], ["--executor_ema", "0.9"], "--executor_ema_every is read with --executor_ema"),
    (["--save_every", "5"], ["--stage", "distill", "--variant", "off,on"], ["--stage", "distill", "--variant", "off"],
     "--save_every is read with the rl stage or a distill run of one --variant (its state.pt) only: --variant off,on"),
    (["--motion_weight", "5"], ["--stage", "distill", "--variant", "off,on"],
     ["--stage", "distill", "--variant", "on,sft"],
     "--motion_weight is read with --stage pretrain, or --variant sft or paired (their video loss) only: --variant"),
    (["--loss_power", "2"], ["--stage", "distill"], ["--stage", "distill", "--variant", "paired"],
     "--loss_power is read"),
    *((flag, ["--stage", "distill", "--model", "ltx2-tiny", "--variant", "sft", "--sft_dataset", "f"],
       ["--stage", "distill", "--variant", "sft"],
       f"{flag[0]} is read with the toy's video loss (--model toy) only: --model ltx2-tiny would ignore it")
      for flag in (["--motion_weight", "5"], ["--loss_power", "2"])),
    (["--train_pairs", "64"], ["--stage", "distill", "--model", "ltx2-tiny", "--variant", "sft", "--sft_dataset", "f"],
     ["--model", "ltx2-tiny"], "--train_pairs is read with --model toy (the toy VLM's pairs) in the distill stage only"),
    (["--train_steps", "3"], ["--stage", "distill", "--variant", "sft,paired"],
     ["--stage", "distill", "--variant", "dmd"],
     "--train_steps is read with the rl stage and --variant off, on or dmd (their rollouts) only: --variant sft"),
    *((flag, ["--executor_update", "off"], ["--executor_update", "off", "--alternate", "2"],
       f"{flag[0]} is read with RL rounds (--executor_update wmsd, or --alternate N's Demonstrator rounds) only: "
       "--executor_update off without --alternate would ignore it")
      for flag in (["--trainer", "flow-grpo"], ["--clip_range", "0.1"], ["--sampler", "sde"], ["--lambda_task", "0.5"],
                   ["--lambda_cons", "0"], ["--task_reward", "attributed"], ["--adv_agg", "sum"], ["--adv_clip", "2"],
                   ["--lambda_pick", "0.2", "--pick", "pickscore-tiny"])),
    *((flag, ["--executor_update", "off", "--alternate", "2"], ["--alternate", "2"],
       f"{flag[0]} is read with --executor_update wmsd (Eq. 12's rounds) only: --executor_update off would ignore it")
      for flag in (["--lambda_distill", "0.5"], ["--beta_d", "0.1"], ["--inner_epochs", "2"])),
    *((flag, ["--lambda_task", "0", "--lambda_cons", "0", "--lambda_distill", "0"], ["--lambda_cons", "0"],
       f"{flag[0]} is read with L_RL (a --lambda_* > 0) only: every --lambda_* 0 (the anchor alone) would ignore it")
      for flag in (["--trainer", "nft"], ["--awm_timesteps", "3"], ["--adv_agg", "sum"], ["--adv_clip", "2"])),
    (["--task_reward", "attributed"], ["--lambda_task", "0"], ["--lambda_task", "0.5"],
     "--task_reward is read with --lambda_task > 0 (r_task's weight) only: --lambda_task 0 would ignore it"),
])
def test_a_flag_nothing_would_read_is_refused(flag, wrong, right, msg, capsys):
    """A flag set where the chosen stage, trainer or setting does not read it: exit 2 naming what would read it;
    the same flag where that is chosen: accepted."""
    with pytest.raises(SystemExit) as e:
        train.parse_args([*wrong, *flag])
    assert e.value.code == 2 and msg in capsys.readouterr().err
    train.parse_args([*right, *flag])


def test_the_final_table_names_the_fig5_setting_the_flags_select():
    name = lambda *argv: train.fig5_setting(train.parse_args(["--toy", *argv]))  # noqa: E731
    assert name() == "WMSD"
    assert name("--beta_d", "0", "--lambda_distill", "0") == "RL from the judges alone"
    assert name("--alternate", "2") == "WMSD, alternating (Alg. 2)"
    assert name("--alternate", "2", "--executor_update", "off") == "off-policy distillation + RL on the teacher"
    assert name("--executor_update", "off") == "off-policy distillation (Eq. 3)"       # Fig. 4 left's three, on
    assert name("--lambda_task", "0", "--lambda_cons", "0", "--lambda_distill", "0") == (   # a real model too
        "the anchor alone (Eq. 11, on-policy)")
    assert name("--lambda_task", "0", "--lambda_cons", "0") == "WMSD"
    assert name("--demonstrator", "executor") == "WMSD, the Executor as its own Demonstrator (App. A.3)"


def test_per_step_r_distill_trains_flow_grpo_on_per_step_advantages(tiny_ckpt, tmp_path):
    """--distill_reward per_step (App. A.3): advantages per (rollout, transition); the logged r_distill is still
    Eq. 9's trajectory sum, so it equals the trajectory-level run's on the same first step."""
    traj, _, _, _ = _one_step(tiny_ckpt, tmp_path, trainer="flow-grpo")
    per, grads, _, _ = _one_step(tiny_ckpt, tmp_path, trainer="flow-grpo", distill_reward="per_step")
    S = train.train_steps(_args(tiny_ckpt, tmp_path))
    assert len(per["A"]) == 8 and all(len(a) == S for a in per["A"])          # 2 tasks x a group of 4, S steps
    assert len(traj["A"]) == 8 and not isinstance(traj["A"][0], list)
    assert per["r_distill"] == traj["r_distill"] < 0
    assert per["loss"] != traj["loss"] and any(g.abs().sum() > 0 for g in grads)


def _spy(monkeypatch, owner, name: str) -> list:
    """Wrap owner.name so each call is recorded as (args, kwargs, result) in the returned list, then returned as is."""
    fn, calls = getattr(owner, name), []

    def spy(*a, **k):
        calls.append((a, k, fn(*a, **k)))
        return calls[-1][2]

    monkeypatch.setattr(owner, name, spy)
    return calls


def test_rl_step_wires_eq9_into_eq10_with_the_lambdas_and_eq12_with_beta_d(tiny_ckpt, tmp_path, monkeypatch):
    """rl_step hands the advantages r_distill = the sum of distill_reward's per-step terms (Eq. 9) -- with
    --distill_reward per_step each transition's credit to go (App. A.3) -- under the --lambda_* weights (Eq. 10), and
    its loss is L_RL + beta_d L_anchor (Eq. 12). Non-default weights, so a flag that does not arrive shows."""
    rewards_of = _spy(monkeypatch, train.distill, "distill_reward")
    advantages_of = _spy(monkeypatch, train.rl, "advantages")
    for mode in ("trajectory", "per_step"):
        rewards_of.clear()
        rec = _one_step(tiny_ckpt, tmp_path, trainer="flow-grpo", distill_reward=mode, lambda_distill=0.5,
                        lambda_cons=0.7, beta_d=0.3)[0]
        terms = torch.cat([out for _, _, out in rewards_of])                      # (N, S), each -(dt) l <= 0
        (rewards, weights, *_), _, _ = advantages_of[-1]
        assert terms.shape == (8, train.train_steps(_args(tiny_ckpt, tmp_path))) and (terms < 0).all()
        expect = terms.sum(1) if mode == "trajectory" else train.distill.distill_reward_to_go(terms)
        assert torch.equal(rewards["distill"], expect), mode
        assert weights == {"task": 1.0, "distill": 0.5, "consistency": 0.7}
        assert rec["r_distill"] == pytest.approx(terms.sum(1).mean().item(), rel=1e-6)   # the log keeps Eq. 9's sum
        # the tiny base's velocities are small (L_anchor ~1e-8): a tolerance relative to the anchor's term
        assert rec["l_anchor"] > 0 and abs(rec["loss"] - (rec["l_rl"] + 0.3 * rec["l_anchor"])) < 1e-3 * rec["l_anchor"]


def test_with_no_reward_weighed_the_step_trains_the_anchor_alone(tiny_ckpt, tmp_path, monkeypatch):
    """Every --lambda_* 0 with --beta_d > 0 (train.anchor_only): no advantages, no L_RL, the loss is beta_d L_anchor
    (Eq. 11 on the Executor's own states) -- Fig. 4 left's on-policy variant, runnable on a real model. The same
    step with r_distill weighed (the full on-policy objective) does compute advantages and L_RL."""
    advantages_of = _spy(monkeypatch, train.rl, "advantages")
    awm, awm_of = train.rl.OBJECTIVES["awm"], []
    monkeypatch.setitem(train.rl.OBJECTIVES, "awm", lambda *a, **k: awm_of.append(1) or awm(*a, **k))
    rec, grads, *_ = _one_step(tiny_ckpt, tmp_path, lambda_task=0, lambda_cons=0, lambda_distill=0, beta_d=0.3)
    assert not advantages_of and not awm_of and rec["l_rl"] == 0 and rec["adv_abs"] == 0
    assert rec["l_anchor"] > 0 and rec["loss"] == pytest.approx(0.3 * rec["l_anchor"], rel=1e-5)
    assert any(g.abs().sum() > 0 for g in grads)
    assert train.fig5_setting(_args(tiny_ckpt, tmp_path, lambda_task=0, lambda_cons=0, lambda_distill=0)).startswith(
        "the anchor alone")
    _one_step(tiny_ckpt, tmp_path, lambda_task=0, lambda_cons=0, lambda_distill=1, beta_d=0.3)   # Fig. 4 left's
    assert advantages_of and awm_of                                           # full on-policy objective: r_distill


def test_off_policy_update_regresses_on_the_demonstrators_own_states_under_d(tiny_ckpt, tmp_path, monkeypatch):
    """Fig. 5 (iii), --executor_update off: Eq. 3's states are the Demonstrator's (adapters off) under c_D, and the
    loss compares the Executor under c_E with the Demonstrator under that same c_D: the velocities its sampler took
    along that trajectory, not computed again."""
    rollouts, losses = (_spy(monkeypatch, train.distill, n) for n in ("rollout", "off_policy_loss"))
    _one_step(tiny_ckpt, tmp_path, executor_update="off")
    ((_, _, c, _), kw, (traj, v_D)), ((_, states, c_E, c_D, *_), loss_kw, _) = rollouts[-1], losses[-1]
    assert kw["demonstrator"] and c is c_D and not torch.equal(c_E["ids"], c_D["ids"])
    assert states is traj and loss_kw["teacher_v"] is v_D


def test_alg2s_off_policy_rounds_regress_on_phis_states_and_velocities(tiny_ckpt, tmp_path, monkeypatch):
    """Fig. 5 (iii) as the paper runs it, --executor_update off with --alternate ("off-policy distillation + RL on
    the teacher"): the Executor's Eq. 3 follows the trained Demonstrator phi -- its trajectory under c_D and the
    velocities its sampler took -- not the base's."""
    args = _args(tiny_ckpt, tmp_path, group_size=4, executor_update="off", alternate=2)
    model = train.models.load_checkpoint(tiny_ckpt)[0]
    phi = train.models.copy_for_adapter(model)
    torch.manual_seed(0)
    for net in (model, phi):
        train.models.add_lora(net, args.lora_rank, args.lora_alpha)
    for name, p in phi.named_parameters():      # phi trained away from the base
        if "lora_B" in name:
            p.data.normal_(0, 0.05)
    params = train.models.lora_parameters(model)
    rollouts = _spy(monkeypatch, train.distill, "rollout")
    frame0, tasks, descs = train._batch(train.world.bench_pairs(0.3), [0, 1])
    train.rl_step(1, model, torch.optim.Adam(params, lr=args.lr), params, args, train.rl_config(args), frame0, tasks,
                  descs, torch.Generator().manual_seed(0), teacher=phi)
    (_, _, c_D, _), _, (traj, v_D) = rollouts[-1]
    phis = train.distill.teacher_velocities(model, traj, c_D, phi)
    assert torch.allclose(v_D, phis, rtol=1e-4, atol=1e-6)      # with Eq. 2's steps: phi's trajectory
    assert not torch.allclose(v_D, train.distill.teacher_velocities(model, traj, c_D), rtol=1e-4, atol=1e-6)


def test_the_flags_refused_under_executor_update_off_change_nothing_in_its_rounds(tiny_ckpt, tmp_path, monkeypatch):
    """train.unread_flags' rules for Fig. 5 (iii), checked against the code: each flag it refuses under
    --executor_update off leaves the Executor's off-policy round (loss, LoRA gradients, random stream) exactly as it
    was, and each it refuses even with --alternate leaves the Demonstrator round so too. A flag each round reads
    (Eq. 3's --distill_motion_weight; the Demonstrator's --trainer) changes it: the comparison sees a flag read."""
    changed = {"trainer": "flow-grpo", "clip_range": 0.1, "kl_beta": 0.5, "awm_timesteps": 3, "awm_times": "grid",
               "awm_weighting": "t", "awm_ratio": "sum_first", "nft_beta": 2, "sampler": "sde", "lambda_task": 0.5,
               "lambda_cons": 0.5, "task_reward": "attributed", "adv_agg": "sum", "adv_clip": 2,
               "lambda_distill": 0.5, "beta_d": 0.1, "inner_epochs": 2, "distill_motion_weight": 2}
    off_only = ("lambda_distill", "beta_d", "inner_epochs")
    unread = set(changed) - {"distill_motion_weight"}

    def refused(**kw):
        args = dataclasses.replace(_args(tiny_ckpt, tmp_path), executor_update="off", **kw)
        return {name for name, *_ in train.unread_flags(args)}

    assert refused(**changed) == unread
    judged = {k: v for k, v in changed.items() if k not in train.TRAINER_READS}   # not another trainer's flags
    assert refused(alternate=2, **judged) == set(off_only)
    monkeypatch.setattr(train, "unread_flags", lambda args: [])      # so that parse_args takes them all
    # the Executor's round, then Alg. 2's Demonstrator round (_one_step runs it when alternate is set); the unread
    # flags all at once (one run, not one each: their effects, were there any, would not cancel to the last bit)
    for alternate, ignored, read in ((0, unread, "distill_motion_weight"), (2, off_only, "trainer")):
        rec0, grads0, gen0, _ = _one_step(tiny_ckpt, tmp_path, executor_update="off", alternate=alternate)
        for names in (ignored, [read]):
            rec, grads, gen, _ = _one_step(tiny_ckpt, tmp_path, executor_update="off", alternate=alternate,
                                           **{name: changed[name] for name in names})
            same = (rec["loss"] == rec0["loss"] and torch.equal(gen, gen0)
                    and all(torch.equal(g, h) for g, h in zip(grads, grads0)))
            assert same == (names != [read]), (alternate, names)


def test_distill_variants_train_on_the_states_and_videos_their_objective_names(tiny_ckpt, tmp_path, monkeypatch):
    """One step of each --stage distill variant: off (Eq. 3) on the Demonstrator's rollout (adapters off) under c_D,
    on (Eq. 5) and dmd (App. A.2.1, both the generator and the fake score) on the Executor's own under c_E, with c_E
    holding T and c_D the toy VLM's D; paired fits the correct executions of T, sft the sft_batch's videos under
    their own labels. Pairs whose D is wrong, so D and the correct plan differ."""
    args = _args(tiny_ckpt, tmp_path, stage="distill", steps=1, batch=2)
    res = {k: 0.0 for k in train.EVAL_KEYS}
    monkeypatch.setattr(train, "evaluate_executor", lambda *a, **k: res)
    conds = _spy(monkeypatch, train.models.ToyVideoFlow, "condition")
    rollouts, fits, sft = (_spy(monkeypatch, owner, n) for owner, n in
                           ((train.distill, "rollout"), (train, "video_loss"), (train.world, "sft_batch")))
    losses = {n: _spy(monkeypatch, train.distill, n) for n in
              ("off_policy_loss", "on_policy_loss", "dmd_generator_loss", "dmd_fake_score_loss")}
    pairs = [p for p in train.world.make_pairs(40, seed=0, error_rate=0.5) if p.error][:4]
    texts = lambda c: next(a[2] for a, _, out in conds if out is c)  # noqa: E731
    for variant in ("off", "on", "dmd", "paired", "sft"):
        for calls in (conds, rollouts, fits, sft, *losses.values()):
            calls.clear()
        with open(tmp_path / "log.jsonl", "w") as logf:
            _, evals = train.distill_variant(args, variant, pairs, logf, res)
        assert [e["step"] for e in evals] == [0, 1]       # the base's, and the last step's (not on --eval_every 10)
        if variant in ("off", "on", "dmd"):
            (_, _, c, *demo), _, traj = rollouts[-1]
            name = {"off": "off_policy_loss", "on": "on_policy_loss", "dmd": "dmd_generator_loss"}[variant]
            (_, *a), _, _ = losses[name][-1]
            c_E, c_D = a[2:4] if variant == "dmd" else a[1:3]            # after (fake, x) or (trajectory)
            assert all(t.startswith("[") for t in texts(c_E)) and set(texts(c_D)) <= {p.d_vlm for p in pairs}
            assert (c is c_D and demo[1:] == [True]) if variant == "off" else (c is c_E and demo[1:] == [])
        if variant == "on":
            assert losses[name][-1][0][1] is traj
        if variant == "off":      # the Demonstrator's trajectory, and the velocities its sampler took along it
            (_, states, *_), kw, _ = losses[name][-1]
            assert states is traj[0] and kw["teacher_v"] is traj[1]
        if variant == "dmd":
            assert losses["dmd_fake_score_loss"][-1][0][2] is c_E
        if variant == "paired":
            (_, videos, captions, _), _, _ = fits[-1]
            for v, t in zip(videos, captions):
                p = next(p for p in pairs if p.task.text == t and np.array_equal(p.frame0, v[0]))
                assert np.array_equal(v, train.world.render(p.scene, train.world.simulate(p.scene, p.plan_oracle)))
        if variant == "sft":
            (_, videos, captions, _), _, _ = fits[-1]
            assert videos is sft[-1][2][0] and captions is sft[-1][2][1]
    # paired under a control's prompt labels the correct executions with it; sft under --train_crowded fits plain
    # videos of 5-sprite scenes
    with open(tmp_path / "log.jsonl", "w") as logf:
        train.distill_variant(_args(tiny_ckpt, tmp_path, stage="distill", steps=1, batch=2, variant="paired",
                                    executor_prompt="oracle_instruction"), "paired", pairs, logf, res)
        (_, _, captions, _), _, _ = fits[-1]
        assert set(captions) <= set(bench.prompts_for(pairs, "oracle_instruction")) and not set(captions) & {
            p.task.text for p in pairs}
        train.distill_variant(dataclasses.replace(args, train_crowded=True), "sft", pairs, logf, res)
    (_, videos, _, _), _, _ = fits[-1]
    assert {len(train.world.read_sprites(v[0])) for v in videos} == {5}


def test_off_judged_regresses_only_on_the_demonstrator_rollouts_the_judges_pass(tiny_ckpt, tmp_path, monkeypatch):
    """--off_judged (ours): the judges see each of the Demonstrator's videos -- its trajectory's end decoded after
    its first frame -- against its pair's T, and Eq. 3 regresses on the rows they pass only: those rows' states,
    their sampler's velocities, T under c_E and D under c_D. A row judged NaN (no judgment) is dropped as a failure;
    a step whose every row fails updates nothing."""
    args = dataclasses.replace(_args(tiny_ckpt, tmp_path, stage="distill", steps=1, batch=4), off_judged=True)
    res = {k: 0.0 for k in train.EVAL_KEYS}
    monkeypatch.setattr(train, "evaluate_executor", lambda *a, **k: res)
    conds = _spy(monkeypatch, train.models.ToyVideoFlow, "condition")
    rollouts, losses = (_spy(monkeypatch, train.distill, n) for n in ("rollout", "off_policy_loss"))
    texts = lambda c: next(a[2] for a, _, out in conds if out is c)  # noqa: E731
    pairs = train.world.make_pairs(40, seed=0, error_rate=0.5)[:8]
    judged, verdicts = [], torch.tensor([1.0, float("nan"), 0.0, 1.0])
    monkeypatch.setattr(train, "judge_rollouts", lambda v, t, *a, **k: judged.append((v, t)) or {"solved": verdicts})
    with open(tmp_path / "log.jsonl", "w") as logf:
        train.distill_variant(args, "off", pairs, logf, res)
    (_, _, c_D, *_), _, ((xs, _), v_D) = rollouts[-1]
    (videos, tasks), = judged
    batch = [next(p for p in pairs if p.d_vlm == d and np.array_equal(p.frame0, f))
             for d, f in zip(texts(c_D), videos[:, 0])]
    assert tasks == [p.task.text for p in batch]
    assert np.array_equal(videos[:, 1:], train.models.ToyVideoFlow.decode(xs[-1], videos[:, 0])[:, 1:])
    (_, (states, _), c_E, c_D_kept, *_), kw, _ = losses[-1]
    assert torch.equal(states, xs[:, [0, 3]]) and torch.equal(kw["teacher_v"], v_D[:, [0, 3]])
    c_E_all = next(out for a, _, out in conds if a[2] == tasks)     # the batch's condition under T
    assert torch.equal(c_E_all["frame0"], c_D["frame0"])
    for kept, whole in ((c_E, c_E_all), (c_D_kept, c_D)):      # rows 0 and 3: their first frames, T and D
        assert kept.keys() == whole.keys() and all(torch.equal(kept[k], whole[k][[0, 3]]) for k in whole)
    verdicts.zero_()
    with open(tmp_path / "log.jsonl", "w") as logf:
        model, _ = train.distill_variant(dataclasses.replace(args, executor_weights="all"), "off", pairs, logf, res)
    base = train.models.load_checkpoint(tiny_ckpt)[0]
    assert all(torch.equal(p, q) for p, q in zip(base.parameters(), model.parameters()))
    assert json.loads(open(tmp_path / "log.jsonl").read().splitlines()[-2])["judged_kept"] == 0


def test_off_pool_draws_eq3_batches_from_judged_demonstrator_rollouts_made_once(tiny_ckpt, tmp_path, monkeypatch):
    """--off_pool N (ours): before the first step the Demonstrator rolls out N trajectories under c_D for each
    training pair, from noises all different, judged against T under --off_judged; the steps roll out nothing and
    regress Eq. 3 on trajectories drawn from the pool -- the kept ones only, each with its own states, its sampler's
    velocities, its pair's T under c_E and D under c_D. A pool smaller than a batch is refused."""
    args = dataclasses.replace(_args(tiny_ckpt, tmp_path, stage="distill", steps=3, batch=4), off_judged=True,
                               off_pool=2)
    res = {k: 0.0 for k in train.EVAL_KEYS}
    monkeypatch.setattr(train, "evaluate_executor", lambda *a, **k: res)
    conds = _spy(monkeypatch, train.models.ToyVideoFlow, "condition")
    rollouts, losses = (_spy(monkeypatch, train.distill, n) for n in ("rollout", "off_policy_loss"))
    texts = lambda c: next(a[2] for a, _, out in conds if out is c)  # noqa: E731
    pairs = train.world.make_pairs(40, seed=0, error_rate=0.5)[:6]
    judged, verdicts = [], torch.tensor([1.0, float("nan"), 0.0, 1.0])
    monkeypatch.setattr(train, "judge_rollouts", lambda v, t, *a, **k: judged.append(t) or {"solved": verdicts[:len(t)]})
    with open(tmp_path / "log.jsonl", "w") as logf:
        train.distill_variant(args, "off", pairs, logf, res)
    assert len(rollouts) == 3 and len(losses) == 3         # 12 rollouts in batches of 4 before the steps; none after
    descs = sum((texts(a[2]) for a, _, _ in rollouts), [])
    assert descs == [p.d_vlm for p in pairs for _ in range(2)] and judged == [
        [p.task.text for p in pairs for _ in range(2)][i:i + 4] for i in (0, 4, 8)]
    x_0 = torch.cat([a[1] for a, _, _ in rollouts])
    assert len({tuple(x.flatten()[:4].tolist()) for x in x_0}) == 12
    kept = [(xs[:, j], v_D[:, j], d) for (_, _, c, *_), _, ((xs, _), v_D) in rollouts
            for j, d in enumerate(texts(c)) if verdicts[j] == 1]
    drawn = []                  # which kept trajectories each step drew: not the same ones every step
    for (_, (states, _), c_E, c_D, *_), kw, _ in losses:
        assert states.shape[1] == 4
        drawn.append(set())
        for j in range(4):
            (i, v, d), = [(i, v, d) for i, (x, v, d) in enumerate(kept) if torch.equal(x, states[:, j])]
            assert torch.equal(kw["teacher_v"][:, j], v) and texts(c_D)[j] == d
            assert texts(c_E)[j] == next(p.task.text for p in pairs if p.d_vlm == d)
            drawn[-1].add(i)
    assert len(set(map(frozenset, drawn))) > 1
    pool = json.loads(open(tmp_path / "log.jsonl").read().splitlines()[0])
    assert pool["pool"] and (pool["rollouts"], pool["kept"]) == (12, 6)
    verdicts[0] = 0.0
    with pytest.raises(ValueError, match="the Demonstrator pool kept 3 of 12 rollouts, fewer than a batch of 4"):
        with open(tmp_path / "log.jsonl", "w") as logf:
            train.distill_variant(args, "off", pairs, logf, res)


def _base_rollouts(base, rollouts: list) -> None:
    """Every Demonstrator trajectory Eq. 3 read (distill.rollout's spy, calls with velocities=True) is `base`'s own
    from that noise under c_D: its states and the velocities its sampler took, Eq. 3's targets."""
    assert rollouts
    for (_, x_0, c, steps, *_), kw, ((xs, _), v_D) in rollouts:     # the first argument is the Executor
        (base_xs, _), base_v = REAL_ROLLOUT(base, x_0, c, steps, velocities=True)
        assert kw["velocities"] and torch.allclose(xs, base_xs, atol=1e-5) and torch.allclose(v_D, base_v, atol=1e-5)


def _base_targets(base, targets: list) -> None:
    """Every Demonstrator velocity distill.teacher_velocity returned (its spy's calls) is `base`'s own at that
    state, time and c_D."""
    assert targets
    with torch.no_grad():
        for (_, x_t, t, c_D, *_), _, v in targets:
            assert torch.allclose(v, base(x_t, t, c_D), atol=1e-5)


def test_executor_weights_all_trains_every_weight_against_the_frozen_base(tiny_ckpt, tmp_path, monkeypatch):
    """--executor_weights all, distill stage: the Executor has no adapter and every weight of it trains, and at every
    step every Demonstrator velocity Eqs. 3 and 5 read is the base's -- not the moving Executor's with adapters off,
    which it would be if the frozen copy did not arrive. Eq. 3's states and targets are the base's rollouts under c_D
    and the velocities its sampler took, not computed again (no teacher_velocity call)."""
    base = train.models.load_checkpoint(tiny_ckpt)[0]
    targets, rollouts = (_spy(monkeypatch, train.distill, n) for n in ("teacher_velocity", "rollout"))
    res = {k: 0.0 for k in train.EVAL_KEYS}
    monkeypatch.setattr(train, "evaluate_executor", lambda *a, **k: res)
    pairs = [p for p in train.world.make_pairs(40, seed=0, error_rate=0.5) if p.error][:4]
    args = _args(tiny_ckpt, tmp_path, stage="distill", steps=3, batch=2, executor_weights="all", lr=0.01)
    for variant in ("on", "off"):
        targets.clear()
        rollouts.clear()
        with open(tmp_path / "log.jsonl", "w") as logf:
            model, _ = train.distill_variant(args, variant, pairs, logf, res)
        assert not any(isinstance(m, train.models.LoRA) for m in model.modules())
        moved = {n for (n, p), q in zip(model.named_parameters(), base.parameters()) if not torch.equal(p, q)}
        assert {"inp.weight", "text_proj.weight", "out.weight"} <= moved, variant
        if variant == "on":
            _base_targets(base, targets)
            assert len(targets) == 3
        else:      # the Demonstrator's states and velocities: the base's rollout from the same noise under c_D
            assert not targets and len(rollouts) == 3
            _base_rollouts(base, rollouts)


def test_executor_weights_all_in_the_rl_stage_anchors_to_the_base_and_resumes_every_weight(tiny_ckpt, tmp_path,
                                                                                         monkeypatch):
    """--executor_weights all, rl stage: Eqs. 9 and 11 read the base's velocities at every step, and the state keeps
    every weight, so 2 steps and then --resume to 4 end where 4 steps do, away from the base."""
    base = train.models.load_checkpoint(tiny_ckpt)[0]
    targets = _spy(monkeypatch, train.distill, "teacher_velocity")

    def state(name, steps, resume=False):
        args = _args(tiny_ckpt, tmp_path / name, steps=steps, executor_weights="all", lr=0.01)
        args.resume = resume
        train.rl_stage(args)
        return torch.load(tmp_path / name / "state.pt", weights_only=True)["lora"]

    whole = state("whole", 4)
    _base_targets(base, targets)
    state("halves", 2)
    halves = state("halves", 4, resume=True)
    assert whole.keys() == halves.keys() == base.state_dict().keys()
    assert all(torch.equal(whole[k], halves[k]) for k in whole)
    assert not torch.equal(whole["inp.weight"], base.state_dict()["inp.weight"])


@pytest.mark.parametrize("stage", ["rl", "distill"])
def test_executor_init_starts_the_executor_from_a_saved_one_beside_the_base_demonstrator(stage, tiny_ckpt, tmp_path,
                                                                                       monkeypatch, capsys):
    """--executor_init (Fig. 1's two stages, distillation and then RL; or distillation from a distilled Executor):
    the stage's Executor starts from the saved Executor's weights, which step 0's evaluation scores, while the
    Demonstrator's velocities (Eq. 3; Eqs. 9 and 11) are the base's (the frozen copy taken before the weights
    arrive); a checkpoint of another network is refused before anything is written."""
    base = train.models.load_checkpoint(tiny_ckpt)[0]
    saved = train.models.load_checkpoint(tiny_ckpt)[0]
    with torch.no_grad():
        for p in saved.parameters():
            p.add_(0.05 * torch.randn_like(p))
    train.models.save_checkpoint(saved, str(tmp_path / "executor_off.pt"), {})
    targets, rollouts = (_spy(monkeypatch, train.distill, n) for n in ("teacher_velocity", "rollout"))
    real, seen = train.evaluate_executor, []
    monkeypatch.setattr(train, "evaluate_executor", lambda model, *a, **k: seen.append(
        {n: v.clone() for n, v in model.state_dict().items()}) or real(model, *a, **k))
    distill = dict(stage="distill", variant="off", batch=2) if stage == "distill" else {}
    args = _args(tiny_ckpt, tmp_path / "run", steps=1, eval_every=1, executor_weights="all", lr=0.01,
                 executor_init=tmp_path / "executor_off.pt", **distill)
    train.STAGES[stage](args)
    assert ("eval step 0 (--executor_init, given T)" if stage == "rl" else
            "every variant's Executor starts from") in capsys.readouterr().out
    if stage == "rl":      # Eqs. 9 and 11
        _base_targets(base, targets)
    else:                  # Eq. 3: the base's own rollouts under c_D, and the velocities its sampler took
        _base_rollouts(base, [r for r in rollouts if r[1].get("velocities")])
    at_0, final = seen[-2:]      # step 0's evaluation, then step 1's
    assert all(torch.equal(at_0[n], v) for n, v in saved.state_dict().items())
    assert not torch.equal(final["inp.weight"], at_0["inp.weight"])
    out = tmp_path / "never"
    tiny = TINY if stage == "rl" else [*TINY_ANY, "--stage", "distill", "--variant", "off"]
    err = exit_2(train.main, [*tiny, "--init", tiny_ckpt, "--executor_weights", "all", "--executor_init",
                              train.models.SHIPPED_BASE, "--run_dir", out], capsys)
    assert "is not an Executor of this base" in err and not out.exists(), err


def test_train_crowded_draws_both_stages_training_pairs_from_five_sprite_scenes(tiny_ckpt, tmp_path, monkeypatch):
    """--train_crowded (the toy's Table 2): the rl stage's pairs (load_pairs) and the pairs the distill stage hands
    each variant come from 5-sprite scenes, none of them the crowded bench's; without it, from the bench's 2-4."""
    sprites = lambda pairs: {len(p.scene.sprites) for p in pairs}  # noqa: E731
    rl_args = _args(tiny_ckpt, tmp_path)
    assert sprites(train.load_pairs(rl_args, None)) <= {2, 3, 4}
    crowded = train.load_pairs(dataclasses.replace(rl_args, train_crowded=True), None)
    assert sprites(crowded) == {5} and len(crowded) == rl_args.train_pairs
    assert not train.world.bench_scene_keys(True) & {train.world.scene_key(p.scene) for p in crowded}

    class Handed(Exception):
        pass

    def handed(args, variant, pairs, logf, at_0, base=None, start_from=None, fixed=None, state=None):
        raise Handed(pairs)

    monkeypatch.setattr(train, "distill_variant", handed)
    monkeypatch.setattr(train, "evaluate_executor", lambda *a, **k: {k: 0.0 for k in train.EVAL_KEYS})
    args = _args(tiny_ckpt, tmp_path, stage="distill", variant="paired")
    for flag, want in ((False, {2, 3, 4}), (True, {5})):
        with pytest.raises(Handed) as e:
            train.distill_stage(dataclasses.replace(args, train_crowded=flag))
        assert sprites(e.value.args[0]) <= want and len(sprites(e.value.args[0]) & want) > 0


def test_eval_crowded_evaluates_every_model_of_both_stages_and_draws_the_gif_on_the_crowded_bench(
        tiny_ckpt, tmp_path, monkeypatch):
    """--eval_crowded: every video the run generates for evaluation or its GIF (the base's, the Demonstrator's, the
    Executor's) starts from a crowded bench pair's first frame; without it, from the bench's. Training rollouts do
    not go through models.generate, so all it sees are the bench's videos; they and the updates are the same either
    way."""
    firsts = {b: {p.frame0.tobytes() for p in pairs(0.3)}
              for b, pairs in (("toy", train.world.bench_pairs), ("crowded", train.world.crowded_pairs))}
    real, seen = train.models.generate, []
    monkeypatch.setattr(train.models, "generate",
                        lambda m, frame0, *a, **k: seen.append(frame0) or real(m, frame0, *a, **k))
    for stage, kw in (("rl", {"steps": 1}), ("distill", {"steps": 1, "variant": "on", "batch": 2})):
        for bench_name, flag in (("toy", False), ("crowded", True)):
            seen.clear()        # a stale bench and judge, as an in-process rl run with --eval_dataset and --judge
            monkeypatch.setattr(train, "BENCH", train.world.bench_pairs(0.3)[:4] if flag else   # leaves them, unread
                                train.world.crowded_pairs(0.3)[:4])
            monkeypatch.setattr(train, "JUDGE", object())       # no .bench: reading it fails
            args = dataclasses.replace(_args(tiny_ckpt, tmp_path / stage / bench_name, stage=stage, **kw),
                                       eval_crowded=flag)
            (train.rl_stage if stage == "rl" else train.distill_stage)(args)
            rows = {f.tobytes() for frame0 in seen for f in frame0}
            assert len(seen) >= 4, (stage, bench_name)          # the base, the Demonstrator, an Executor, the GIF
            assert rows <= firsts[bench_name], (stage, bench_name)
    steps = lambda d: [r for r in _metrics(d / "rl.jsonl") if "A" in r]  # noqa: E731
    assert steps(tmp_path / "rl" / "toy") == steps(tmp_path / "rl" / "crowded")    # training itself is unchanged


def test_a_group_is_group_size_rollouts_of_one_task_from_their_own_noise(tiny_ckpt, tmp_path):
    """Alg. 1 lines 3-5: each (image, T, D) repeated group_size times, in consecutive rows that rl.advantages
    standardises together (groups), each rollout from its own noise."""
    args = _args(tiny_ckpt, tmp_path, group_size=3)
    model = train.models.load_checkpoint(tiny_ckpt)[0]
    pairs = train.world.make_pairs(4, seed=0, error_rate=0.0)
    frame0, tasks, descs = train._batch(pairs, range(4))
    b = train._group_batch(model, frame0, tasks, descs, args, torch.Generator().manual_seed(0), sde=False)
    assert b.groups.tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3]
    for g in range(4):
        rows = (b.groups == g).nonzero().flatten().tolist()
        assert {b.tasks[r] for r in rows} == {tasks[g]} and {b.descs[r] for r in rows} == {descs[g]}
        assert all(np.array_equal(b.frame0[r], frame0[g]) for r in rows)
    assert len({tuple(x.flatten()[:4].tolist()) for x in b.x_0}) == 12


def test_update_clips_the_gradient_norm_to_1():
    """Table 3's max grad norm 1: _update's SGD step (lr 1) moves the weights by the gradient clipped to norm 1; the
    gradient itself, (20, 20, 20, 20), has norm 40, which _update reports."""
    w = torch.nn.Parameter(torch.zeros(4))
    before = w.detach().clone()
    _, gnorm, _ = train._update(1, torch.optim.SGD([w], lr=1.0), [w], [types.SimpleNamespace(share=1.0)],
                                lambda p: ((20 * w).sum(), {}), torch.Generator(), "test")
    assert gnorm == pytest.approx(40.0) and (w.detach() - before).norm().item() == pytest.approx(1.0, rel=1e-6)


def test_a_demonstrator_round_weighs_task_and_consistency_by_their_lambdas(tiny_ckpt, tmp_path, monkeypatch):
    """Alg. 2 lines 11-16: phi's advantages are of lambda_task r_task + lambda_cons r_cons (no r_distill: phi is
    judged on its own rollouts under c_D). With --pick, PickScore's lambda_pick r_pick is weighed in phi's rounds and
    in the Executor's (Table 3's third reward)."""
    advantages_of = _spy(monkeypatch, train.rl, "advantages")
    _one_step(tiny_ckpt, tmp_path, alternate=1, lambda_task=0.9, lambda_cons=0.7)
    (rewards, weights, *_), _, _ = advantages_of[-1]
    assert weights == {"task": 0.9, "consistency": 0.7} and set(rewards) == set(weights)
    # with PickScore (--pick; here a stand-in scoring each video by its row), weighed in both kinds of round
    monkeypatch.setattr(train, "PICK", lambda videos, prompts: np.arange(len(prompts), dtype=float))
    for alternate in (1, 0):      # phi's round, then the Executor's
        _one_step(tiny_ckpt, tmp_path, alternate=alternate, lambda_task=0.9, lambda_cons=0.7, lambda_pick=0.2,
                  pick="pickscore-tiny")        # parse_args asks for one; the stand-in above is what scores
        (rewards, weights, *_), _, _ = advantages_of[-1]
        assert weights == {"task": 0.9, "consistency": 0.7, "pick": 0.2, **({} if alternate else {"distill": 1.0})}
        assert rewards["pick"].tolist() == list(range(8))


def test_judge_rollouts_solves_with_both_judges_and_an_unjudged_rollout_is_invalid(monkeypatch):
    """judge_rollouts: solved = task yes and consistency yes; a rollout either judge could not judge is invalid
    (rl.advantages skips it, the log counts it). The judges are stand-ins that read their verdicts off the "video"."""
    yes, no = train.reward.Judgment(True, 1.0), train.reward.Judgment(False, -1.0, "x")
    monkeypatch.setattr(train, "JUDGE", None)
    monkeypatch.setattr(train.reward, "read_video", lambda v: v)
    monkeypatch.setattr(train.reward, "judge_task", lambda r, t: r[0])
    monkeypatch.setattr(train.reward, "judge_consistency", lambda r: r[1])
    out = train.judge_rollouts([(yes, yes), (yes, no), (no, yes), (yes, train.reward.INVALID),
                                (train.reward.INVALID, yes)], ["t"] * 5)
    assert out["solved"][:4].tolist() == [1.0, 0.0, 0.0, 0.0] and out["solved"][4].isnan()
    assert out["invalid"].tolist() == [False, False, False, True, True]
    assert out["task"][:4].tolist() == [1.0, 1.0, -1.0, 1.0] and out["consistency"][3].isnan()


def test_a_judge_that_raises_is_counted_and_its_rollouts_skipped(monkeypatch):
    """judge_rollouts never lets a judge's exception stop the run: the rollout is invalid (NaN score) and its
    judge_errors counts the judges that raised -- the toy judges per video, a VLM judge per batch."""
    yes = train.reward.Judgment(True, 1.0)

    def raises_on(bad):
        def judge(r, *t):
            if r == bad:
                raise RuntimeError("judge down")
            return yes
        return judge

    monkeypatch.setattr(train, "JUDGE", None)
    monkeypatch.setattr(train.reward, "read_video", lambda v: v)
    monkeypatch.setattr(train.reward, "judge_task", raises_on("task fails"))
    monkeypatch.setattr(train.reward, "judge_consistency", raises_on("consistency fails"))
    out = train.judge_rollouts(["fine", "task fails", "consistency fails"], ["t"] * 3)
    assert out["judge_errors"].tolist() == [0, 1, 1] and out["invalid"].tolist() == [False, True, True]
    assert out["task"][0] == 1 and out["task"][1].isnan() and out["task"][2] == 1 and out["consistency"][2].isnan()

    class VLM:                               # a batched judge: one of its two questions raises for the whole batch
        def __init__(self, down):
            self.down = down

        def task_reward(self, videos, tasks):
            if "task" in self.down:
                raise RuntimeError("judge down")
            return [yes] * len(tasks)

        def consistency_reward(self, videos):
            if "consistency" in self.down:
                raise RuntimeError("judge down")
            return [yes] * len(videos)

    for down, errors in (((), 0), (("task",), 1), (("consistency",), 1), (("task", "consistency"), 2)):
        monkeypatch.setattr(train, "JUDGE", VLM(down))
        out = train.judge_rollouts(np.zeros((2, 3, 16, 16, 3), np.uint8), ["t", "t"])
        assert out["judge_errors"].tolist() == [errors] * 2 and out["invalid"].tolist() == [bool(down)] * 2, down
        assert out["task"].isnan().all() == ("task" in down) and out["solved"].isnan().all() == ("task" in down)
        assert out["consistency"].isnan().all() == ("consistency" in down), down


def test_inner_epochs_update_again_on_the_same_rollouts(tiny_ckpt, tmp_path, monkeypatch):
    """--inner_epochs 2: two optimizer steps on one step's rollouts (sampled once)."""
    updates = _spy(monkeypatch, train, "_update")
    for k in (1, 2):
        updates.clear()
        _one_step(tiny_ckpt, tmp_path, trainer="flow-grpo", inner_epochs=k)
        rollouts = [[p.ro for p in parts] for (_, _, _, parts, *_), _, _ in updates]
        assert len(rollouts) == k and all(ro is first for ro, first in zip(rollouts[-1], rollouts[0]))


def test_demonstrator_executor_reads_the_executors_own_weights_under_d(tiny_ckpt, tmp_path):
    """--demonstrator executor (App. A.3's shared weights): at step 1 the LoRA is zero, so the Executor under c_D is
    the base and the run logs what the fixed-Demonstrator run logs; from step 2 on the Demonstrator is the updated
    Executor, and r_distill (Eq. 9) differs. Fails if the flag does not reach Eqs. 9 and 11."""
    logs = {}
    for who in ("base", "executor"):
        d = tmp_path / who
        threads = torch.get_num_threads()
        try:
            train.main([*TINY, "--init", tiny_ckpt, "--steps", "2", "--eval_every", "2", "--demonstrator", who,
                        "--run_dir", str(d)])
        finally:
            torch.set_num_threads(threads)
        logs[who] = [r for r in _metrics(d / "rl.jsonl") if not r.get("eval")]
    base, own = logs["base"], logs["executor"]
    assert base[0] == own[0]
    assert base[1]["r_distill"] != own[1]["r_distill"]


def _dataset(d, seed: int, n: int) -> str:
    """A WorldTasks JSONL file over toy first frames (what world.make_worldtasks writes)."""
    from PIL import Image
    d.mkdir(parents=True, exist_ok=True)
    rows = []
    for i, p in enumerate(train.world.make_pairs(n, seed=seed, error_rate=0.0)):
        Image.fromarray(p.frame0).save(d / f"{seed}_{i}.png")
        rows.append({"image": f"{seed}_{i}.png", "task": p.task.text, "description": p.d_oracle})
    (d / f"{seed}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return str(d / f"{seed}.jsonl")


def test_eval_dataset_is_the_bench_and_must_be_held_out(tiny_ckpt, tmp_path, monkeypatch, capsys):
    """--eval_dataset: every evaluation (the base, the Demonstrator, the Executor, the GIF) samples its first --eval_n
    rows, not the toy bench; a bench row that is also a training row, too few rows, or another stage: exit 2."""
    data, held = _dataset(tmp_path, 11, 4), _dataset(tmp_path, 12, 3)
    rows = [json.loads(line) for line in open(held)][:2]
    prompts, generate = [], train.models.generate
    monkeypatch.setattr(train.models, "generate", lambda m, f, texts, *a, **k: prompts.append(list(texts)) or
                        generate(m, f, texts, *a, **k))
    monkeypatch.setattr(train, "BENCH", None)
    out, threads = tmp_path / "run", torch.get_num_threads()
    try:
        train.main([*TINY, "--init", tiny_ckpt, "--dataset", data, "--eval_dataset", held, "--eval_n", "2",
                    "--steps", "1", "--run_dir", str(out)])
    finally:
        torch.set_num_threads(threads)
    tasks, descs = [r["task"] for r in rows], [r["description"] for r in rows]
    assert prompts[0] == tasks and prompts[1] == descs            # the base given T, the Demonstrator given D
    assert prompts[-3] == tasks and prompts[-2] == descs[:2] and prompts[-1] == tasks    # final bench; the GIF
    assert len(prompts) == 5 and (out / "rollouts_rl.gif").exists()
    for argv, msg in ((["--dataset", data, "--eval_dataset", data], "the bench must be held out"),
                      (["--eval_dataset", held, "--eval_n", 4], "fewer than --eval_n 4"),
                      (["--stage", "distill", "--eval_dataset", held], "--eval_dataset is the rl stage's bench")):
        err = exit_2(train.main, [*TINY, "--init", tiny_ckpt, "--steps", "1", *argv, "--run_dir", tmp_path / "never"],
                     capsys)
        assert msg in err and not (tmp_path / "never").exists(), (argv, err)


def test_video_loss_is_app_a9s_loss_weighted_by_1_minus_t_and_by_the_moving_pixels(shipped):
    """train.video_loss, pretraining's loss (and +SFT's): App. A.9's flow-matching loss under each video's caption,
    each video weighted (1 - t)^--loss_power and each pixel that differs from the first frame --motion_weight times
    the others. One video, so the draws of x_0 and t are known; the shipped base, whose velocity reads the caption."""
    m = shipped
    videos, captions = train.world.pretraining_batch(np.random.default_rng(0), 8)
    i = next(i for i, v in enumerate(videos) if (v[1:] != v[:1]).any() and captions[i])   # a moving, captioned clip
    video, caption = videos[i:i + 1], captions[i:i + 1]

    def loss(power, motion_weight, v=video, cap=caption):
        torch.manual_seed(1)
        with torch.no_grad():
            return train.video_loss(m, v, cap, types.SimpleNamespace(loss_power=power, motion_weight=motion_weight))

    torch.manual_seed(1)
    x_1 = m.encode_video(video)
    x_0, t = torch.randn_like(x_1), torch.rand(1)          # video_loss's draws, in its order
    c = m.condition(video[:, 0], caption)
    with torch.no_grad():
        plain = train.flow.flow_matching_loss(lambda x, tt: m(x, tt, c), x_0, x_1, t)
    assert torch.allclose(loss(0.0, 1.0), plain, rtol=1e-6)
    for power in (1.0, 2.0):
        assert torch.allclose(loss(power, 1.0), (1 - t).clamp(min=m.cfg.min_one_minus_t) ** power * plain, rtol=1e-5)
    assert not torch.allclose(loss(0.0, 1.0, cap=["camera pans up 1 for 2 frames then stops"]), plain, rtol=1e-3)
    moving = loss(0.0, 2.0) - plain                        # the moving pixels' share of the error, counted once more
    assert moving > 0 and torch.allclose(loss(0.0, 10.0), plain + 9 * moving, rtol=1e-5)
    still = np.repeat(video[:, :1], video.shape[1], 1)     # nothing moves: every pixel counts once
    assert torch.equal(loss(0.0, 10.0, v=still), loss(0.0, 1.0, v=still))


def test_pretrain_wires_its_flags_into_the_batches_and_losses_and_saves_the_warmed_up_average(tmp_path, monkeypatch):
    """train.pretrain: batches drawn with --p_goal and without the bench's scenes; the loss is the video loss plus
    --point_weight times the pointing loss (with --point_goal_only); the EMA's decay at step s is
    min(--ema, s / (s + 10)) (a warm-up), and the checkpoint holds that average, not the trained weights."""
    batches, fits, points = (_spy(monkeypatch, owner, n) for owner, n in
                             ((train.world, "pretraining_batch"), (train, "video_loss"), (train, "pointing_loss")))
    decays, trained, averaged, ema_step = [], [], [], train.ema_step

    def spy(ema, params, decay):
        ema, params = list(ema), list(params)
        ema_step(ema, params, decay)
        decays.append(decay)
        trained[:], averaged[:] = [p.detach().clone() for p in params], ema

    monkeypatch.setattr(train, "ema_step", spy)
    out = str(tmp_path / "base.pt")
    train.pretrain(train.parse_args([
        "--stage", "pretrain", "--relate", "--p_goal", "0.5", "--point_weight", "0.1", "--point_goal_only",
        "--pretrain_steps", "3", "--pretrain_batch", "4", "--width", "8", "--log_every", "1", "--ema", "0.2",
        "--threads", "2", "--out", out, "--run_dir", str(tmp_path)]))
    bench_scenes = train.world.bench_scene_keys()
    assert len(batches) == 3 and all(a[4] == 0.5 and a[5] == bench_scenes for a, _, _ in batches)
    log = [json.loads(line) for line in open(tmp_path / "pretrain.jsonl")]
    assert len(log) == len(fits) == len(points) == 3
    for rec, (_, _, fit), (a, _, point) in zip(log, fits, points):
        assert a[4] is True                                                       # goal_only
        assert rec["loss"] == pytest.approx(fit.item() + 0.1 * point.item(), rel=1e-6)
    assert decays == [1 / 11, 2 / 12, 0.2]
    saved = list(train.models.load_checkpoint(out)[0].parameters())
    assert len(saved) == len(averaged) and all(torch.equal(s, e) for s, e in zip(saved, averaged))
    assert not all(torch.equal(s, w) for s, w in zip(saved, trained))
