"""world.py and the judges of reward.py on simulator-made videos, correct and with hand-made faults; the VLM
score from its logits."""
import json

import numpy as np
import pytest

import reward
import world
from conftest import exit_2
from world import Plan, Scene, Sprite


@pytest.fixture(scope="module")
def bench():
    return world.bench_pairs(0.3)


def _video(scene, plan):
    return world.render(scene, world.simulate(scene, plan))


def test_bench_split_is_fixed_balanced_and_disjoint_from_training(bench):
    assert len(bench) == 200
    again = world.bench_pairs(0.3)
    assert [p.task.text for p in again] == [p.task.text for p in bench]
    assert [p.task.text for p in world.bench_pairs(0.0)] == [p.task.text for p in bench]  # errors don't move tasks
    fams = {f: sum(p.task.family == f for p in bench) for f in world.FAMILIES}
    assert min(fams.values()) >= 40, fams
    keys = world.bench_scene_keys()
    assert all(world.scene_key(p.scene) not in keys for p in world.train_pairs(50, seed=1, error_rate=0.3))
    # drawn from the bench's own seed, training scenes would be the bench's but for the exclusion
    assert not keys & {world.scene_key(p.scene) for p in world.train_pairs(20, world.BENCH_SEED, error_rate=0.0)}
    videos, captions = world.pretraining_batch(np.random.default_rng(0), 64, exclude=keys)
    assert videos.shape == (64, world.F, world.H, world.W, 3)


def test_the_crowded_bench_holds_five_sprites_a_scene_and_the_benchs_tasks(bench):
    """world.crowded_pairs, bench.py --crowded: 200 fixed pairs on scenes of 5 sprites (every scene of the bench,
    of training and of pretraining holds 2-4), with the bench's task kinds and words, each solved by the simulator
    executing its error-free D as the judges see it; the toy VLM errs on them as on the bench."""
    crowded = world.crowded_pairs(0.3)
    assert len(crowded) == 200 and {len(p.scene.sprites) for p in crowded} == {5}
    assert {len(p.scene.sprites) for p in bench} == {2, 3, 4}
    rng = np.random.default_rng(0)
    assert {len(world.random_scene(rng).sprites) for _ in range(200)} == {2, 3, 4}
    assert [p.task.text for p in world.crowded_pairs(0.0)] == [p.task.text for p in crowded]
    assert {p.task.kind for p in crowded} == {p.task.kind for p in bench}
    assert 0.2 < np.mean([bool(p.error) for p in crowded]) < 0.4
    for p in crowded[:40]:
        assert len(world.read_sprites(p.frame0)) == 5
        assert world.parse_task(p.task.text) == p.task
        judged = reward.judge_all(_video(p.scene, p.plan_oracle), p.task.text)
        assert all(judged[k].yes for k in ("task", "agent", "consistency")), p.task.text


def test_crowded_training_scenes_hold_five_sprites_and_never_the_crowded_benchs(monkeypatch):
    """train.py --train_crowded (the toy's Table 2: SFT on the target domain): the training pairs and the sft
    variant's plain videos come from 5-sprite scenes, none of them the crowded bench's; the default draw stays 2-4
    sprites, away from the bench."""
    keys = world.bench_scene_keys(True)
    assert keys == {world.scene_key(p.scene) for p in world.crowded_pairs(0.0)} and keys != world.bench_scene_keys()
    pairs = world.train_pairs(60, seed=1, error_rate=0.3, crowded=True)
    assert {len(p.scene.sprites) for p in pairs} == {5}
    assert not keys & {world.scene_key(p.scene) for p in pairs}
    # drawn from the crowded bench's own seed, they would be its scenes but for the exclusion
    assert not keys & {world.scene_key(p.scene) for p in world.train_pairs(20, world.CROWDED_SEED, 0.0, crowded=True)}
    assert {len(p.scene.sprites) for p in world.train_pairs(60, seed=1, error_rate=0.3)} == {2, 3, 4}
    videos, _ = world.sft_batch(np.random.default_rng(0), 40, crowded=True)
    assert {len(world.read_sprites(v[0])) for v in videos} == {5}
    assert {len(world.read_sprites(v[0])) for v in world.sft_batch(np.random.default_rng(0), 40)[0]} <= {2, 3, 4}
    # a bench's scene that the sft draw comes upon (here the first 20, served first) is skipped
    for crowded, held_out in ((False, world.bench_pairs(0.0)), (True, world.crowded_pairs(0.0))):
        served, draw = iter([p.scene for p in held_out[:20]]), world.random_scene
        monkeypatch.setattr(world, "random_scene", lambda rng, sprites: next(served, None) or draw(rng, sprites))
        videos, _ = world.sft_batch(np.random.default_rng(0), 10, crowded)
        assert not {v[0].tobytes() for v in videos} & {p.frame0.tobytes() for p in held_out}
        monkeypatch.setattr(world, "random_scene", draw)


