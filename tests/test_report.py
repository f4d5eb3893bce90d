"""report.py, the reproduction report: its arithmetic over seeds, its denominators, and a --quick run end to end."""
import json
import os
import re
import types

import numpy as np
import pytest
import torch

import bench
import report
import reward
import train
from conftest import exit_2, per_seed, run, table_after

J = reward.Judgment


def _j(task, agent, cons):
    mk = lambda y: reward.INVALID if y is None else J(y, 1.0 if y else -1.0)  # noqa: E731
    return {"task": mk(task), "agent": mk(agent), "consistency": mk(cons)}


def test_denominators_count_discarded_judgments():
    seed0 = bench.score_table([_j(True, True, True), _j(None, True, False), _j(False, None, None)])
    assert seed0["valid"] == {"task": 2, "agent": 2, "consistency": 2, "avg": 1, "solved": 1, "by_agent": 1}
    assert seed0["failures"] == {"task": 1, "agent": 1, "consistency": 1, "avg": 2, "solved": 2, "by_agent": 2}
    assert seed0["task"] == 0.5 and seed0["agent"] == 1.0 and seed0["consistency"] == 0.5
    assert seed0["avg"] == pytest.approx(2 / 3)          # Tab. 1's Avg: the mean of the three columns
    seed1 = bench.score_table([_j(True, False, True), _j(True, True, True)])
    # solved = task and consistency both yes: a task solved by an implausible video does not count
    assert bench.score_table([_j(True, True, False), _j(True, False, True), _j(False, True, True)])["solved"] == 1 / 3
    # by_agent = task and agent both yes: an end state reached with a bystander moving (agent no) does not count
    assert bench.score_table([_j(True, True, False), _j(True, False, True), _j(False, True, True)])["by_agent"] == 1 / 3
    assert bench.score_table([_j(True, None, True), _j(True, True, True)])["valid"]["by_agent"] == 1
    # over seeds: successes and valid judgments add up; the failure rate is over all 5 videos
    assert report.table4_cell([seed0, seed1], "task") == "0.750 (3/4; 20.0%)"
    assert report.table4_cell([seed0, seed1], "agent") == "0.750 (3/4; 20.0%)"
    assert report.table4_cell([seed0, seed1], "avg") == "0.889 (2.7/3; 40.0%)"


def test_consistency_faults_count_videos_per_kind():
    def c(yes, why):
        return {"task": J(True, 1.0), "agent": J(True, 1.0), "consistency": J(yes, 1.0 if yes else -3.0, why)}
    judgments = [c(False, "reshaped blue, reshaped red, teleports red"), c(False, "reshaped red"), c(True, ""),
                 c(False, "VLM"), {**c(True, ""), "consistency": reward.INVALID}]
    # a video counts once per kind however many sprites show it; a VLM's "no" gives no kind
    assert bench.consistency_faults(judgments) == {"reshaped": 2, "teleports": 1}


def test_still_videos_counts_videos_where_nothing_moved():
    rng = np.random.default_rng(0)
    frame0 = rng.integers(0, 256, (4, 1, 8, 8, 3), dtype=np.uint8)
    videos = np.repeat(frame0, 6, axis=1)            # four still videos
    videos[1, 3, 2, 5, 0] = np.uint8((int(frame0[1, 0, 2, 5, 0]) + 17) % 256)  # one pixel, one frame, 17+ levels off
    near = frame0[2, 0, 4, 4, 1]
    videos[2, 5, 4, 4, 1] = near + 16 if near < 128 else near - 16             # 16 levels off: still counts as still
    assert bench.still_videos(videos) == 3
    assert bench.still_videos(videos, level=15) == 2
    assert bench.still_videos(videos[:, :1]) == 4    # a single frame cannot move
    assert bench.moved_pixels(videos, 16).tolist() == [0, 1, 0, 0]   # pixel-frames moved, video by video
    assert bench.moved_pixels(videos, 15).tolist() == [0, 1, 1, 0]
    assert bench.moved_pixels(videos, (16, 15)).tolist() == [[0, 0], [1, 1], [0, 1], [0, 0]]   # one pass, both


def test_mean_and_spread_over_seeds():
    assert bench.mean_sd([1, 2, 3]) == (2.0, 1.0)
    assert bench.mean_sd([0.5]) == (0.5, 0.0)
    assert bench.fmt([0.1, 0.3]) == "0.200 ± 0.141"