def test_arrangements_place_a_tasks_sprites_anew_where_it_is_feasible(monkeypatch, capsys):
    """world.arrangements: a pair's sprites at new centres drawn as random_scene draws them, a draw taken unless its
    sprites touch, its scene is one to avoid (or taken already) or T is infeasible there, each reason met here on the
    draws and restated; each new pair's D and plan the error-free ones of T's correct plan there. train.py
    --train_arrangements M: --train_pairs / M tasks of the run's pairs, each on its own scene and M - 1 such places,
    no scene twice nor a bench's; and its refusals."""
    import train
    p = next(p for p in world.bench_pairs(0.0) if p.task.kind == "move_to")

    def draws(seed):     # the scenes arrangements draws from this seed; None where the sprites would touch
        rng = np.random.default_rng(seed)
        while True:
            xy = rng.integers(1, world.W - 1, size=(len(p.scene.sprites), 2))
            yield Scene([Sprite(s.colour, s.shape, int(x), int(y)) for s, (x, y) in zip(p.scene.sprites, xy)],
                        p.scene.background) if world.spaced(xy) else None
    first = next(s for s in draws(5) if s is not None and world.solutions(s, p.task))
    avoid, want, reasons, taken = {world.scene_key(first)}, [], set(), {world.scene_key(first)}
    got = world.arrangements(p, 12, np.random.default_rng(5), taken)
    for s in draws(5):
        why = ("touch" if s is None else "avoided" if world.scene_key(s) in avoid else
               "infeasible" if not world.solutions(s, p.task) else "")
        reasons.add(why)
        if not why:
            avoid.add(world.scene_key(s))
            want.append(s)
        if len(want) == 12:
            break
    assert reasons == {"touch", "avoided", "infeasible", ""}
    assert [q.scene for q in got] == want and taken == avoid      # each place taken, to be avoided from then on
    for q in got:
        plan = world.canonical_solution(world.solutions(q.scene, p.task))
        assert q.task == p.task and q.plan_oracle == q.plan_vlm == plan and not q.error
        assert q.d_vlm == q.d_oracle == world.describe(q.scene, plan)
        assert np.array_equal(q.frame0, _video(q.scene, plan)[0])
        assert reward.judge_all(_video(q.scene, plan), p.task.text)["task"].yes
    with monkeypatch.context() as m:
        m.setattr(world, "solutions", lambda scene, task: [])
        with pytest.raises(ValueError, match="no new place of its sprites where it is feasible in 50 draws"):
            world.arrangements(p, 1, np.random.default_rng(0), set(), tries=50)
    run = ["--stage", "distill", "--train_pairs", "12", "--error_rate", "0", "--seed", "2"]
    pairs = train.toy_pairs(train.parse_args(run + ["--train_arrangements", "4"]))
    tasks = world.train_pairs(3, seed=3, error_rate=0.0)
    assert len(pairs) == 12 and [q.scene for q in pairs[::4]] == [q.scene for q in tasks]
    assert [q.task for q in pairs] == [t.task for t in tasks for _ in range(4)]
    first = world.arrangements(tasks[0], 3, np.random.default_rng([2, 7]),     # drawn from (seed, 7)
                               set(world.bench_scene_keys()) | {world.scene_key(t.scene) for t in tasks})
    assert [q.scene for q in pairs[1:4]] == [q.scene for q in first]
    assert all(q.scene.names() == pairs[i // 4 * 4].scene.names() for i, q in enumerate(pairs))
    keys = [world.scene_key(q.scene) for q in pairs]
    assert len(set(keys)) == 12 and not set(keys) & world.bench_scene_keys()
    assert all(reward.judge_all(_video(q.scene, q.plan_vlm), q.task.text)["task"].yes for q in pairs)
    assert train.toy_pairs(train.parse_args(run)) == world.train_pairs(12, seed=3, error_rate=0.0)
    assert "not a whole number of tasks on --train_arrangements 5" in exit_2(
        train.parse_args, run + ["--train_arrangements", "5"], capsys)
    assert "give --error_rate 0" in exit_2(train.parse_args, run[:4] + ["--train_arrangements", "4"], capsys)
    assert "--train_arrangements must be >= 1" in exit_2(train.parse_args, run + ["--train_arrangements", "0"], capsys)


def test_error_rates_are_laid_over_one_set_of_pairs():
    """make_pairs makes the error-free pairs once and lays each error rate over them. That gives what drawing each
    pair's error inside propose_tasks gives, and a description wrong at one rate stays wrong at every higher one."""
    def direct(n, seed, e):   # the one-pass form: propose_tasks draws the error from the pair's own generator
        rng, pairs = np.random.default_rng(seed), []
        while len(pairs) < n:
            scene = world.random_scene(rng)
            frame0 = world.render(scene, world.simulate(scene, Plan(None)))[0]
            pairs += world.propose_tasks(frame0, rng, 1, e, np.random.default_rng([seed, len(pairs)]))
        return [(task.text, d, err) for _, task, d, _, _, _, err in pairs]

    for e in (0.0, 0.3, 0.7):
        assert [(p.task.text, p.d_vlm, p.error) for p in world.make_pairs(40, 5, e)] == direct(40, 5, e)
    wrong = lambda e: {i for i, p in enumerate(world.make_pairs(40, 5, e)) if p.error}   # noqa: E731
    assert wrong(0.0) == set() and wrong(0.3) and wrong(0.3) <= wrong(0.7)


def test_a_bad_dataset_file_is_one_clear_error(tmp_path):
    """world.load_dataset: a missing file, a row without its description or with an image that is not there, a file
    with no rows -- each one ValueError naming the file (and the line); split_task, which reads each row's task, and
    a task with a blank agent or instruction or without its brackets."""
    p = world.make_pairs(1, seed=0, error_rate=0.0)[0]
    from PIL import Image
    Image.fromarray(p.frame0).save(tmp_path / "f.png")
    good = json.dumps({"image": "f.png", "task": p.task.text, "description": p.d_oracle})
    for rows, msg in (([], "has no rows"),
                      ([good, json.dumps({"image": "f.png", "task": p.task.text})], "line 2: missing or empty description"),
                      ([good, good.replace("f.png", "g.png")], "line 2: image .*g.png' does not exist")):
        (tmp_path / "d.jsonl").write_text("".join(r + "\n" for r in rows))
        with pytest.raises(ValueError, match=msg):
            world.load_dataset(str(tmp_path / "d.jsonl"))
    with pytest.raises(ValueError, match="does not exist"):
        world.load_dataset(str(tmp_path / "missing.jsonl"))
    with pytest.raises(ValueError, match="is a directory, not a JSONL file"):
        world.load_dataset(str(tmp_path))
    for task in ("[ ]: move left", "[red square]:  ", "red square: move left"):
        with pytest.raises(ValueError, match="is not of the form"):
            world.split_task(task)
    (tmp_path / "d.jsonl").write_text("\n" + good + "\n  \n" + good + "\n")     # blank lines are skipped, and counted
    assert [r["line"] for r in world.load_dataset(str(tmp_path / "d.jsonl"))] == [2, 4]


def test_random_scenes_have_sprites_in_view_a_pixel_apart_that_read_back():
    """random_scene's docstring: 2-4 sprites of distinct colours, fully in view, at least one pixel apart -- 3x3
    sprites with centres 4 px apart (Chebyshev), not 3, where they would touch -- and read_sprites finds each."""
    rng = np.random.default_rng(1)
    for _ in range(300):
        scene = world.random_scene(rng)
        xy = np.array([[s.x, s.y] for s in scene.sprites])
        assert 2 <= len(xy) <= 4 and len({s.colour for s in scene.sprites}) == len(xy)
        assert ((xy >= 1) & (xy <= world.W - 2)).all()
        gaps = np.abs(xy[:, None] - xy[None]).max(-1) + 99 * np.eye(len(xy), dtype=int)
        assert gaps.min() >= 4, xy
        frame0 = world.render(scene, world.simulate(scene, Plan(None)))[0]
        assert sorted((s.colour, s.x, s.y) for s in world.read_sprites(frame0)) == sorted(
            (s.colour, s.x, s.y) for s in scene.sprites)


def test_motion_table_is_simulate_and_plan_is_valid_for_every_motion():
    """The planner's vectorised table (world.motion_table) agrees with the one-plan functions it stands in for."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        scene = world.random_scene(rng)
        for mover in [-1, *range(len(scene.sprites))]:
            pos, valid = world.motion_table(scene, mover)
            plans = [Plan(mover, vx, vy, k) for vx, vy, k in world.ALL_MOTIONS]
            assert all((pos[i] == world.simulate(scene, p)).all() for i, p in enumerate(plans))
            assert valid.tolist() == [world.plan_is_valid(scene, p) for p in plans]
            assert 0 < valid.sum() <= len(plans)


def test_solutions_stop_when_they_first_solve_their_task_and_the_vlm_describes_the_soonest():
    """world.solutions as its docstring says, checked on simulate()'s frames: every plan is valid and solves its task
    at its last moving frame k, not at k - 1; a task already solved at frame 0 has none; "level with" moves only
    vertically. No task is relative to its own agent. canonical_solution, the plan the toy VLM describes, arrives
    soonest, then moves along fewer axes."""
    rng, counted = np.random.default_rng(3), {"solved at frame 0": 0, "level_with plans": 0, "plans": 0}
    for _ in range(15):
        scene = world.random_scene(rng)
        frame0_pos = world.simulate(scene, Plan(None))[0]
        for task in world.candidate_tasks(scene):
            assert task.agent != task.target
            sols = world.solutions(scene, task)
            if world._margins(scene, task, frame0_pos) >= 0:
                assert sols == []
                counted["solved at frame 0"] += 1
            for p in sols:
                m = world._margins(scene, task, world.simulate(scene, p))      # (F,): the margin at each frame
                assert world.plan_is_valid(scene, p) and m[p.k] >= 0 > m[p.k - 1], (task, p, m)
                assert task.kind != "level_with" or p.vx == 0, (task, p)
                counted["level_with plans"] += task.kind == "level_with"
                counted["plans"] += 1
            if sols:
                best = world.canonical_solution(sols)
                assert (best.k, abs(best.vx) + abs(best.vy)) == min((p.k, abs(p.vx) + abs(p.vy)) for p in sols)
    assert min(counted.values()) > 0, counted


def test_d_says_the_motion_the_simulator_renders_and_a_valid_plan_never_overlaps():
    """describe's words against the rendered frames (+x is right, +y is down: rows grow downwards), and
    plan_is_valid's 3 px between centres: 3x3 sprites with centres 2 px apart would share a column."""
    scene = Scene([Sprite("red", "square", 5, 8), Sprite("blue", "circle", 12, 8)])
    for plan, d, end in [(Plan(0, 1, -2, 2), "red square moves right 1 up 2 for 2 frames then stops", (7, 4)),
                         (Plan(0, -1, 1, 1), "red square moves left 1 down 1 for 1 frame then stops", (4, 9))]:
        assert world.describe(scene, plan) == d
        red = [s for s in world.read_sprites(_video(scene, plan)[-1]) if s.colour == "red"]
        assert [(s.x, s.y) for s in red] == [end]
    # red moving right 1 a frame towards blue (7 px away): 4 frames leave 3 px, 5 frames leave 2 px
    assert world.plan_is_valid(scene, Plan(0, 1, 0, 4)) and not world.plan_is_valid(scene, Plan(0, 1, 0, 5))


def test_sft_labels_are_short_tasks_the_video_solves_or_trivial_moves():
    """The +SFT baseline's labeller: a derived task must be one the judge says the labelled video solves."""
    rng = np.random.default_rng(0)
    videos, tasks = world.sft_batch(rng, 120)
    trivial = [t for t in tasks if t.split(": ")[1] in ("move left", "move right", "move up", "move down")]
    assert 0.3 < len(trivial) / len(tasks) < 0.9          # many are trivial, as Sec. 4.4 found
    for v, t in zip(videos, tasks):
        if t not in trivial:
            assert reward.judge_task(v, t).yes, t
    assert world.sft_task(Scene([Sprite("red", "square", 4, 4), Sprite("blue", "circle", 12, 4)]), Plan(None), rng) \
        is None
    # a derived task is one the motion solves and frame 0 did not; where none is, the move's dominant direction
    for _ in range(200):
        scene = world.random_scene(rng)
        plan = world.random_plan(scene, rng)
        label = world.sft_task(scene, plan, rng)
        if label is not None and label.split(": ")[1] not in ("move left", "move right", "move up", "move down"):
            pos = world.simulate(scene, plan)
            task = world.parse_task(label)
            assert world._margins(scene, task, pos[-1]) >= 0 > world._margins(scene, task, pos[0]), label
    apart = Scene([Sprite("red", "square", 6, 6), Sprite("blue", "circle", 13, 13)])   # 2 px solve nothing here
    for vx, vy, word in ((1, 0, "right"), (-1, 0, "left"), (0, 1, "down"), (0, -1, "up"), (1, 1, "right")):
        assert world.sft_task(apart, Plan(0, vx, vy, 2), rng) == f"[red square]: move {word}"


def test_pretraining_captions_are_empty_vague_or_detailed_in_their_shares():
    """world.pretraining_batch: an empty caption with probability p_empty, a vague one (who moves, not how) with
    p_vague, else D's detailed form; a still clip says "nothing moves" either way, so the shares are counted on the
    moving clips."""
    _, captions = world.pretraining_batch(np.random.default_rng(5), 400, p_vague=0.3, p_empty=0.2)
    moving = [c for c in captions if c not in ("", "nothing moves")]
    vague = [c for c in moving if " for " not in c]
    assert all(c.endswith(("moves", "pans")) for c in vague)
    assert abs(captions.count("") / 400 - 0.2) < 0.06
    assert abs(len(vague) / len(moving) - 0.3 / 0.8) < 0.08


def test_goal_clips_move_by_a_feasible_tasks_canonical_solution_and_are_captioned_by_its_goal():
    """world.goal_clip: a feasible task of the scene and its canonical solution, which solves it; goal_caption says
    the goal as a captioner would, each kind in its own words."""
    rng, n = np.random.default_rng(0), 0
    for _ in range(20):
        scene = world.random_scene(rng)
        clip = world.goal_clip(scene, rng)
        if clip is not None:
            task, plan = clip
            assert plan == world.canonical_solution(world.solutions(scene, task, {}))
            assert world._margins(scene, task, world.simulate(scene, plan)[-1]) >= 0
            n += 1
    assert n >= 15
    captions = {("move_to", "red square", "blue circle"): "red square moves to the blue circle",
                ("level_with", "red square", "blue circle"): "red square moves level with the blue circle",
                ("edge", "red square", "left"): "red square moves to the left edge",
                ("centre", world.FIRST_PERSON, "blue circle"): "camera pans to the blue circle"}
    for (kind, agent, target), caption in captions.items():
        assert world.goal_caption(world.Task("navigation", kind, agent, target)) == caption


def test_task_format_and_parse_round_trip(bench):
    for p in bench:
        assert p.task.text.startswith("[") and "]: " in p.task.text
        assert world.parse_task(p.task.text) == p.task


def test_instruction_form_carries_the_description_s_information(bench):
    """The positive control's prompt: D's mover and motion, in the task's "[agent]: instruction" form."""
    import models
    tok = models.Tokenizer(world.VOCAB)
    for p in bench:
        form = world.instruction_form(p.d_vlm)
        agent, rest = world.split_task(form)
        words = p.d_vlm.split()
        assert agent == (world.FIRST_PERSON if words[0] == "camera" else " ".join(words[:2]))
        who = 2 if words[0] == "camera" else 3                     # "camera pans" / "red square moves"
        assert rest == "move " + " ".join(words[who:-2])          # D's motion without "then stops"
        assert tok.words(form)                                     # every word is in the toy vocabulary
    assert world.instruction_form("camera pans up 2 for 1 frame then stops") == \
        "[first-person view]: move up 2 for 1 frame"
    with pytest.raises(ValueError, match="not a description"):
        world.instruction_form("nothing moves")


def test_direction_form_drops_only_the_duration(bench):
    """The partial control's prompt: the instruction form without "for k frames" -- who, which way, how fast."""
    import models
    tok = models.Tokenizer(world.VOCAB)
    for p in bench:
        form, full = world.direction_form(p.d_oracle), world.instruction_form(p.d_oracle)
        k = full[len(form):].split()                               # ["for", k, "frame" or "frames"]
        assert full.startswith(form + " for ") and k[2] == ("frame" if k[1] == "1" else "frames") and len(k) == 3
        assert tok.words(form)
    assert world.direction_form("red square moves left 2 up 1 for 3 frames then stops") == \
        "[red square]: move left 2 up 1"
    assert world.direction_form("camera pans down 1 for 1 frame then stops") == "[first-person view]: move down 1"


def test_captions_in_task_words_name_the_same_motion():
    """--p_task_words: a share of pretraining captions says up/down and the camera as T does (top/bottom, first-person
    view); the rest of each caption is as before."""
    import models
    assert world.in_task_words("red square moves right 1 up 1 for 3 frames then stops") == \
        "red square moves right 1 top 1 for 3 frames then stops"
    assert world.in_task_words("camera pans down 1 for 2 frames then stops") == \
        "first-person view pans bottom 1 for 2 frames then stops"
    tok = models.Tokenizer(world.VOCAB)
    plain = world.pretraining_batch(np.random.default_rng(3), 64)                  # the default share: 0
    said = lambda caps, ws: sum(any(w in tok.words(c) for w in ws) for c in caps)  # noqa: E731
    assert said(plain[1], ("top", "bottom", "first-person")) == 0 < said(plain[1], ("up", "down", "camera"))
    _, every = world.pretraining_batch(np.random.default_rng(3), 64, p_task_words=1.0)
    assert said(every, ("up", "down", "camera")) == 0 < said(every, ("top", "bottom", "first-person"))
    _, half = world.pretraining_batch(np.random.default_rng(3), 200, p_task_words=0.5)
    assert said(half, ("up", "down", "camera")) > 0 and said(half, ("top", "bottom", "first-person")) > 0


def test_toy_vlm_error_rate_and_oracle(bench):
    rate = np.mean([p.error != "" for p in bench])
    assert 0.2 < rate < 0.4
    assert all((p.d_vlm == p.d_oracle) == (p.error == "") for p in bench)
    assert all(p.d_vlm == p.d_oracle for p in world.bench_pairs(0.0))


def test_a_frame_without_a_feasible_task_gets_none_proposed():
    """The toy VLM and goal_clip give up, with nothing, on a scene that has no feasible task: a plain background
    (no sprites to read) proposes no task, however many are asked for, and a sprite-less scene has no goal clip.
    A scene with sprites gets its n, each with a plan that solves it."""
    rng = np.random.default_rng(0)
    blank = np.full((world.H, world.W, 3), 20, np.uint8)
    assert world.propose_tasks(blank, rng, n=3) == []
    assert world.goal_clip(world.Scene([]), rng) is None
    scene = world.random_scene(rng)
    frame0 = world.render(scene, world.simulate(scene, world.Plan(None)))[0]
    got = world.propose_tasks(frame0, rng, n=3)
    assert len(got) == 3 and all(plan in world.solutions(s, task) for s, task, _, _, _, plan, _ in got)
    task, plan = world.goal_clip(scene, rng)
    assert plan in world.solutions(scene, task)


def test_executing_the_toy_vlm_s_description_fails_where_it_is_wrong(bench):
    """The simulator executing D: every pair whose D is right is solved, (nearly) none whose D is wrong -- so
    bench.vlm_error_scores splits the bench where a Demonstrator must fail, and the toy VLM's errors are real."""
    import bench as bench_mod
    judgments = [reward.judge_all(_video(p.scene, p.plan_vlm), p.task.text) for p in bench]
    split = bench_mod.vlm_error_scores(bench, judgments)
    n_wrong = sum(p.error != "" for p in bench)
    assert split["D right"] == [len(bench) - n_wrong] * 2
    assert split["D wrong"][1] == n_wrong and split["D wrong"][0] <= 0.1 * n_wrong, split


def test_the_vlm_reads_the_frame_not_the_simulator(bench):
    for p in bench[:50]:
        read = world.read_sprites(p.frame0)
        assert sorted(world.scene_key(world.Scene(read))) == sorted(world.scene_key(p.scene))


def test_judges_pass_correct_simulator_videos(bench):
    res = {k: [] for k in reward.JUDGES}
    for p in bench:
        for k, j in reward.judge_all(_video(p.scene, p.plan_oracle), p.task.text).items():
            res[k].append(j.yes)
            assert (j.score > 0) == j.yes
    for k, v in res.items():
        assert np.mean(v) >= 0.98, (k, np.mean(v))


def test_judges_fail_a_still_video_on_task_and_agent_but_not_consistency(bench):
    res = {k: [] for k in reward.JUDGES}
    for p in bench[:60]:
        for k, j in reward.judge_all(_video(p.scene, Plan(None)), p.task.text).items():
            res[k].append(j.yes)
    assert not any(res["task"]) and not any(res["agent"]) and all(res["consistency"])


SCENE = Scene([Sprite("red", "square", 2, 8), Sprite("blue", "circle", 11, 8), Sprite("green", "cross", 7, 12)])
TASK = "[red square]: move to the blue circle"
GOOD = Plan(0, 1, 0, 5)  # red square from x=2 to x=7: 4 px left of the blue circle


def _agent_and_bystander():
    """GOOD's video with the green cross moving too."""
    return world.render(SCENE, world.simulate(SCENE, GOOD) + world.simulate(SCENE, Plan(2, 0, 1, 2))
                        - world.simulate(SCENE, Plan(None)))


def test_hand_made_scene_correct():
    j = reward.judge_all(_video(SCENE, GOOD), TASK)
    assert j["task"].yes and j["agent"].yes and j["consistency"].yes


def test_teleport_is_caught():
    v = _video(SCENE, GOOD)
    teleport = _video(SCENE, Plan(None))
    teleport[3:] = v[-1]  # the agent jumps 5 px between frames 2 and 3
    teleport[1:3] = v[0]
    j = reward.judge_all(teleport, TASK)
    assert j["task"].yes and not j["consistency"].yes and "teleports red" in j["consistency"].why


def test_duplicate_at_goal_fools_the_task_judge_but_not_consistency():
    still = _video(SCENE, Plan(None))
    goal = _video(SCENE, GOOD)[-1]
    hacked = still.copy()
    hacked[-1] = np.where((goal == world.COLOURS["red"]).all(-1, keepdims=True), goal, still[-1])  # a second red square
    j = reward.judge_all(hacked, TASK)
    assert j["task"].yes, "like a VLM looking at the end state, the task judge sees a red square at the goal"
    assert not j["consistency"].yes and "duplicate red" in j["consistency"].why


def test_wrong_agent_moving_is_caught():
    wrong = _video(SCENE, Plan(2, -1, 0, 2))  # the green cross moves instead
    j = reward.judge_all(wrong, TASK)
    assert not j["agent"].yes and not j["task"].yes and j["consistency"].yes
    assert not reward.judge_agent(_agent_and_bystander(), TASK).yes


def test_training_task_reward_asks_for_the_addressed_agent_alone():
    """Fig. 10 (judge_task_reward): solved by the end AND by the addressed agent alone; Fig. 15 (judge_task) only
    looks at the end state, so it passes a video where a bystander moves too."""
    v = _video(SCENE, GOOD)
    good = reward.judge_task_reward(v, TASK)
    assert good.yes and good.score == min(reward.judge_task(v, TASK).score, reward.judge_agent(v, TASK).score)
    both = _agent_and_bystander()   # the agent solves it while the green cross moves
    assert reward.judge_task(both, TASK).yes
    j = reward.judge_task_reward(both, TASK)
    assert not j.yes and j.score < 0
    wrong = reward.judge_task_reward(_video(SCENE, Plan(2, -1, 0, 2)), TASK)   # only the bystander moves
    assert not wrong.yes
    assert reward.judge_task_reward(np.zeros((3, 5, 5, 3)), TASK).score is None   # malformed: no judgment


def test_vanishing_smear_and_new_object_are_caught():
    v = _video(SCENE, GOOD)
    gone = v.copy()
    gone[4:] = np.where((v[4:] == world.COLOURS["green"]).all(-1, keepdims=True), 20, v[4:])
    assert "vanishes green" in reward.judge_consistency(gone).why
    smear = v.copy()
    smear[3, 5:8, 5:8] = 110
    assert "smear" in reward.judge_consistency(smear).why
    new = v.copy()
    new[2:, 12:15, 1:4] = world.COLOURS["yellow"]
    assert "appears yellow" in reward.judge_consistency(new).why
    # every kind the judge names is one bench.consistency_faults counts
    for video in (gone, smear, new):
        assert {w.split()[0] for w in reward.judge_consistency(video).why.split(", ")} <= set(reward.CONSISTENCY_FAULTS)


def test_reshaped_teleport_by_two_pixels_and_each_fault_costs_three():
    v = _video(SCENE, GOOD)                          # the red square moves 1 px a frame: plausible
    assert reward.judge_consistency(v).yes
    jump = v[[0, 0, 2, 3, 4, 5]]                     # ... 2 px from frame 1 to frame 2 (MAX_STEP 1.6)
    assert reward.judge_consistency(jump).why == "teleports red"
    grown = v.copy()
    grown[3, 4:7, 4:7] = world.COLOURS["red"]        # frame 3: a 3x3 block joins the square, twice its pixels
    j = reward.judge_consistency(grown)
    assert j.why == "reshaped red" and j.score == 3.0 - 3.0 * 1
    both = grown.copy()
    both[2:, 12:15, 1:4] = world.COLOURS["yellow"]
    j = reward.judge_consistency(both)
    assert j.why == "appears yellow, reshaped red" and j.score == 3.0 - 3.0 * 2


def test_a_blob_as_small_away_from_the_border_is_still_tracked():
    """reward._clipped: a blob touching the border with under 0.8 of its frame-0 pixels is a sprite half out of view,
    whose centroid is not the sprite's, so the tracks and the teleport test skip it. Away from the border a blob as
    small is the sprite drawn smaller (within the reshape range), and its jump is still a teleport."""
    jump = _video(SCENE, GOOD)[[0, 0, 2, 3, 4, 5]]  # the red square jumps 2 px from frame 1 to frame 2
    shrunk = jump.copy()
    shrunk[2, 7:10, 3] = SCENE.background           # ... and loses its trailing column there: 6 of 9 pixels
    assert reward.judge_consistency(shrunk).why == "teleports red"
    leaving = _video(SCENE, Plan(0, -1, 0, 3))      # the red square leaves the view: 9, 9, 6, then 3 pixels
    assert reward.judge_consistency(leaving).yes    # cut by the border: neither reshaped nor a teleport


def test_task_margins_on_hand_made_centres():
    """world.task_margin's rules in pixels, > 0 inside; a margin of exactly 0 is a no for the judges."""
    tm = world.task_margin
    assert tm("move_to", "blue circle", np.array([2, 2]), np.array([5, 4])) == 1.0        # Chebyshev 3 <= 4
    assert tm("move_to", "blue circle", np.array([2, 2]), np.array([7, 2])) == -1.0
    assert tm("level_with", "blue circle", np.array([2, 5]), np.array([12, 5.25])) == 0.25   # rows 0.25 apart
    assert tm("level_with", "blue circle", np.array([5, 2]), np.array([5, 7])) == -4.5      # a column, not a row
    for edge, xy in {"left": (0, 7), "right": (15, 7), "top": (7, 0), "bottom": (7, 15)}.items():
        assert tm("edge", edge, np.array(xy), None) == 1.0, edge
        assert tm("edge", edge, np.array([7.5, 7.5]), None) < 0, edge
    assert tm("centre", "blue circle", None, np.array([7.5, 8.5])) == 0.0
    assert tm("centre", "blue circle", None, np.array([9.0, 7.5])) == -0.5
    assert reward._graded(0.0).yes is False and reward._graded(0.0).score < 0
    assert reward._graded(0.01).yes is True and reward._graded(0.01).score > 0


def test_first_person_pan():
    task = "[first-person view]: centre the blue circle"
    pan = _video(SCENE, Plan(-1, 1, 0, 3))  # blue circle from x=11 to x=8
    j = reward.judge_all(pan, task)
    assert j["task"].yes and j["agent"].yes and j["consistency"].yes
    j = reward.judge_all(_video(SCENE, Plan(1, -2, 0, 2)), task)  # the circle walks to the centre by itself
    assert j["task"].yes and not j["agent"].yes


def test_no_judgment_is_none_not_a_crash():
    v = _video(SCENE, GOOD)
    for judge in (reward.judge_task, reward.judge_agent, reward.judge_task_reward):
        assert judge(v, "[yellow square]: move to the blue circle") == reward.INVALID, judge  # agent not in the scene
    assert reward.judge_consistency(v[:, :8]).yes is None                                 # wrong shape
    bad = v.astype(float)
    bad[2, 0, 0, 0] = np.nan
    assert all(j.yes is None for j in reward.judge_all(bad, TASK).values())
    assert reward.judge_task_reward(bad, TASK) == reward.INVALID


def test_a_video_at_a_multiple_of_the_worlds_size_is_judged_as_the_world(bench):
    """A real backend renders the toy world at its own resolution (LTX-2 at 32x32): read_video block-averages a
    video k times the world's 16x16 back to it, so each judge says what it says of the world's own video. Each k x k
    block here is the world's pixel give or take 8 levels in a checkerboard (within [0, 255]), which only the block's
    mean undoes."""
    for p in bench[:24]:
        for plan in (p.plan_oracle, Plan(None)):
            v = _video(p.scene, plan)
            want = reward.judge_all(v, p.task.text)
            for k in (2, 4):
                i, j = np.indices((16 * k, 16 * k))
                up = lambda a: np.repeat(np.repeat(a, k, axis=1), k, axis=2)          # noqa: E731
                amp = up(np.where((v >= 8) & (v <= 247), 8.0, 0.0))
                big = up(v) + amp * np.where((i + j) % 2, 1, -1)[..., None]
                assert np.array_equal(reward.read_video(big).frames, v), (p.task.text, k)
                assert reward.judge_all(big, p.task.text) == want, (p.task.text, k)
    assert reward.read_video(np.zeros((6, 24, 24, 3), np.uint8)) is None     # not a multiple: malformed


def test_vlm_score_is_log_p_yes_minus_log_p_no():
    logits = np.array([0.0, 3.0, 1.0, -2.0])               # ids: 1 = yes, 2 = no
    j = reward.judgment_from_logits(logits, 1, 2)
    lp = logits - np.log(np.exp(logits).sum())
    assert j.yes is True and abs(j.score - (lp[1] - lp[2])) < 1e-9
    j = reward.judgment_from_logits(np.array([0.0, 1.0, 3.0, -2.0]), 1, 2)
    assert j.yes is False and j.score < 0
    assert reward.judgment_from_logits(np.array([5.0, 1.0, 3.0, 0.0]), 1, 2).yes is None      # answered neither
    assert reward.judgment_from_logits(np.array([np.nan, 1.0, 3.0, 0.0]), 1, 2).score is None


def test_world_script_draws_the_pairs_it_prints(tmp_path, capsys):
    """`python world.py`: the first --n bench pairs, a row each, frames 0..5 of the simulator's error-free solution."""
    from PIL import Image
    world.main(["--n", "2", "--out", str(tmp_path / "sub" / "w.png")])
    out = capsys.readouterr().out
    pairs = world.bench_pairs(0.0)[:2]
    assert all(p.task.text in out and p.d_oracle in out for p in pairs), out
    img = np.asarray(Image.open(tmp_path / "sub" / "w.png").convert("RGB"))
    assert img.shape == (2 * world.H * 8, world.F * world.W * 8, 3)
    video = world.render(pairs[1].scene, world.simulate(pairs[1].scene, pairs[1].plan_oracle))
    assert np.array_equal(img[world.H * 8::8, ::8], np.concatenate(list(video), axis=1))    # row 1: pair 1's frames
    for argv, msg in ((["--n", "0"], "--n must lie in 1..200"), (["--out", tmp_path], "is a directory, not a file"),
                      (["--out", tmp_path / "w.gif"], "must end in .png")):
        assert msg in exit_2(world.main, argv, capsys), argv


def test_composition_counts_each_pairs_agent_and_task_type_once():
    """Fig. 3 on the toy: every pair counted once in each panel, a sprite agent by its shape, an edge task by its edge;
    checked against T's own words on the bench, and on hand-made pairs."""
    bench = world.bench_pairs(0.0)
    c = world.composition(bench)
    assert sum(c["agent"].values()) == sum(c["task"].values()) == 200
    texts = [q.task.text for q in bench]
    assert c["task"]["move to"] == sum(": move to the " in x for x in texts)
    assert c["task"]["stop level with"] == sum(": stop level with the " in x for x in texts)
    for edge in world.EDGES:
        assert c["task"][f"go to the {edge} edge"] == sum(x.endswith(f"go to the {edge} edge") for x in texts), edge
    assert c["agent"][world.FIRST_PERSON] == c["task"]["centre"] == sum(q.task.family == "perception" for q in bench)
    for shape in world.SHAPES:
        assert c["agent"][shape] == sum(x.split("]")[0].endswith(" " + shape) for x in texts), shape
    made = [world.Pair(None, task, "", "", None, None) for task in (
        world.Task("navigation", "move_to", "red cross", "blue circle"),
        world.Task("positioning", "edge", "green triangle", "bottom"),
        world.Task("positioning", "level_with", "red cross", "green triangle"),
        world.Task("perception", "centre", world.FIRST_PERSON, "red cross"))]
    c = world.composition(made)
    assert {k: v for k, v in c["agent"].items() if v} == {"cross": 2, "triangle": 1, world.FIRST_PERSON: 1}
    assert {k: v for k, v in c["task"].items() if v} == {"move to": 1, "go to the bottom edge": 1,
                                                          "stop level with": 1, "centre": 1}


def test_world_script_draws_the_composition_it_prints(tmp_path, capsys):
    """`python world.py --composition PNG`: the figure, and the counts of the three splits printed; --n and --out,
    which choose videos, are refused beside it."""
    from PIL import Image
    world.main(["--composition", str(tmp_path / "sub" / "fig3.png")])
    out = capsys.readouterr().out
    assert Image.open(tmp_path / "sub" / "fig3.png").size[0] > 400
    bench = world.composition(world.bench_pairs(0.0))
    row = next(line for line in out.splitlines() if line.strip().startswith("go to the bottom edge"))
    assert int(row.split()[-2]) == bench["task"]["go to the bottom edge"], row        # the bench's column
    for argv, msg in ((["--composition", str(tmp_path / "c.png"), "--n", "2"], "not with --composition"),
                      (["--composition", str(tmp_path / "c.gif")], "must end in .png")):
        assert msg in exit_2(world.main, argv, capsys), argv


def test_world_script_draws_a_datasets_composition(tmp_path, capsys):
    """Fig. 3 for WorldTasks JSONL files (`--composition PNG --dataset A --dataset B`): the agents as T names them,
    the commonest over both files kept and the rest "other", and the task families by task_family's keywords; a
    --dataset without --composition, or a file that is not there, is one clear error."""
    from PIL import Image
    Image.fromarray(world.make_pairs(1, seed=0, error_rate=0.0)[0].frame0).save(tmp_path / "f.png")

    def jsonl(name, tasks):
        (tmp_path / name).write_text("".join(json.dumps({"image": "f.png", "task": t, "description": "d"}) + "\n"
                                             for t in tasks))
        return str(tmp_path / name)

    train = jsonl("train.jsonl", ["[person]: walk to the door", "[Person]: look at the dog",
                                  "[robot arm]: stop next to the table", "[dog]: jump", "[cat]: look at the door"])
    bench = jsonl("bench.jsonl", ["[person]: turn left"])
    c = world.dataset_composition({"train": world.load_dataset(train), "bench": world.load_dataset(bench)}, top=2)
    assert c["train"]["agent"] == {"person": 2, "cat": 1, "other": 2}    # the commonest; cat: the first of a tie
    assert c["bench"]["agent"] == {"person": 1, "cat": 0, "other": 0}
    assert c["train"]["task"] == {"navigation": 1, "positioning": 1, "perception": 2, "other": 1}
    assert c["bench"]["task"] == {"navigation": 0, "positioning": 0, "perception": 1, "other": 0}
    world.main(["--composition", str(tmp_path / "c.png"), "--dataset", train, "--dataset", bench])
    rows = [line.rsplit(None, 2) for line in capsys.readouterr().out.splitlines()[1:5]]      # the agent panel's
    assert {name.strip(): counts for name, *counts in rows} == {"person": ["2", "1"], "robot arm": ["1", "0"],
                                                                "dog": ["1", "0"], "cat": ["1", "0"]}
    assert (tmp_path / "c.png").stat().st_size > 0
    for argv, msg in ((["--dataset", train], "--dataset is read with --composition only"),
                      (["--composition", str(tmp_path / "c.png"), "--dataset", str(tmp_path / "no.jsonl")],
                       "does not exist")):
        assert msg in exit_2(world.main, argv, capsys), argv