def test_pull_is_a_against_y_standardised_within_its_group():
    """bench.pull (the rl step's still_push): mean of A times y standardised within each group, 0 where y is
    constant in its group, so it does not depend on y's scale."""
    A, ids = torch.tensor([1.0, 0.0, 0.5, -0.5]), torch.tensor([0, 0, 1, 1])
    assert bench.pull(A, [3.0, 1.0, 5.0, 5.0], ids) == pytest.approx((1.0 * 1 + 0.0 * -1 + 0 + 0) / 4)
    assert bench.pull(A, [30.0, 10.0, 5.0, 5.0], ids) == pytest.approx(0.25)


def test_subgroup_scores_for_fig7():
    import world
    pairs = world.bench_pairs(0.3)[:40]
    judgments = [_j(i % 2 == 0, i % 3 == 0, True) for i in range(40)]
    fam, types = bench.family_scores(pairs, judgments), bench.agent_type_scores(pairs, judgments)
    assert sum(v for _, v in fam.values()) == 40 and set(fam) <= set(world.FAMILIES)
    no_judgment = [_j(None, True, True)] + judgments[1:]           # a video the task judge could not judge
    assert sum(v for _, v in bench.family_scores(pairs, no_judgment).values()) == 39
    assert set(types) <= {"sprite", "first-person view"} and sum(v for _, v in types.values()) == 40
    fpv = [i for i, p in enumerate(pairs) if p.task.agent == world.FIRST_PERSON]
    assert types["first-person view"] == [sum(i % 3 == 0 for i in fpv), len(fpv)] and fpv   # the agent judgments
    wrong = [i for i, p in enumerate(pairs) if p.error]    # the task score where the toy VLM's D is wrong
    assert bench.vlm_error_scores(pairs, judgments)["D wrong"] == [sum(i % 2 == 0 for i in wrong), len(wrong)]
    assert 0 < len(wrong) < 20
    assert fam["perception"][1] == len(fpv)   # perception tasks are the first-person ones
    kinds = bench.kind_scores(pairs, judgments)   # finer: each kind, edges by side, the same successes
    assert set(kinds) <= {"move_to", "level_with", "centre", *(f"edge ({e})" for e in world.EDGES)}
    assert kinds["centre"] == fam["perception"]
    edges = [kinds[g] for g in kinds if g.startswith("edge")]
    pos, level = fam["positioning"], kinds.get("level_with", [0, 0])   # positioning = edges + level_with
    assert [sum(s for s, _ in edges), sum(v for _, v in edges)] == [pos[0] - level[0], pos[1] - level[1]]
    left = [i for i, p in enumerate(pairs) if p.task.text.endswith("the left edge")]
    assert kinds["edge (left)"] == [sum(i % 2 == 0 for i in left), len(left)] and left



def test_fig7_shows_the_subgroups_over_5_percent_of_the_bench_and_names_the_rest():
    """bench.fig7_lines, the paper's rule for Fig. 7 ("all categories with more than 5% benchmark support"): a
    subgroup's support is its pairs' share of the bench, judged or not (bench.subgroup_sizes); a subgroup at 5% or
    under is not in the figure's list but follows it with its counts and size, so nothing is hidden."""
    from types import SimpleNamespace as NS
    kinds = ["navigation"] * 30 + ["perception"] * 3 + ["vehicle control"] * 2 + ["positioning"] * 5
    agents = ["vehicle"] * 3 + ["human character"] * 37
    pairs = [NS(task=NS(family=f, agent_type=a)) for f, a in zip(kinds, agents)]
    judgments = [_j(None if i == 31 else i % 2 == 0, i < 2, True) for i in range(40)]     # pair 31 not judged
    res = {"n": 40, "families": bench.family_scores(pairs, judgments), "sizes": bench.subgroup_sizes(pairs),
           "agent_types": bench.agent_type_scores(pairs, judgments)}
    assert res["sizes"] == {"families": {"navigation": 30, "perception": 3, "vehicle control": 2, "positioning": 5},
                            "agent_types": {"vehicle": 3, "human character": 37}}
    task, agent = bench.fig7_lines(res)
    shown, rest = task.split("; ")
    assert shown.endswith("navigation 0.500 (15/30), perception 1.000 (2/2), positioning 0.400 (2/5)")
    assert rest.endswith("not shown in the paper's figure: vehicle control 1/2 (2 pairs)")      # 2/40 = 5%: not over
    assert agent.endswith("human character 0.000 (0/37), vehicle 0.667 (2/3)") and "; " not in agent   # 3/40 = 7.5%
    unjudged = [_j(None if 30 <= i < 33 else i % 2 == 0, i < 2, True) for i in range(40)]   # no perception judged
    res["families"] = bench.family_scores(pairs, unjudged)
    assert "perception nan (0/0)" in bench.fig7_lines(res)[0]            # no judgment is not a failure (0.000)


def test_reports_fig7_table_shows_the_subgroups_over_5_percent_and_keeps_the_rest_per_seed():
    """report.fig7_table applies bench.fig7_shown's rule to the report's table, as bench.py's lines do: a subgroup at 5%
    of the bench's pairs or under has no column of means, is named with its size, and keeps its per-seed cells."""
    res = lambda nav, per: {"n": 40, "families": {"navigation": [nav, 38], "perception": [per, 2]},   # noqa: E731
                            "agent_types": {"sprite": [5, 40]},
                            "sizes": {"families": {"navigation": 38, "perception": 2}, "agent_types": {"sprite": 40}}}
    rows = report.fig7_table([0, 1], {"Base (T)": [res(19, 1), res(38, 2)]})
    assert rows[:3] == ["| model | task: navigation | agent: sprite |", "|---|---|---|",
                        "| Base (T) | 0.750 ± 0.354 | 0.125 ± 0.000 |"]
    assert rows[3].endswith("sprite 40. At most 5% of the bench's pairs, so not in the figure or the table above, "
                            "as in the paper: perception (2 pairs).")
    assert rows[-4] == "| model | seed | task: navigation | task: perception | agent: sprite |"
    assert rows[-2:] == ["| Base (T) | 0 | 0.500 (19/38) | 0.500 (1/2) | 0.125 (5/40) |",
                         "| Base (T) | 1 | 1.000 (38/38) | 1.000 (2/2) | 0.125 (5/40) |"]
    assert "At most" not in report.fig7_table([0], {"B": [res(1, 1) | {"n": 39}]})[3]    # 2/39 > 5%: shown
    assert report.fig7_table([0], {"B": [res(1, 1) | {"n": 39}]})[0].count("perception") == 1


def test_per_seed_rows_give_each_seed_its_own_values():
    """report.per_seed_rows: a final evaluation's scores, or a curve's at its end and then its peaks, in the order of
    the seeds they belong to."""
    rec = lambda t, a, c: {"task": t, "agent": a, "consistency": c, "avg": (t + a + c) / 3}  # noqa: E731
    curve = lambda *tasks: [{**rec(t, 0.5, 1.0), "step": i} for i, t in enumerate(tasks)]  # noqa: E731
    assert report.per_seed_rows([3, 7], {"M": [rec(0.1, 0.2, 0.3), rec(0.4, 0.5, 0.6)]},
                                {"R": [curve(0.2, 0.6, 0.4), curve(0.1, 0.3, 0.5)]}) == [
        "| M | 3 | 0.100 | 0.200 | 0.300 | 0.200 | | |", "| M | 7 | 0.400 | 0.500 | 0.600 | 0.500 | | |",
        "| R | 3 | 0.400 | 0.500 | 1.000 | 0.633 | 0.600 | 0.700 |",
        "| R | 7 | 0.500 | 0.500 | 1.000 | 0.667 | 0.500 | 0.667 |"]


def test_subgroup_rows_give_each_seed_its_counts():
    """report.subgroup_rows: Fig. 7's row per (label, seed), task families then agent types, each score with the
    successes and valid judgments it is the ratio of (a subgroup without a valid judgment scores nan, as the bench
    table's scores: no judgment is not a failure)."""
    ev = lambda fam, agent: {"families": fam, "agent_types": agent}  # noqa: E731
    assert report.subgroup_rows([3, 7], {"M": [ev({"nav": [1, 4], "pos": [0, 0]}, {"sprite": [2, 3]}),
                                               ev({"nav": [3, 4], "pos": [2, 5]}, {"sprite": [0, 3]})]}) == [
        "| M | 3 | 0.250 (1/4) | nan (0/0) | 0.667 (2/3) |", "| M | 7 | 0.750 (3/4) | 0.400 (2/5) | 0.000 (0/3) |"]


def test_quick_report_writes_every_file_and_reuses_finished_runs(tiny_ckpt, tmp_path):
    out = tmp_path / "report"
    r = run("report.py", str(out), "--quick", "--checkpoint", tiny_ckpt)
    assert r.returncode == 0, r.stderr[-2000:]
    for f in report.REPORT_FILES:
        assert (out / f).exists() and (out / f).stat().st_size > 100, f
    md = (out / "report.md").read_text()
    for heading in ("Table 1", "Table 4", "Fig. 4 left", "Fig. 4 right", "Fig. 5", "Fig. 7", "Fig. 8", "error rate"):
        assert heading in md, heading
    assert "| Base + SFT (T) |" in md and "| WMSD (T) |" in md and " ± " in md
    # Fig. 4's panels: the task score and the paper's average of the three, read from the runs over both seeds
    dist = [json.load(open(out / "runs" / f"distill_s{s}" / "distill_summary.json")) for s in (0, 1)]
    cells = [bench.fmt(d["variants"]["on"][i][k] for d in dist) for k, i in (("task", -1), ("avg", 0), ("avg", -1))]
    assert f"| on | {bench.fmt(d['variants']['on'][0]['task'] for d in dist)} | {' | '.join(cells)} |" in md
    full = [report.read_run(out / "runs" / f"on_full_s{s}")["evals"] for s in (0, 1)]   # the full objective's row
    assert f"| {report.ON_FULL} | " + " | ".join(bench.fmt(ev[i][k] for ev in full) for k, i in (
        ("task", 0), ("task", -1), ("avg", 0), ("avg", -1), ("consistency", -1))) + " |" in md
    beta = [report.read_run(out / "runs" / f"beta_0.1_s{s}")["evals"] for s in (0, 1)]
    assert (f"| 0.1 | {bench.fmt(max(e['task'] for e in ev) for ev in beta)} | "
            f"{bench.fmt(ev[-1]['task'] for ev in beta)} | {bench.fmt(max(e['avg'] for e in ev) for ev in beta)} | "
            f"{bench.fmt(ev[-1]['avg'] for ev in beta)} |") in md
    seeds = per_seed(md)   # the values behind the means: each model's and run's own row per seed
    assert [seeds[("on_full @end (--lambda_task 0 --lambda_cons 0)", s)][3] for s in (0, 1)] == \
        [f"{ev[-1]['avg']:.3f}" for ev in full]
    assert [seeds[("beta_0.1 @end (--beta_d 0.1)", s)][4] for s in (0, 1)] == \
        [f"{max(e['task'] for e in ev):.3f}" for ev in beta]
    wmsd = next(line for line in md.splitlines() if line.startswith("| WMSD (T) |")).split(" | ")
    for i, k in enumerate(("task", "agent", "consistency", "avg")):   # Table 1's means, from the rows per seed
        assert abs(float(wmsd[1 + i].split(" ± ")[0]) - sum(float(seeds[("WMSD (T)", s)][i]) for s in (0, 1)) / 2) \
            < 1e-3, k
    fig7, fig7_seeds = table_after(md, "## Fig. 7"), per_seed(md, "## Fig. 7")   # its subgroups, seed by seed
    assert set(fig7_seeds) == {(m, s) for m in ("Base (T)", "Demonstrator", "WMSD (T)") for s in (0, 1)}
    for (model, s), cells in fig7_seeds.items():
        counts = [re.fullmatch(r"(\d\.\d{3}) \((\d+)/(\d+)\)", c).groups() for c in cells]
        assert len(counts) == len(fig7[model]) and all(
            float(x) == round(int(k) / max(int(v), 1), 3) for x, k, v in counts), (model, s, cells)
    for model, cells in fig7.items():   # its means, from the rows per seed
        for i, cell in enumerate(cells):
            m = sum(float(fig7_seeds[(model, s)][i].split()[0]) for s in (0, 1)) / 2
            assert abs(float(cell.split(" ± ")[0]) - m) < 1e-3, (model, i, cell)
    # Table 1's 5 rows and WMSD without r_cons, the 5 distill variants' curves, the other experiments' curves, and
    # the Demonstrator at each error rate: a row per seed each
    assert len(seeds) == 2 * (5 + 1 + 5 + len(report.EXPERIMENTS) - 1 + len(report.ERRORS))
    runs = len(report.EXPERIMENTS) * 2
    assert f"0 of {runs} runs already done" in r.stdout and f"[{runs}/{runs}]" in r.stdout
    etas = [float(x) for x in re.findall(r"report: \[\d+/\d+\].*ETA ([0-9.]+) min\)", r.stdout)]
    assert len(etas) == runs and etas[-1] == 0.0 and etas[0] > 0   # a progress line per run, its ETA to the end
    cmd = json.load(open(out / "runs" / "wmsd_s1" / "report_cmd.json"))["cmd"]
    assert cmd[cmd.index("--seed") + 1] == "1" and "--quick" not in cmd
    for s in (0, 1):   # the full objective's row reads its own runs (in the tiny runs its numbers may equal WMSD's)
        log = out / "runs" / f"on_full_s{s}" / "rl.jsonl"
        recs = [json.loads(line) for line in log.read_text().splitlines()]
        for i, r in enumerate(r for r in recs if r.get("eval")):   # the i-th evaluation; the task's peak at i = 1
            r.update(avg=0.9 + i / 1000, task=0.9 if i == 1 else 0.1 + i / 100)
        log.write_text("".join(json.dumps(r) + "\n" for r in recs))
    again = run("report.py", str(out), "--quick", "--checkpoint", tiny_ckpt)
    assert again.returncode == 0 and f"{runs} of {runs} runs already done; running 0" in again.stdout
    md = (out / "report.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith(f"| {report.ON_FULL} |"))
    assert row.split(" | ")[1:5] == ["0.100 ± 0.000", "0.120 ± 0.000", "0.900 ± 0.000", "0.902 ± 0.000"], row
    # the per-seed rows: task, agent, consistency, avg at the end, then the task's and the average's peaks
    on_full = [per_seed(md)[("on_full @end (--lambda_task 0 --lambda_cons 0)", s)] for s in (0, 1)]
    assert [(c[0], c[3], c[4], c[5]) for c in on_full] == [("0.120", "0.902", "0.900", "0.902")] * 2, on_full


def test_a_finished_run_is_reused_only_for_the_same_command_and_base(tmp_path):
    d = str(tmp_path)
    assert not report.finished_run(d, "rl", ["--seed", "0"], "aaaa")                  # nothing there
    json.dump({"cmd": ["--seed", "0"], "base": "aaaa", "minutes": 1.0}, open(tmp_path / "report_cmd.json", "w"))
    assert not report.finished_run(d, "rl", ["--seed", "0"], "aaaa")                  # no summary: it did not finish
    (tmp_path / report.SUMMARY["rl"]).write_text("{}")
    assert report.finished_run(d, "rl", ["--seed", "0"], "aaaa")
    assert not report.finished_run(d, "rl", ["--seed", "1"], "aaaa")                  # other flags
    assert not report.finished_run(d, "rl", ["--seed", "0"], "bbbb")                  # a rebuilt base
    (tmp_path / "ck.pt").write_bytes(b"x")
    assert bench.file_digest(str(tmp_path / "ck.pt")) == "2d711642b726b044"       # sha256(b"x")[:16]


def test_the_reports_runs_start_from_its_base_and_run_again_when_that_base_is_rebuilt(tmp_path, monkeypatch):
    """report.run_experiments with a base (--checkpoint): every train.py run gets --init, and is recorded with the
    base's digest, so a second report runs nothing and a base rebuilt at the same path runs everything again.
    train.py is not run: a stand-in writes the summary a finished run leaves."""
    calls = []

    def train_py(cmd, **kw):
        calls.append(cmd)
        stage, d = cmd[cmd.index("--stage") + 1], cmd[cmd.index("--run_dir") + 1]
        open(os.path.join(d, report.SUMMARY[stage]), "w").write("{}")
        return types.SimpleNamespace(returncode=0)

    monkeypatch.setattr(report.subprocess, "run", train_py)
    base, out = tmp_path / "base.pt", str(tmp_path / "out")
    base.write_bytes(b"a")
    dirs = report.run_experiments(out, [0], "quick", jobs=1, init=str(base))
    assert len(calls) == len(dirs) == len(report.EXPERIMENTS)
    assert all(c[c.index("--init") + 1] == str(base) for c in calls)
    assert all(json.load(open(os.path.join(d, "report_cmd.json")))["base"] == bench.file_digest(str(base))
               for d in dirs.values())
    calls.clear()
    report.run_experiments(out, [0], "quick", jobs=1, init=str(base))
    assert calls == []
    base.write_bytes(b"b")                                   # rebuilt where it was
    report.run_experiments(out, [0], "quick", jobs=1, init=str(base))
    assert len(calls) == len(report.EXPERIMENTS)


def test_each_experiment_sets_what_its_figure_says_it_does():
    """EXPERIMENTS through train.py's own parser: Fig. 5's four runs select the settings fig5_setting names, Fig. 4
    right's beta_d and the error-rate figure's rates are the flags' values, Fig. 8's ablation differs from WMSD in
    r_cons's weight alone, the distill run trains the SFT executors Tab. 1 loads, and Fig. 4 left's full on-policy
    objective is WMSD without the judges' rewards."""
    def parse(name):
        stage, flags = report.EXPERIMENTS[name]
        return train.parse_args(["--stage", stage, *flags])
    settings = {"no_anchor": "RL from the judges alone", "wmsd": "WMSD", "alternate": "WMSD, alternating (Alg. 2)",
                "teacher_rl": "off-policy distillation + RL on the teacher"}
    assert set(report.FIG5) == set(settings)
    assert all(train.fig5_setting(parse(name)) == label for name, label in settings.items())
    assert all(parse(name).beta_d == b for name, b in report.BETAS.items())
    assert all(parse(name).error_rate == e for name, e in report.ERRORS.items())
    wmsd, no_cons = vars(parse("wmsd")), vars(parse("no_cons"))
    assert [k for k in wmsd if wmsd[k] != no_cons[k]] == ["lambda_cons"] and no_cons["lambda_cons"] == 0
    assert {"sft", "paired"} <= set(parse("distill").variant.split(","))
    full = vars(parse("on_full"))   # Fig. 4 left's full on-policy objective: WMSD with r_distill the only reward
    assert [k for k in wmsd if wmsd[k] != full[k]] == ["lambda_task", "lambda_cons"]
    assert full["lambda_task"] == full["lambda_cons"] == 0 < full["lambda_distill"] and full["beta_d"] > 0


def test_a_failed_run_stops_the_report_with_its_logs_tail_and_the_rest_are_kept(tmp_path, monkeypatch, capsys):
    """report.py when one train.py run fails: exit status 1, one error naming the run and the last 8 lines of its
    log; every other run is recorded as finished, so the next report runs only the failed one. train.py is not run:
    a stand-in writes what a run leaves, and fails for one experiment."""
    failing, calls = sorted(report.EXPERIMENTS)[1], []

    def train_py(cmd, stdout=None, **kw):
        stage, d = cmd[cmd.index("--stage") + 1], cmd[cmd.index("--run_dir") + 1]
        calls.append(os.path.basename(d))
        if os.path.basename(d) == f"{failing}_s0":
            stdout.write("".join(f"log line {i}\n" for i in range(1, 11)))
            return types.SimpleNamespace(returncode=3)
        open(os.path.join(d, report.SUMMARY[stage]), "w").write("{}")
        return types.SimpleNamespace(returncode=0)

    monkeypatch.setattr(report.subprocess, "run", train_py)
    out = str(tmp_path / "out")
    err = exit_2(report.main, [out, "--quick", "--seeds", "0", "--jobs", "1"], capsys, code=1)
    assert err.startswith(f"error: run {failing} seed 0 failed (exit 3); "), err
    assert err.split("log.txt ends:\n")[1].split() == [w for i in range(3, 11) for w in ("log", "line", str(i))]
    assert len(calls) == len(report.EXPERIMENTS) and not os.path.exists(os.path.join(out, "report.md"))
    done = {n for n in report.EXPERIMENTS if os.path.isfile(os.path.join(out, "runs", f"{n}_s0", "report_cmd.json"))}
    assert done == set(report.EXPERIMENTS) - {failing}
    calls.clear()
    failed, failing = failing, None
    report.run_experiments(out, [0], "quick", jobs=1)
    assert calls == [f"{failed}_s0"]


def test_ctrl_c_starts_no_more_runs_and_keeps_the_finished(tmp_path, monkeypatch, capsys):
    """Ctrl-C during report.py's runs: the queued runs are not started (before, the pool ran every one of them, up to
    an hour, after the interrupt), the finished ones stay recorded for the next call, exit status 130 and one line.
    A stand-in for train.py, in the second run, sends SIGINT to the main thread and exits 130, as a terminal's Ctrl-C
    does to both. Python's SIGINT handler is set for the test, as in a terminal: a background job (CI's) starts with
    SIGINT ignored, and then no KeyboardInterrupt comes at all."""
    import signal
    import threading
    calls = []

    def train_py(cmd, stdout=None, **kw):
        stage, d = cmd[cmd.index("--stage") + 1], cmd[cmd.index("--run_dir") + 1]
        calls.append(os.path.basename(d))
        if len(calls) == 2:
            open(os.path.join(d, "state.pt"), "w").write("x")                  # what the interrupted run saved
            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)   # Ctrl-C reaches report.py ...
            return types.SimpleNamespace(returncode=130)                         # ... and its train.py
        open(os.path.join(d, report.SUMMARY[stage]), "w").write("{}")
        return types.SimpleNamespace(returncode=0)

    monkeypatch.setattr(report.subprocess, "run", train_py)
    out = tmp_path / "out"
    handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        err = exit_2(report.main, [out, "--quick", "--seeds", "0", "--jobs", "1"], capsys, code=130)
    except KeyboardInterrupt:                           # escaped report.main: pytest would stop, not fail
        pytest.fail("the interrupt escaped report.main as a traceback")
    finally:
        signal.signal(signal.SIGINT, handler)
    assert f"interrupted; the runs that finished are kept in {out / 'runs'}" in err
    assert len(calls) == 2 < len(report.EXPERIMENTS), calls
    assert sum(os.path.isfile(out / "runs" / c / "report_cmd.json") for c in calls) == 1
    # the next report runs the interrupted one again from the start, its state.pt removed (train.py would refuse to
    # start afresh over an unfinished run's state); a run interrupted while report.py was not (its SIGINT ignored, or
    # the run's alone): no more runs start either
    interrupted = out / "runs" / calls[1]
    calls.clear()
    monkeypatch.setattr(report.subprocess, "run", lambda cmd, **kw: calls.append(
        (cmd[cmd.index("--run_dir") + 1], os.listdir(cmd[cmd.index("--run_dir") + 1]))) or types.SimpleNamespace(
        returncode=130))
    assert "failed (exit 130)" in exit_2(report.main, [out, "--quick", "--seeds", "0", "--jobs", "1"], capsys, code=1)
    assert calls == [(str(interrupted), ["log.txt"])], calls


def test_report_bad_input(tmp_path, monkeypatch, capsys):
    r = run("report.py", str(tmp_path), "--quick", "--checkpoint", str(tmp_path / "nope.pt"))
    assert r.returncode == 2 and "does not exist" in r.stderr
    assert not os.listdir(tmp_path)
    r = run("report.py", str(tmp_path), "--jobs", "0")
    assert r.returncode == 2 and "--jobs" in r.stderr
    monkeypatch.setattr(report, "report", lambda *a: pytest.fail("a bad flag let the report start"))
    for argv, msg in ((["--threads", "0"], "--threads must be >= 1"), (["--seeds", "0", "-1"], "--seeds must be >= 0"),
                      (["--seeds", "1", "0", "1"], "--seeds must differ")):   # a seed twice: two runs in one folder
        assert msg in exit_2(report.main, [tmp_path, "--quick", *argv], capsys), argv
    assert not os.listdir(tmp_path)


@pytest.mark.parametrize("bad", ["--variant sft,xyz"])
def test_unknown_variant_names_sft(bad, tmp_path):
    r = run("train.py", "--stage", "distill", *bad.split(), "--run_dir", str(tmp_path))
    assert r.returncode == 2 and "sft" in r.stderr
