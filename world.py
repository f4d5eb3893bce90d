"""The toy world: 2D moving sprites, its task generator (the toy VLM), and the WorldTasks-toy dataset.

This is the laptop-sized stand-in for the paper's data (Sec. 4.1.1, App. A.6) and for the VLM g of Alg. 1 line 4:

* A scene is 2-4 sprites (distinct colours, each a 3x3 shape) on a plain dark background, seen through a
  16x16 camera; 5 on the crowded bench (crowded_pairs), a test of transfer to scenes no model was trained on.
  A video is F = 6 frames: frame 0 is the observation I, frames 1..5 are generated.
* A motion plan moves one mover -- a sprite, or the camera -- by (vx, vy) in {-1, 0, 1}^2 pixels per frame for
  k in 1..5 frames, then stops. `simulate` + `render` turn (scene, plan) into a uint8 video.
* A detailed description D spells out the plan ("red square moves left 2 up 1 for 3 frames then stops"); the base
  model is pretrained on such captions (Sec. 3: the Demonstrator is conditioned on c_D = (I, D)).
* A short task T says only *what* ("[red square]: move to the blue circle"), in the paper's "[agent]: instruction"
  format (Sec. 4.1.1). Families, as in the paper's breakdown (Fig. 7):
    navigation  -- "[A]: move to the X"           : A ends next to X (centres at most 4 px apart, Chebyshev)
    positioning -- "[A]: stop level with the X"   : A ends on X's row
                   "[A]: go to the left edge"     : A ends touching that edge of the view
    perception  -- "[first-person view]: centre the X" : the camera pans until X is at the centre of the view
* `propose_tasks` plays the VLM: it reads only the first frame (pixels), proposes feasible tasks with a solving
  plan, and writes D for it. Like a real VLM it errs: a fraction `error_rate` of its descriptions are wrong in
  direction, distance or agent. `error_rate=0` is the oracle.

Simplifications: integer pixel motion, one mover per video, no pushing, no occlusion (plans never overlap sprites).

Run `python world.py` to write a PNG strip of a few bench pairs (frame 0 .. 5 of the oracle solution); `--help`
says how many and where. `python world.py --composition PNG` draws the toy's Fig. 3 instead: which agents and kinds
of task the training split and the benches hold (`composition`).
"""
from __future__ import annotations

import collections
import functools
import re
from dataclasses import dataclass, field, replace

import numpy as np

H = W = 16          # view size in pixels
F = 6               # frames per video: frame 0 is the observation, 1..F-1 are generated
MAX_SPEED = 1       # |vx|, |vy| <= MAX_SPEED pixels per frame
CENTRE = (H - 1) / 2  # 7.5: the view centre, in pixel-centre coordinates

COLOURS = {  # name -> RGB; pairwise distances > 150 so a judge can tell them apart by colour alone
    "red": (225, 45, 45), "green": (40, 200, 60), "blue": (60, 100, 240), "yellow": (235, 220, 40),
    "magenta": (215, 60, 215), "cyan": (50, 215, 220), "white": (240, 240, 240),
}
SHAPES = {  # name -> 3x3 mask
    "square": np.ones((3, 3), bool),
    "circle": np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool),
    "cross": np.array([[1, 0, 1], [0, 1, 0], [1, 0, 1]], bool),
    "triangle": np.array([[0, 1, 0], [1, 1, 1], [1, 1, 1]], bool),
}
# centroid of each shape's pixels minus the centre of its 3x3 box, (dx, dy): the judges subtract it from a blob's
# centroid so that a triangle's centre is where its box centre is
SHAPE_OFFSET = {k: (np.nonzero(m)[1].mean() - 1, np.nonzero(m)[0].mean() - 1) for k, m in SHAPES.items()}
EDGES = ("left", "right", "top", "bottom")
FIRST_PERSON = "first-person view"
FAMILIES = ("navigation", "positioning", "perception")
NUMBERS = ("0", "1", "2", "3", "4", "5")
# Every word the prompts of this world can contain: the toy model's word-level tokenizer is built from this list,
# so a prompt with any other word is rejected with a clear error rather than silently mapped to <unk>.
VOCAB = sorted(set(
    list(COLOURS) + list(SHAPES) + list(EDGES) + list(NUMBERS)
    + "[ ] : moves camera pans left right up down for frames frame then stops nothing".split()
    + "first-person view move to the stop level with go edge centre".split()))


@dataclass
class Sprite:
    colour: str
    shape: str
    x: int  # centre column in view coordinates at frame 0
    y: int  # centre row

    @property
    def name(self) -> str:
        return f"{self.colour} {self.shape}"


@dataclass
class Scene:
    sprites: list[Sprite]
    background: int = 20  # grey level of the plain background

    def names(self) -> list[str]:
        return [s.name for s in self.sprites]


@dataclass(frozen=True)
class Plan:
    """One mover (a sprite index, or -1 for the camera, or None for a still video) moves by (vx, vy) per frame
    during frames 1..k, then stays."""
    mover: int | None
    vx: int = 0
    vy: int = 0
    k: int = 0


@dataclass
class Task:
    family: str         # one of FAMILIES
    kind: str           # move_to | level_with | edge | centre
    agent: str          # sprite name or FIRST_PERSON
    target: str         # sprite name, or an edge name for kind == "edge"

    @property
    def text(self) -> str:
        phrase = {"move_to": "move to the {}", "level_with": "stop level with the {}",
                  "edge": "go to the {} edge", "centre": "centre the {}"}[self.kind].format(self.target)
        return f"[{self.agent}]: {phrase}"


@dataclass
class Pair:
    """One WorldTasks-toy example: the observation, the task T, the toy VLM's description D (maybe wrong),
    the error-free description, and the plan each describes."""
    scene: Scene
    task: Task
    d_vlm: str
    d_oracle: str
    plan_vlm: Plan
    plan_oracle: Plan
    error: str = ""     # "" | direction | distance | agent
    frame0: np.ndarray = field(default=None, repr=False)  # (H, W, 3) uint8


# ----------------------------------------------------------------------------------------------------------------
# simulation and rendering
# ----------------------------------------------------------------------------------------------------------------

def simulate(scene: Scene, plan: Plan) -> np.ndarray:
    """Sprite centres in view coordinates for every frame: (F, n_sprites, 2) int, [..., 0] = x, [..., 1] = y.
    A camera pan by (vx, vy) shifts every sprite by (-vx, -vy) in the view."""
    pos = np.array([[s.x, s.y] for s in scene.sprites])[None].repeat(F, 0)
    if plan.mover is None or plan.k == 0:
        return pos
    steps = np.minimum(np.arange(F), plan.k)[:, None] * np.array([plan.vx, plan.vy])  # (F, 2)
    if plan.mover == -1:
        return pos - steps[:, None, :]
    pos[:, plan.mover] += steps
    return pos


def render(scene: Scene, positions: np.ndarray) -> np.ndarray:
    """Draw sprites at `positions` (F, n, 2) into a uint8 video (F, H, W, 3); sprites leaving the view are clipped."""
    video = np.full((len(positions), H, W, 3), scene.background, np.uint8)
    for f, frame_pos in enumerate(positions):
        for s, (cx, cy) in zip(scene.sprites, frame_pos):
            ys, xs = np.nonzero(SHAPES[s.shape])
            ys, xs = ys + cy - 1, xs + cx - 1
            keep = (ys >= 0) & (ys < H) & (xs >= 0) & (xs < W)
            video[f, ys[keep], xs[keep]] = COLOURS[s.colour]
    return video


def plan_is_valid(scene: Scene, plan: Plan) -> bool:
    """A moving sprite stays fully in view and never overlaps another sprite (so nothing is ever occluded)."""
    if plan.mover is None or plan.mover == -1:
        return True
    return bool(_stays_clear(simulate(scene, plan), plan.mover))


def _stays_clear(pos: np.ndarray, mover: int) -> np.ndarray:
    """plan_is_valid's rule on sprite centres pos (..., F, n, 2) with sprite `mover` moving: its 3x3 box stays fully
    in view, and its centre keeps >= 3 px (Chebyshev) from every other sprite's in every frame. -> (...) bool."""
    p = pos[..., mover, :]                                                # (..., F, 2)
    inside = (p.min((-2, -1)) >= 1) & (p.max((-2, -1)) <= W - 2)
    others = np.delete(pos, mover, axis=-2)                               # (..., F, n - 1, 2)
    return inside & (np.abs(others - p[..., None, :]).max(-1) >= 3).all((-2, -1))


# ----------------------------------------------------------------------------------------------------------------
# language: descriptions D, tasks T
# ----------------------------------------------------------------------------------------------------------------

def describe(scene: Scene, plan: Plan) -> str:
    """The detailed description D of a plan, e.g. "camera pans right 1 down 2 for 3 frames then stops"."""
    if plan.mover is None or plan.k == 0:
        return "nothing moves"
    who = "camera pans" if plan.mover == -1 else f"{scene.sprites[plan.mover].name} moves"
    parts = []
    if plan.vx:
        parts.append(f"{'right' if plan.vx > 0 else 'left'} {abs(plan.vx)}")
    if plan.vy:
        parts.append(f"{'down' if plan.vy > 0 else 'up'} {abs(plan.vy)}")
    return f"{who} {' '.join(parts)} for {plan.k} {'frame' if plan.k == 1 else 'frames'} then stops"


def vague_caption(scene: Scene, plan: Plan) -> str:
    """A caption that says who moves but not how -- the kind of short caption real video data is full of."""
    if plan.mover is None or plan.k == 0:
        return "nothing moves"
    return "camera pans" if plan.mover == -1 else f"{scene.sprites[plan.mover].name} moves"


def instruction_form(d: str) -> str:
    """A description D rewritten in the task's "[agent]: instruction" form, e.g. "red square moves left 2 up 1
    for 3 frames then stops" -> "[red square]: move left 2 up 1 for 3 frames", "camera pans right 1 for 2 frames
    then stops" -> "[first-person view]: move right 1 for 2 frames". The same information as D (errors included) in
    a format the base never saw in pretraining: the Executor's prompt in docs/results.md's positive control
    (train.py --executor_prompt instruction), where c_E carries what c_D carries and only the form differs."""
    m = re.fullmatch(r"(camera pans|(?P<agent>\w+ \w+) moves) (?P<motion>.+?)( then stops)?", d.strip())
    if not m:
        raise ValueError(f"{d!r} is not a description of a motion (world.describe)")
    return f"[{m['agent'] or FIRST_PERSON}]: move {m['motion']}"


def direction_form(d: str) -> str:
    """instruction_form without the duration: "red square moves left 2 up 1 for 3 frames then stops" ->
    "[red square]: move left 2 up 1". Who moves, which way and how fast, not for how long: part of D's decision.
    The Executor's prompt in docs/results.md's partial control (train.py --executor_prompt oracle_direction), between T
    (none of the motion) and the second control (all of it)."""
    return re.sub(r" for \d+ frames?$", "", instruction_form(d))


_TASK_RE = re.compile(r"^\[(?P<agent>[^\]]+)\]:\s*(?P<rest>.+)$")


def parse_task(text: str) -> Task:
    """Parse "[agent]: instruction" back into a Task. Raises ValueError naming the problem for anything else."""
    agent, rest = split_task(text.lower())
    names = {f"{c} {s}" for c in COLOURS for s in SHAPES}
    if agent != FIRST_PERSON and agent not in names:
        raise ValueError(f"unknown agent {agent!r} in task {text!r}; agents are '<colour> <shape>' with colour in "
                         f"{sorted(COLOURS)} and shape in {sorted(SHAPES)}, or '{FIRST_PERSON}'")
    patterns = [("navigation", "move_to", r"move to the (.+)"), ("positioning", "level_with", r"stop level with the (.+)"),
                ("positioning", "edge", r"go to the (\w+) edge"), ("perception", "centre", r"centre the (.+)")]
    for family, kind, pat in patterns:
        mm = re.fullmatch(pat, rest)
        if mm:
            target = mm[1]
            if (kind == "edge" and target not in EDGES) or (kind != "edge" and target not in names):
                raise ValueError(f"unknown target {target!r} in task {text!r}")
            if (kind == "centre") != (agent == FIRST_PERSON):
                raise ValueError(f"task {text!r}: 'centre the X' is for [{FIRST_PERSON}] and only that")
            return Task(family, kind, agent, target)
    raise ValueError(f"unknown instruction {rest!r} in task {text!r}; known: 'move to the X', 'stop level with "
                     f"the X', 'go to the <left|right|top|bottom> edge', 'centre the X'")


# ----------------------------------------------------------------------------------------------------------------
# reading frames (shared by the toy VLM and the judges in reward.py: both see pixels, never simulator state)
# ----------------------------------------------------------------------------------------------------------------

COLOUR_TOL = 90.0  # max RGB distance for a pixel to count as a palette colour


@dataclass
class Blob:
    cx: float            # centroid column
    cy: float            # centroid row
    size: int            # pixels
    touches_border: bool
    box: tuple           # (x_min, y_min, x_max, y_max)


def colour_masks(frames: np.ndarray) -> dict[str, np.ndarray]:
    """(..., H, W, 3) uint8 or float in [0, 255] -> {colour: bool mask (..., H, W)} by distance to the palette."""
    fr = frames.astype(np.float32)
    return {c: np.linalg.norm(fr - np.array(rgb, np.float32), axis=-1) < COLOUR_TOL for c, rgb in COLOURS.items()}


def blobs(mask: np.ndarray) -> list[Blob]:
    """8-connected components of a (H, W) bool mask, largest first."""
    seen = np.zeros_like(mask)
    out = []
    for y0, x0 in zip(*np.nonzero(mask)):
        if seen[y0, x0]:
            continue
        stack, pix = [(y0, x0)], []
        seen[y0, x0] = True
        while stack:
            y, x = stack.pop()
            pix.append((y, x))
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    yy, xx = y + dy, x + dx
                    if 0 <= yy < H and 0 <= xx < W and mask[yy, xx] and not seen[yy, xx]:
                        seen[yy, xx] = True
                        stack.append((yy, xx))
        p = np.array(pix)
        out.append(Blob(float(p[:, 1].mean()), float(p[:, 0].mean()), len(p),
                        bool((p == 0).any() or (p[:, 0] == H - 1).any() or (p[:, 1] == W - 1).any()),
                        (int(p[:, 1].min()), int(p[:, 0].min()), int(p[:, 1].max()), int(p[:, 0].max()))))
    return sorted(out, key=lambda b: -b.size)


def read_sprites(frame: np.ndarray) -> list[Sprite]:
    """Find the sprites of a clean first frame (H, W, 3): one per palette colour with a blob of >= 4 pixels.
    The centre is the centre of the blob's bounding box; the shape is read off the 3x3 mask around it."""
    found = []
    for colour, mask in colour_masks(frame).items():
        bs = blobs(mask)
        if not bs or bs[0].size < 4:
            continue
        x0, y0, x1, y1 = bs[0].box
        # the box's centre, not the pixel mean: a triangle's pixel mean lies 2/7 row below it (SHAPE_OFFSET)
        cx, cy = (x0 + x1) // 2, (y0 + y1) // 2
        patch = np.zeros((3, 3), bool)
        for dy in range(3):
            for dx in range(3):
                yy, xx = cy - 1 + dy, cx - 1 + dx
                patch[dy, dx] = 0 <= yy < H and 0 <= xx < W and mask[yy, xx]
        shape = max(SHAPES, key=lambda s: (SHAPES[s] == patch).sum())
        found.append(Sprite(colour, shape, cx, cy))
    return found


# ----------------------------------------------------------------------------------------------------------------
# the toy VLM: tasks and descriptions from a first frame (Alg. 1 line 4, Sec. 4.1.1)
# ----------------------------------------------------------------------------------------------------------------

ALL_MOTIONS = [(vx, vy, k) for vx in range(-MAX_SPEED, MAX_SPEED + 1) for vy in range(-MAX_SPEED, MAX_SPEED + 1)
               for k in range(1, F) if (vx, vy) != (0, 0)]


def task_margin(kind: str, target: str, agent_xy, target_xy):
    """How far inside (> 0) or outside (< 0) the end-state rule of a task the final centres are, in pixels.
      move_to    : Chebyshev distance between agent and target centres <= 4 (side by side, 0-1 px gap)
      level_with : |y_agent - y_target| <= 0.5 (same row)
      edge       : the agent's 3x3 box touches that edge (centre x <= 1, etc.)
      centre     : the target centre within 1 px of the view centre (7.5, 7.5) on both axes
    Centres are arrays (..., 2) = (x, y); the margin has shape (...). The planner needs margin >= 0 on integer
    centres; the judges (reward.py) apply the same rule to centres read from generated frames, with a small slack
    for sub-pixel blur."""
    if kind == "centre":
        return 1.0 - np.abs(np.asarray(target_xy, float) - CENTRE).max(-1)
    a = np.asarray(agent_xy, float)
    if kind == "move_to":
        return 4.0 - np.abs(a - np.asarray(target_xy, float)).max(-1)
    if kind == "level_with":
        return 0.5 - np.abs(a[..., 1] - np.asarray(target_xy, float)[..., 1])
    return {"left": 1.0 - a[..., 0], "right": a[..., 0] - (W - 2), "top": 1.0 - a[..., 1],
            "bottom": a[..., 1] - (H - 2)}[target]


def _margins(scene: Scene, task: Task, pos: np.ndarray) -> np.ndarray:
    """task_margin on sprite centres pos (..., n, 2) -> (...)."""
    names = scene.names()
    tgt = pos[..., names.index(task.target), :] if task.kind != "edge" else None
    agent = pos[..., names.index(task.agent), :] if task.kind != "centre" else None
    return task_margin(task.kind, task.target, agent, tgt)


def candidate_tasks(scene: Scene) -> list[Task]:
    names = scene.names()
    tasks = []
    for a in names:
        for t in names:
            if t != a:
                tasks += [Task("navigation", "move_to", a, t), Task("positioning", "level_with", a, t)]
        tasks += [Task("positioning", "edge", a, e) for e in EDGES]
    tasks += [Task("perception", "centre", FIRST_PERSON, t) for t in names]
    return tasks


_MOTIONS = np.array(ALL_MOTIONS)  # (M, 3): vx, vy, k


def motion_table(scene: Scene, mover: int) -> tuple[np.ndarray, np.ndarray]:
    """simulate() and plan_is_valid() for every motion in ALL_MOTIONS of one mover at once: positions (M, F, n, 2)
    and valid (M,). It depends only on (scene, mover), so the candidate tasks of a scene share it."""
    pos = np.array([[s.x, s.y] for s in scene.sprites])
    steps = np.minimum(np.arange(F)[None], _MOTIONS[:, 2:3])[..., None] * _MOTIONS[:, None, :2]  # (M, F, 2)
    out = np.broadcast_to(pos, (len(_MOTIONS), F, *pos.shape)).copy()
    if mover == -1:
        return out - steps[:, :, None], np.ones(len(_MOTIONS), bool)
    out[:, :, mover] += steps
    return out, _stays_clear(out, mover)


def solutions(scene: Scene, task: Task, tables: dict | None = None) -> list[Plan]:
    """All constant-velocity plans that solve `task`, are valid, and stop exactly when they solve it (they are not
    solved one frame earlier). Empty if the task is already solved at frame 0. `tables`: a dict of motion_table
    results by mover, filled as needed (pass one dict for all tasks of a scene to compute each table once)."""
    mover = -1 if task.agent == FIRST_PERSON else scene.names().index(task.agent)
    tables = {} if tables is None else tables
    if mover not in tables:
        tables[mover] = motion_table(scene, mover)
    pos, valid = tables[mover]                                            # (M, F, n, 2), (M,)
    margins = _margins(scene, task, pos)                                  # (M, F)
    if margins[0, 0] >= 0:
        return []
    k = _MOTIONS[:, 2]
    ok = (margins[np.arange(len(k)), k] >= 0) & (margins[np.arange(len(k)), k - 1] < 0) & valid
    if task.kind == "level_with":
        ok &= _MOTIONS[:, 0] == 0  # "stop level with": a vertical move, as a person would read it
    return [Plan(mover, int(vx), int(vy), int(kk)) for vx, vy, kk in _MOTIONS[ok]]


def canonical_solution(sols: list[Plan]) -> Plan:
    """The one plan the toy VLM describes for a task: the one arriving soonest, then the one moving along fewer
    axes, then a fixed order -- a function of (I, T), as each (I, T) of the paper's dataset has one D."""
    return min(sols, key=lambda p: (p.k, abs(p.vx) + abs(p.vy), p.vx, p.vy))


def corrupt(scene: Scene, plan: Plan, rng: np.random.Generator) -> tuple[Plan, str]:
    """A plausible VLM mistake: wrong direction, wrong distance, or wrong agent, as (a valid, different plan, its
    kind). If 50 draws find none (not once in 12,000 corruptions of training pairs), the plan itself and kind "":
    a right D, and counted as one."""
    n = len(scene.sprites)
    for _ in range(50):
        kind = rng.choice(["direction", "distance", "agent"])
        if kind == "direction":
            vx, vy = [(-plan.vx, plan.vy), (plan.vx, -plan.vy), (plan.vy, plan.vx), (-plan.vx, -plan.vy)][rng.integers(4)]
            new = Plan(plan.mover, vx, vy, plan.k)
        elif kind == "distance":
            new = Plan(plan.mover, plan.vx, plan.vy, int(rng.integers(1, F)))
        else:
            movers = [m for m in [-1, *range(n)] if m != plan.mover]
            new = Plan(int(rng.choice(movers)), plan.vx, plan.vy, plan.k)
        if new != plan and plan_is_valid(scene, new) and (new.vx, new.vy) != (0, 0):
            return new, str(kind)
    return plan, ""


def vlm_mistake(scene: Scene, plan: Plan, error_rate: float, err_rng: np.random.Generator) -> tuple[Plan, str]:
    """The plan the toy VLM describes for the solution `plan`: with probability `error_rate` a corrupted one
    (corrupt), else `plan` itself. Returns (plan, error kind or "")."""
    return corrupt(scene, plan, err_rng) if err_rng.random() < error_rate else (plan, "")


def propose_tasks(frame0: np.ndarray, rng: np.random.Generator, n: int = 1, error_rate: float = 0.0,
                  err_rng: np.random.Generator | None = None):
    """The toy VLM g(I) of Alg. 1 line 4: read the first frame, propose up to `n` feasible tasks (one family drawn
    uniformly among those feasible here, then a task), describe its canonical_solution. For each, return
    (scene, task, D, D_oracle, plan, plan_oracle, error). With probability `error_rate` D describes a corrupted
    plan. Errors are drawn from `err_rng` (default: rng) so that the tasks do not depend on the error rate, and a
    description wrong at one error rate stays wrong at every higher one."""
    err_rng = err_rng or rng
    scene = Scene(read_sprites(frame0), background=int(np.median(frame0)))
    by_family: dict[str, list[tuple[Task, list[Plan]]]] = {}
    tables: dict = {}
    for task in candidate_tasks(scene):
        sols = solutions(scene, task, tables)
        if sols:
            by_family.setdefault(task.family, []).append((task, sols))
    out = []
    for _ in range(n):
        if not by_family:
            break
        fam = sorted(by_family)[rng.integers(len(by_family))]
        task, sols = by_family[fam][rng.integers(len(by_family[fam]))]
        plan = canonical_solution(sols)
        plan_vlm, err = vlm_mistake(scene, plan, error_rate, err_rng)
        out.append((scene, task, describe(scene, plan_vlm), describe(scene, plan), plan_vlm, plan, err))
    return out


# ----------------------------------------------------------------------------------------------------------------
# scenes and the WorldTasks-toy dataset
# ----------------------------------------------------------------------------------------------------------------

SPRITES = (2, 4)           # the fewest and most sprites of a scene: pretraining, training and the bench
CROWDED_SPRITES = (5, 5)   # the crowded bench's scenes (crowded_pairs): more sprites than any scene the models saw


def random_scene(rng: np.random.Generator, sprites: tuple[int, int] = SPRITES) -> Scene:
    """sprites[0] to sprites[1] sprites (2-4 unless told) with distinct colours, fully in view, at least one pixel
    apart."""
    n = int(rng.integers(sprites[0], sprites[1] + 1))
    colours = rng.choice(list(COLOURS), n, replace=False)
    while True:
        xy = rng.integers(1, W - 1, size=(n, 2))
        if spaced(xy):
            break
    return Scene([Sprite(str(c), str(rng.choice(list(SHAPES))), int(x), int(y)) for c, (x, y) in zip(colours, xy)],
                 background=int(rng.integers(0, 41)))


def spaced(xy: np.ndarray) -> bool:
    """random_scene's rule for sprite centres xy (n, 2): every two at least 4 px apart (Chebyshev), one pixel between
    their 3x3 boxes."""
    n = len(xy)
    return bool((np.abs(xy[:, None] - xy[None]).max(-1) + np.eye(n, dtype=int) * 99).min() >= 4)


def new_place(scene: Scene, rng: np.random.Generator) -> Scene | None:
    """The scene's sprites (colours, shapes, background kept) at centres drawn as random_scene draws them; None where
    two would touch (not spaced). world.arrangements and bench.moved_pairs draw their new places with it."""
    xy = rng.integers(1, W - 1, size=(len(scene.sprites), 2))
    if not spaced(xy):
        return None
    return Scene([Sprite(s.colour, s.shape, int(x), int(y)) for s, (x, y) in zip(scene.sprites, xy)], scene.background)


def scene_key(scene: Scene) -> tuple:
    return tuple(sorted((s.colour, s.shape, s.x, s.y) for s in scene.sprites))


BENCH_SEED = 2606_12072


def make_pairs(n: int, seed: int, error_rate: float, exclude: set | None = None,
               sprites: tuple[int, int] = SPRITES) -> list[Pair]:
    """n task pairs, each on its own random scene of `sprites` sprites (random_scene; scenes in `exclude` are
    skipped). Pair i's description is wrong with probability `error_rate`, drawn from its own generator (seed, i), so
    the scenes and tasks do not depend on the error rate and a description wrong at one rate stays wrong at every
    higher one. The error-free pairs are made once per (n, seed, exclude, sprites) and each error rate is laid over
    them: a run reads the bench at its error rate and the bench's scenes (error rate 0) without making the 200
    scenes twice."""
    out = []
    for i, p in enumerate(_error_free_pairs(n, seed, frozenset(exclude) if exclude else None, tuple(sprites))):
        plan_vlm, err = vlm_mistake(p.scene, p.plan_oracle, error_rate, np.random.default_rng([seed, i]))
        if err:
            p = replace(p, d_vlm=describe(p.scene, plan_vlm), plan_vlm=plan_vlm, error=err)
        out.append(p)
    return out


@functools.lru_cache(maxsize=8)
def _error_free_pairs(n: int, seed: int, exclude: frozenset | None, sprites: tuple[int, int]) -> tuple:
    rng = np.random.default_rng(seed)
    pairs = []
    while len(pairs) < n:
        scene = random_scene(rng, sprites)
        if exclude and scene_key(scene) in exclude:
            continue
        frame0 = render(scene, simulate(scene, Plan(None)))[0]
        # error rate 0; a generator of its own takes propose_tasks' error draw, so `rng` draws what it always did
        proposals = propose_tasks(frame0, rng, 1, 0.0, np.random.default_rng([seed, len(pairs)]))
        for sc, task, d, d_or, p, p_or, err in proposals:
            pairs.append(Pair(sc, task, d, d_or, p, p_or, err, frame0))
    return tuple(pairs)


def bench_pairs(error_rate: float, n: int = 200) -> list[Pair]:
    """The fixed WorldTasks-toy bench split (Sec. 4.1.2): 200 pairs on 200 scenes, from a fixed seed.
    The scenes and tasks do not depend on `error_rate`; only which descriptions are corrupted does."""
    return list(_fixed_pairs(n, BENCH_SEED, float(error_rate), SPRITES))


@functools.lru_cache(maxsize=16)
def _fixed_pairs(n: int, seed: int, error_rate: float, sprites: tuple[int, int]) -> tuple:
    """make_pairs of a fixed bench (bench_pairs, crowded_pairs), made once per argument set: every evaluation of a
    run reads the same pairs."""
    return tuple(make_pairs(n, seed, error_rate, sprites=sprites))


@functools.lru_cache(maxsize=2)
def bench_scene_keys(crowded: bool = False) -> frozenset:
    """The scenes of the bench (or, crowded=True, of the crowded bench): what training scenes must not be."""
    return frozenset(scene_key(p.scene) for p in (crowded_pairs if crowded else bench_pairs)(0.0))


CROWDED_SEED = 2606_12073


def crowded_pairs(error_rate: float, n: int = 200) -> list[Pair]:
    """An out-of-distribution bench (bench.py --crowded), the toy's counterpart of the paper's transfer tests
    (Sec. 4.7's DreamGen, App. A.5's VBVR): 200 pairs made as the bench's are, from their own seed, on scenes of
    CROWDED_SPRITES sprites, where every scene the models pretrain and train on, and the bench's, holds 2-4. The
    tasks and their words are the bench's kinds; only the scenes are new, and more crowded. Made once per
    (error_rate, n), as the bench is: train.py --eval_crowded reads it at every evaluation."""
    return list(_fixed_pairs(n, CROWDED_SEED, float(error_rate), CROWDED_SPRITES))


def train_pairs(n: int, seed: int, error_rate: float, crowded: bool = False) -> list[Pair]:
    """Training pairs on scenes disjoint from the bench split; crowded=True (train.py --train_crowded): on scenes of
    CROWDED_SPRITES sprites disjoint from the crowded bench's, the toy's counterpart of Table 2's SFT on the target
    domain's own data."""
    return make_pairs(n, seed, error_rate, exclude=bench_scene_keys(crowded),
                      sprites=CROWDED_SPRITES if crowded else SPRITES)


def arrangements(pair: Pair, m: int, rng: np.random.Generator, avoid: set, tries: int = 20000) -> list[Pair]:
    """m new places of a pair's sprites where its task T is feasible: centres drawn as random_scene draws them (same
    sprites, colours, shapes and background: new_place), a scene in `avoid` (scene keys) or with T infeasible drawn
    again; each scene taken is added to `avoid`. Each new pair's D, and its plan, are the error-free ones of T's correct
    plan there (canonical_solution). train.py --train_arrangements trains on them, bench.py --keyed_on arranged
    evaluates on them. A ValueError if `tries` draws in a row find none."""
    out = []
    while len(out) < m:
        for _ in range(tries):
            scene = new_place(pair.scene, rng)
            if scene is None or scene_key(scene) in avoid or not (sols := solutions(scene, pair.task)):
                continue
            plan = canonical_solution(sols)
            d = describe(scene, plan)
            avoid.add(scene_key(scene))
            out.append(Pair(scene, pair.task, d, d, plan, plan, "", render(scene, simulate(scene, Plan(None)))[0]))
            break
        else:
            raise ValueError(f"{pair.task.text!r}: no new place of its sprites where it is feasible in {tries} draws")
    return out


TASK_TYPES = ("move to", "stop level with", *(f"go to the {e} edge" for e in EDGES), "centre")


def composition(pairs: list[Pair]) -> dict[str, dict[str, int]]:
    """The toy's Fig. 3 (Sec. 4.1.2, "WorldTasks prompt composition"), counted: how many of `pairs` address each
    agent category -- a sprite by its shape, or the camera (FIRST_PERSON) -- and how many ask each task type,
    TASK_TYPES, the edge tasks by the edge T names. Every category is listed, with 0 where none occurs:
    {"agent": {category: n}, "task": {type: n}}, each summing to len(pairs)."""
    agent = {**{shape: 0 for shape in SHAPES}, FIRST_PERSON: 0}
    task = dict.fromkeys(TASK_TYPES, 0)
    for q in pairs:
        agent[q.task.agent if q.task.agent == FIRST_PERSON else q.task.agent.split()[-1]] += 1
        task[{"move_to": "move to", "level_with": "stop level with", "centre": "centre"}.get(
            q.task.kind, f"go to the {q.task.target} edge")] += 1
    return {"agent": agent, "task": task}


def random_plan(scene: Scene, rng: np.random.Generator) -> Plan:
    """A pretraining motion: a still video (10%), a camera pan (25%) or one sprite moving (65%), always valid."""
    u = rng.random()
    if u < 0.10:
        return Plan(None)
    while True:
        vx, vy, k = ALL_MOTIONS[rng.integers(len(ALL_MOTIONS))]
        plan = Plan(-1 if u < 0.35 else int(rng.integers(len(scene.sprites))), vx, vy, k)
        if plan_is_valid(scene, plan):
            return plan


def goal_caption(task: Task) -> str:
    """What a captioner writes about a goal-directed clip: "red square moves to the blue circle", "camera pans to
    the blue circle". A description of the video, not an instruction (no "[agent]:" format, no imperative)."""
    if task.kind == "centre":
        return f"camera pans to the {task.target}"
    return f"{task.agent} moves " + {"move_to": "to the {}", "level_with": "level with the {}",
                                     "edge": "to the {} edge"}[task.kind].format(task.target)


def goal_clip(scene: Scene, rng: np.random.Generator):
    """A random feasible task of `scene` and its canonical solution, or None if the scene has none."""
    tasks, tables = candidate_tasks(scene), {}
    for i in rng.permutation(len(tasks)):
        sols = solutions(scene, tasks[i], tables)
        if sols:
            return tasks[i], canonical_solution(sols)
    return None


TASK_WORDS = {"up": "top", "down": "bottom", "camera": FIRST_PERSON}   # a caption's word -> the word T uses for it


def in_task_words(caption: str) -> str:
    """A caption with its vertical directions and its camera named as the bench's tasks name them: up/down -> top/
    bottom (the edge the motion heads for), camera -> first-person view. "red square moves right 1 up 1 for 3 frames
    then stops" -> "red square moves right 1 top 1 for 3 frames then stops". The same motion, in words of T that
    D-style captions never use (docs/given-t.md, "Task by kind"): a base pretrained on some of these has read them."""
    return " ".join(TASK_WORDS.get(w, w) for w in caption.split())


def pretraining_batch(rng: np.random.Generator, batch: int, p_vague: float = 0.15, p_empty: float = 0.10,
                      p_goal: float = 0.0, exclude: set | None = None, places: bool = False,
                      p_task_words: float = 0.0):
    """World videos for pretraining the base model (Sec. 3): most captioned like D (how things move); with
    probability p_goal a goal-directed clip with a goal caption ("red square moves to the blue circle" -- real
    video captions say such things, and they are why a real base half-understands a short task); with p_vague a
    caption that names the mover but not the motion; with p_empty an empty caption (as video models are trained
    for classifier-free guidance). With probability p_task_words a caption is said in T's words (in_task_words).
    Returns (videos uint8 (B, F, H, W, 3), captions list[str]) and, with places,
    where the caption's sprites are in frame 0: (B, 2, 2) float (x, y) of the mover it names, and of the sprite
    the motion heads for: a goal caption's target sprite, else the mover itself (no sprite to head for); NaN
    where the caption names none (the camera, an empty caption)."""
    videos, captions, where = [], [], []
    while len(videos) < batch:
        scene = random_scene(rng)
        if exclude and scene_key(scene) in exclude:
            continue
        goal = goal_clip(scene, rng) if p_goal > 0 and rng.random() < p_goal else None  # no draw when p_goal = 0
        plan = goal[1] if goal else random_plan(scene, rng)
        videos.append(render(scene, simulate(scene, plan)))
        u = rng.random()
        captions.append(goal_caption(goal[0]) if goal else "" if u < p_empty else
                        vague_caption(scene, plan) if u < p_empty + p_vague else describe(scene, plan))
        if p_task_words > 0 and rng.random() < p_task_words:   # no draw when p_task_words = 0
            captions[-1] = in_task_words(captions[-1])
        named = captions[-1] != "" and plan.mover is not None and plan.mover >= 0 and plan.k > 0
        mover = (scene.sprites[plan.mover].x, scene.sprites[plan.mover].y) if named else (np.nan, np.nan)
        target = {s.name: (s.x, s.y) for s in scene.sprites}.get(goal[0].target) if goal else None
        where.append([mover, target or mover])
    if places:
        return np.stack(videos), captions, np.array(where, dtype=np.float32)
    return np.stack(videos), captions


def sft_task(scene: Scene, plan: Plan, rng: np.random.Generator) -> str:
    """The SFT baseline's labeller (Sec. 4.4 "+SFT"): a short task in the "[agent]: instruction" format derived
    automatically from a plain world video. If the video ends solving a task it did not solve at frame 0, one such
    task at random; otherwise a trivial one naming the dominant direction ("[red square]: move right") -- the toy's
    "walk forward". Still videos get none (None)."""
    if plan.mover is None or plan.k == 0:
        return None
    pos = simulate(scene, plan)
    agent = FIRST_PERSON if plan.mover == -1 else scene.names()[plan.mover]
    done = [t for t in candidate_tasks(scene) if t.agent == agent
            and _margins(scene, t, pos[-1]) >= 0 > _margins(scene, t, pos[0])]
    if done:
        return done[int(rng.integers(len(done)))].text
    if abs(plan.vx) >= abs(plan.vy):
        return f"[{agent}]: move {'right' if plan.vx > 0 else 'left'}"
    return f"[{agent}]: move {'down' if plan.vy > 0 else 'up'}"


def sft_batch(rng: np.random.Generator, batch: int, crowded: bool = False):
    """Plain world videos (random motions, as in pretraining) with sft_task's labels: (videos, tasks), on scenes
    never in the bench (crowded=True: of CROWDED_SPRITES sprites, never in the crowded bench)."""
    videos, tasks = [], []
    exclude = bench_scene_keys(crowded)
    while len(videos) < batch:
        scene = random_scene(rng, CROWDED_SPRITES if crowded else SPRITES)
        if scene_key(scene) in exclude:
            continue
        plan = random_plan(scene, rng)
        task = sft_task(scene, plan, rng)
        if task is not None:
            videos.append(render(scene, simulate(scene, plan)))
            tasks.append(task)
    return np.stack(videos), tasks


# ----------------------------------------------------------------------------------------------------------------
# real images: the WorldTasks construction of Sec. 4.1.1 / App. A.6 for the real-model path (--model ltx2)
# ----------------------------------------------------------------------------------------------------------------

def split_task(text: str) -> tuple[str, str]:
    """Any task in the paper's format "[agent]: instruction" -> (agent, instruction); ValueError otherwise.
    (parse_task above additionally checks the toy world's vocabulary.)"""
    m = _TASK_RE.match(text.strip())
    if not m or not m["agent"].strip():     # after strip() "rest" ends in a non-space; "[ ]" names no agent
        raise ValueError(f"task {text!r} is not of the form '[agent]: instruction'")
    return m["agent"].strip(), m["rest"].strip()


QUALITY_THRESHOLDS = {"min_laplacian_var": 12.0, "min_mean_luma": 20.0, "max_mean_luma": 235.0,
                      "max_black_ratio": 0.85, "max_white_ratio": 0.85}   # App. A.6.1, the paper's main setup


def image_quality(image: np.ndarray) -> dict:
    """App. A.6.1's low-level statistics of an RGB image (H, W, 3) uint8: the variance of the Laplacian of the luma
    (blur), the mean luma (too dark / too bright), and the fractions of near-black (< 16) and near-white (> 239)
    pixels (nearly empty frames). Luma: ITU-R BT.601, Y = 0.299 R + 0.587 G + 0.114 B."""
    y = np.asarray(image, np.float64)[..., :3] @ np.array([0.299, 0.587, 0.114])
    lap = (y[:-2, 1:-1] + y[2:, 1:-1] + y[1:-1, :-2] + y[1:-1, 2:] - 4 * y[1:-1, 1:-1])   # 4-neighbour Laplacian
    return {"laplacian_var": float(lap.var()), "mean_luma": float(y.mean()),
            "black_ratio": float((y < 16).mean()), "white_ratio": float((y > 239).mean())}


def quality_ok(image: np.ndarray, th: dict = QUALITY_THRESHOLDS) -> tuple[bool, str]:
    """The image-quality filter of App. A.6.1: (kept?, reason if rejected)."""
    q = image_quality(image)
    for bad, why in ((q["laplacian_var"] < th["min_laplacian_var"], "blurry"),
                     (q["mean_luma"] < th["min_mean_luma"], "underexposed"),
                     (q["mean_luma"] > th["max_mean_luma"], "overexposed"),
                     (q["black_ratio"] > th["max_black_ratio"], "mostly black"),
                     (q["white_ratio"] > th["max_white_ratio"], "mostly white")):
        if bad:
            return False, why
    return True, ""


SUITABILITY_PROMPT = (  # Fig. 12, verbatim
    "Look at this image carefully. Is this image suitable as a training sample for an agent-based video generation "
    "model? Consider whether: The scene contains meaningful, diverse visual content (not blank, corrupted, or "
    "trivially simple) The image quality is acceptable (not severely blurry, overexposed, underexposed, or distorted) "
    "The image depicts a scene where an agent could plausibly perform tasks Output Format Answer with ONLY Yes or No. "
    "Do not include any explanation or additional text.")

TASK_SOLUTION_PROMPT = (  # ours: the paper shows outputs (Figs. 13-14) but not its generation prompt
    "Look at this image, the first frame of a video. Propose {n} short tasks that an agent visible in the image (or "
    "the camera, as [First-person view]) could carry out within a few seconds, and for each a detailed description "
    "of the motion that solves it, as a video model would need it: who moves, which way, how far, what stays still. "
    "Cover navigation (go to an object), positioning (stop beside or level with something) and perception (turn the "
    "view to bring something into view). Answer exactly in this format, nothing else:\n"
    "1. Task 1: [agent]: instruction\nDescription 1: description\n2. Task 2: [agent]: instruction\n"
    "Description 2: description")

_SOLUTION_RE = re.compile(r"Task\s*(\d+)\s*:\s*(\[[^\]]+\]\s*:.+?)\s*Description\s*\1\s*:\s*(.+?)(?=\s*\d+\.\s*Task\s*\d+\s*:|$)",
                          re.S)


def parse_task_solutions(text: str) -> list[tuple[str, str]]:
    """The generator's answer -> [(T, D), ...] in the format of Figs. 13-14 ("1. Task 1: [agent]: ... Description 1:
    ..."). Items whose task is not "[agent]: instruction" are dropped; an unparseable answer gives []."""
    out = []
    for _, task, desc in _SOLUTION_RE.findall(text):
        task, desc = " ".join(task.split()), " ".join(desc.split())
        try:
            split_task(task)
        except ValueError:
            continue
        out.append((task, desc))
    return out


FAMILY_WORDS = {"navigation": ("go to", "move to", "walk to", "drive to", "approach", "reach"),
                "positioning": ("level with", "beside", "align", "stop", "next to", "edge"),
                "perception": ("look", "centre", "center", "turn", "pan", "view")}


def task_family(task: str) -> str:
    """A coarse family label for Fig. 7's breakdown, by keywords of the instruction (first match; else "other")."""
    instr = split_task(task)[1].lower()
    return next((f for f, ws in FAMILY_WORDS.items() if any(w in instr for w in ws)), "other")


# Sec. 4.1.2's prompt-only taxonomy (Fig. 3; Fig. 7's subgroups): the paper's categories, in its order
AGENT_TAXONOMY = ("first-person view", "human character", "vehicle", "inanimate object or landmark", "creature",
                  "animal", "crowd")
TASK_TAXONOMY = ("positioning", "navigation", "object interaction", "perception", "combat action",
                 "compound instruction", "vehicle control", "UI interaction", "other")
UNCLASSIFIED = "unclassified"   # a row whose taxonomy answer was malformed

TAXONOMY_PROMPT = (  # ours: the paper names its classifier (Qwen3.5-27B, prompt only) but shows no prompt
    "Here is a task for an agent in a video, written as [agent]: instruction.\n"
    "Task: {task}\n"
    "{question}\n"
    "{options}\n"
    "Answer with ONLY the number of one category. Do not include any explanation or additional text.")
TAXONOMY_QUESTIONS = {"agent_type": ("Which category does the agent named in square brackets belong to?",
                                     AGENT_TAXONOMY),
                      "task_type": ("Which category does the instruction belong to?", TASK_TAXONOMY)}


def taxonomy_prompt(task: str, key: str) -> str:
    """TAXONOMY_PROMPT for task T and one of TAXONOMY_QUESTIONS' keys: its categories as a numbered list, 1..n."""
    question, options = TAXONOMY_QUESTIONS[key]
    return TAXONOMY_PROMPT.format(task=task, question=question,
                                  options="\n".join(f"{k}. {o}" for k, o in enumerate(options, 1)))


def classify_tasks(vlm, tasks: list[str]) -> list[dict]:
    """Sec. 4.1.2: "We further characterize the final prompt set using a prompt-only Qwen3.5-27B taxonomy" -- each
    task T's addressed agent (AGENT_TAXONOMY) and task type (TASK_TAXONOMY), asked of a VLM from T's text alone, no
    image. vlm.choose(prompts, n) (reward.VLMJudge.choose) answers each with an option's index 0..n-1, or None for a
    malformed answer, kept as None (App. A.4 discards such answers). Returns [{"agent_type": category or None,
    "task_type": category or None}] in the order of `tasks`."""
    out = [{} for _ in tasks]
    for key, (_, options) in TAXONOMY_QUESTIONS.items():
        for row, k in zip(out, vlm.choose([taxonomy_prompt(t, key) for t in tasks], len(options)) if tasks else []):
            row[key] = None if k is None else options[k]
    return out


def dataset_composition(splits: dict[str, list[dict]], top: int = 8) -> dict[str, dict[str, dict[str, int]]]:
    """Fig. 3 (Sec. 4.1.2, "WorldTasks prompt composition") for WorldTasks JSONL files (load_dataset's rows), split by
    split. Where every row carries the taxonomy (classify_tasks; make_worldtasks writes it): the paper's categories,
    AGENT_TAXONOMY and TASK_TAXONOMY, in its order, and UNCLASSIFIED for a malformed answer. Otherwise: the agent T
    addresses, as written between its brackets (lower-cased), the `top` commonest over all splits by name and the rest
    as "other"; and the task family by task_family's keywords. {split: {"agent": {category: n}, "task": {family:
    n}}}, every category in every split, each panel summing to the split's rows."""
    if all("agent_type" in r and "task_type" in r for rows in splits.values() for r in rows):
        out = {}
        for split, rows in splits.items():
            agent = dict.fromkeys((*AGENT_TAXONOMY, UNCLASSIFIED), 0)
            task = dict.fromkeys((*TASK_TAXONOMY, UNCLASSIFIED), 0)
            for r in rows:
                agent[r["agent_type"] or UNCLASSIFIED] += 1
                task[r["task_type"] or UNCLASSIFIED] += 1
            out[split] = {"agent": agent, "task": task}
        return out
    agents = [[split_task(r["task"])[0].strip().lower() for r in rows] for rows in splits.values()]
    total = collections.Counter(a for a_s in agents for a in a_s)
    names = sorted(total, key=lambda a: (-total[a], a))
    kept = names[:top] + (["other"] if len(names) > top else [])
    out = {}
    for (split, rows), a_s in zip(splits.items(), agents):
        agent, task = dict.fromkeys(kept, 0), dict.fromkeys((*FAMILY_WORDS, "other"), 0)
        for r, a in zip(rows, a_s):
            agent[a if a in agent else "other"] += 1
            task[task_family(r["task"])] += 1
        out[split] = {"agent": agent, "task": task}
    return out


def load_dataset(path: str) -> list[dict]:
    """A WorldTasks JSONL file: one {"image", "task", "description", "agent", "family"} per line (image a path,
    relative to the file), and the taxonomy's "agent_type" and "task_type" where make_worldtasks wrote them (a
    category, or null). Raises ValueError "path line N: ..." on the first bad line, naming the problem."""
    import os

    def check(r: dict) -> dict:
        missing = [k for k in ("image", "task", "description") if not isinstance(r.get(k), str) or not r[k]]
        if missing:
            raise ValueError(f"missing or empty {', '.join(missing)}")
        split_task(r["task"])
        for key, (_, options) in TAXONOMY_QUESTIONS.items():
            if r.get(key) is not None and r[key] not in options:
                raise ValueError(f"{key} {r[key]!r} is not one of the taxonomy's categories ({', '.join(options)})")
        r["image"] = os.path.join(os.path.dirname(os.path.abspath(path)), r["image"])
        if not os.path.isfile(r["image"]):
            raise ValueError(f"image {r['image']!r} does not exist")
        return r
    rows = [r | {"line": n} for n, r in read_jsonl(path, "dataset", check)]
    if not rows:
        raise ValueError(f"dataset {path!r} has no rows")
    return rows


AESTHETIC_KEEP = 0.9   # App. A.6.1: keep the top 90% of the frames that pass the quality filter


class CLIPAesthetic:
    """App. A.6.1's "aesthetic score based on a CLIP-based scoring function": a linear head on CLIP's normalised
    image embedding, the form of the LAION aesthetic predictor (the paper does not name its head). images (list of
    RGB uint8 arrays) -> scores (np.ndarray, higher is better). Weights from local paths: a CLIP model directory
    and a torch file holding the head's {"weight": (1, D), "bias": (1,)}."""

    def __init__(self, clip, processor, head):
        self.clip, self.processor, self.head = clip.eval(), processor, head.eval()

    @classmethod
    def from_pretrained(cls, clip_path: str, head_path: str):
        import os

        import torch
        from transformers import CLIPImageProcessorPil, CLIPVisionModelWithProjection
        for p in (clip_path, head_path):
            if not os.path.exists(p):
                raise FileNotFoundError(f"aesthetic scorer weights not found at {p!r} (nothing is downloaded)")
        clip = CLIPVisionModelWithProjection.from_pretrained(clip_path)
        head = torch.nn.Linear(clip.config.projection_dim, 1)
        head.load_state_dict(torch.load(head_path, weights_only=True))
        return cls(clip, CLIPImageProcessorPil.from_pretrained(clip_path), head)

    @classmethod
    def tiny(cls, seed: int = 0):
        """Random weights of the real classes, for CPU tests."""
        import torch
        from transformers import CLIPImageProcessorPil, CLIPVisionConfig, CLIPVisionModelWithProjection
        torch.manual_seed(seed)
        clip = CLIPVisionModelWithProjection(CLIPVisionConfig(
            hidden_size=16, intermediate_size=32, num_hidden_layers=1, num_attention_heads=2, image_size=32,
            patch_size=8, projection_dim=8))
        proc = CLIPImageProcessorPil(size={"shortest_edge": 32}, crop_size={"height": 32, "width": 32})
        return cls(clip, proc, torch.nn.Linear(8, 1))

    def __call__(self, images: list) -> np.ndarray:
        import torch
        with torch.no_grad():
            pix = self.processor(images=[np.asarray(im) for im in images], return_tensors="pt").pixel_values
            e = self.clip(pixel_values=pix).image_embeds
            return self.head(e / e.norm(dim=-1, keepdim=True)).squeeze(-1).numpy()


def aesthetic_top(scores, keep: float = AESTHETIC_KEEP) -> np.ndarray:
    """Indices of the top `keep` share of `scores` (at least one when there are any), in their original order."""
    scores = np.asarray(scores, float)
    n = int(np.ceil(keep * len(scores))) if len(scores) else 0
    return np.sort(np.argsort(-scores, kind="stable")[:n])


def read_jsonl(path: str, what: str, check) -> list[tuple[int, dict]]:
    """The rows of a JSONL file as (line number, check(row)), blank lines skipped: what load_dataset and
    train.sft_rows read. `check` returns the row it is given, made whole, or raises for a bad one. A missing file, a
    folder, or a bad row is one ValueError: "{what} 'path' does not exist", or "path line N: what was wrong"."""
    import json
    import os
    if not os.path.isfile(path):
        raise ValueError(f"{what} {path!r} " + ("is a directory, not a JSONL file" if os.path.isdir(path) else
                                               "does not exist"))
    rows = []
    with open(path) as f:
        for n, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:    # a JSON error is a ValueError; a missing or unread file, OSError; an mp4 without PyAV, ImportError
                rows.append((n, check(json.loads(line))))
            except (ValueError, TypeError, AttributeError, OSError, ImportError) as e:
                raise ValueError(f"{path} line {n}: {e}") from None
    return rows


def write_jsonl(path: str, rows: list[dict]) -> None:
    """`rows` as JSON lines, written whole: to a temporary file, then renamed, so a run cut short leaves no half file.
    Missing folders on the way are made."""
    import json
    import os
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        f.writelines(json.dumps(r) + "\n" for r in rows)
    os.replace(tmp, path)


def make_worldtasks(image_paths: list[str], vlm, out_path: str, per_image: int = 8, aesthetic=None) -> dict:
    """Sec. 4.1.1 / App. A.6 end to end: the image-quality filter, the aesthetic ranking (with a scorer such as
    CLIPAesthetic: keep the top 90% of what passed), the VLM suitability filter (Fig. 12), and `per_image`
    task-solution pairs per kept image from the VLM, each labelled by Sec. 4.1.2's prompt-only taxonomy
    (classify_tasks), written as JSONL (load_dataset's format). `vlm` needs yes_no(images, prompt) -> list[bool |
    None], generate(images, prompt) -> list[str] and choose(prompts, n) -> list[int | None] (reward.VLMJudge has all
    three). Returns counts of what was kept and why the rest was dropped, and of the rows the taxonomy could not
    label (an answer that was no category's number: "taxonomy malformed")."""
    import os

    from PIL import Image
    counts = {"images": len(image_paths), "kept_images": 0, "pairs": 0}
    rows, images, kept = [], [], []
    for p in image_paths:
        try:
            with Image.open(p) as im:
                img = np.asarray(im.convert("RGB"))
        except OSError:         # not an image PIL reads, or cut short: dropped and counted, as the filters drop
            counts["unreadable"] = counts.get("unreadable", 0) + 1
            continue
        ok, why = quality_ok(img)
        if ok:
            images.append(img)
            kept.append(p)
        else:
            counts[why] = counts.get(why, 0) + 1
    if aesthetic is not None and images:
        top = aesthetic_top(aesthetic(images))
        counts["low aesthetic score"] = len(images) - len(top)
        images, kept = [images[i] for i in top], [kept[i] for i in top]
    suitable = vlm.yes_no(images, SUITABILITY_PROMPT) if images else []
    base = os.path.dirname(os.path.abspath(out_path))
    answers = vlm.generate([im for im, s in zip(images, suitable) if s], TASK_SOLUTION_PROMPT.format(n=per_image))
    counts["unsuitable"] = sum(1 for s in suitable if not s)
    for p, ans in zip([p for p, s in zip(kept, suitable) if s], answers):
        pairs = parse_task_solutions(ans)[:per_image]
        counts["kept_images"] += bool(pairs)
        for task, desc in pairs:
            rows.append({"image": os.path.relpath(p, base), "task": task, "description": desc,
                         "agent": split_task(task)[0], "family": task_family(task)})
    for r, types in zip(rows, classify_tasks(vlm, [r["task"] for r in rows])):
        r.update(types)
    counts["taxonomy malformed"] = sum(None in (r["agent_type"], r["task_type"]) for r in rows)
    write_jsonl(out_path, rows)
    counts["pairs"] = len(rows)
    return counts


VIDEO_CONTAINERS = (".mp4", ".m4v", ".mov", ".mkv", ".webm", ".avi")   # decoded through PyAV (requirements-real.txt)


def _open_container(path: str, mode: str = "r"):
    """An mp4 or other VIDEO_CONTAINERS file opened through PyAV, the optional package that decodes them: an
    ImportError naming the install if it is missing, a ValueError for a file it cannot read (PyAV's
    InvalidDataError is one), a FileNotFoundError for a missing one. mode "w": opened to be written."""
    import models       # models imports this module: here, not at the top
    models._require("av")
    import av
    return av.open(path, mode)


def write_video(path: str, frames: np.ndarray, fps: float) -> None:
    """uint8 (F, H, W, 3) -> an mp4 to watch at `fps` frames a second: H.264 in 4:2:0 at crf 18, what players take,
    through PyAV. 4:2:0 needs an even height and width: an odd one loses its last row or column."""
    import av
    from fractions import Fraction
    frames = frames[:, :frames.shape[1] // 2 * 2, :frames.shape[2] // 2 * 2]
    with _open_container(path, "w") as c:
        s = c.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001), options={"crf": "18"})
        s.height, s.width, s.pix_fmt = frames.shape[1], frames.shape[2], "yuv420p"
        for f in frames:
            c.mux(s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(f), format="rgb24")))
        c.mux(s.encode())        # what the encoder still holds


def video_length(path: str) -> int:
    """How many frames a video file holds: a .npy array uint8 (F, H, W, 3) or an image PIL reads (an animated GIF,
    PNG or WebP; a still image is one frame), from the header; a video container (VIDEO_CONTAINERS: mp4, mov, webm,
    ...) through PyAV, from its stream's header where it records the count (mp4, mov), else by decoding (webm). A
    ValueError for a .npy of another kind, an OSError or ValueError for a file that cannot be read."""
    from PIL import Image
    if path.endswith(".npy"):
        v = np.load(path, mmap_mode="r")          # no pickles, nothing read but the header
        if v.dtype != np.uint8 or v.ndim != 4 or v.shape[-1] != 3:
            raise ValueError(f"{path}: a .npy video is uint8 (F, H, W, 3), not {v.dtype} {v.shape}")
        return len(v)
    if path.lower().endswith(VIDEO_CONTAINERS):
        with _open_container(path) as c:
            if not c.streams.video:
                raise ValueError(f"{path}: no video stream")
            return c.streams.video[0].frames or sum(1 for _ in c.decode(video=0))
    with Image.open(path) as img:
        return getattr(img, "n_frames", 1)


def load_video(path: str, size: tuple | None = None) -> np.ndarray:
    """A video file (video_length's kinds, checked as it checks them) -> uint8 (F, H, W, 3), each frame bilinear to
    size = (width, height) if given. A container whose frames decoded differ in number from its header's count (the
    count train.sft_rows checked before training) is a ValueError."""
    from PIL import Image, ImageSequence
    n = video_length(path)
    if path.endswith(".npy"):
        frames = [Image.fromarray(f) for f in np.load(path)]
    elif path.lower().endswith(VIDEO_CONTAINERS):
        with _open_container(path) as c:
            frames = [f.to_image() for f in c.decode(video=0)]      # RGB
        if len(frames) != n:
            raise ValueError(f"{path}: {len(frames)} frames decoded where its header counts {n}")
    else:
        with Image.open(path) as img:
            frames = [f.convert("RGB") for f in ImageSequence.Iterator(img)]
    return np.stack([np.asarray(f.resize(size, Image.BILINEAR) if size else f) for f in frames])


VIDEO_TASK_PROMPT = (  # ours: the paper says only that unannotated videos are labelled with tasks (Sec. 4.4, +SFT)
    "You are given the frames of a video in temporal order. Write the one short task that the video shows an agent "
    "carrying out, as the instruction that agent could have been given. Name the agent as it appears; for the "
    "camera's own motion, write [First-person view]. Answer exactly in this format, nothing else:\n"
    "[agent]: instruction")


def label_videos(video_paths: list[str], vlm, out_path: str) -> dict:
    """Sec. 4.4's +SFT data (Table 1's "+SFT" row): unannotated videos labelled by the VLM with the task each shows,
    "[agent]: instruction" (VIDEO_TASK_PROMPT, ours), written as the JSONL that train.py --sft_dataset reads
    ({"video", "task"}, paths relative to the file). `vlm` needs generate(videos, prompt) -> list[str]
    (reward.VLMJudge). A video that cannot be read, or whose answer holds no task, is dropped and counted. Returns
    {"videos", "labelled", "unreadable", "malformed"}."""
    import os
    counts = {"videos": len(video_paths), "labelled": 0, "unreadable": 0, "malformed": 0}
    base, rows = os.path.dirname(os.path.abspath(out_path)), []
    for p in video_paths:                     # one video in memory at a time
        try:
            video = load_video(p)
        except (OSError, ValueError):
            counts["unreadable"] += 1
            continue
        answer, task = vlm.generate([video], VIDEO_TASK_PROMPT)[0], None
        for line in answer.splitlines():      # the first line that holds a task, from its opening bracket
            try:
                task = " ".join(line[line.index("["):].split())    # ValueError: no bracket on this line
                split_task(task)
                break
            except ValueError:
                task = None
        if task is None:
            counts["malformed"] += 1
            continue
        rows.append({"video": os.path.relpath(os.path.abspath(p), base), "task": task})
    write_jsonl(out_path, rows)
    counts["labelled"] = len(rows)
    return counts


def main(argv=None) -> None:
    """`python world.py`: the first bench pairs as the simulator solves them, and their T and D; or, with
    --composition, the toy's Fig. 3; or, with --worldtasks or --label_videos and a VLM, a real dataset file."""
    import argparse

    import bench        # bench imports this module: here, not at the top
    p = argparse.ArgumentParser(description="Draw the first N pairs of the 200-pair bench as the simulator solves them "
                                "(the error-free plan; one pair a row, frames 0..5 left to right) into a PNG, and "
                                "print each pair's family, T and D. With --composition, draw the toy's Fig. 3 "
                                "instead: the agents and task types of the training split and the two benches.")
    p.add_argument("--n", type=int, default=None, help="bench pairs to draw, 1..200 (default 6)")
    p.add_argument("--out", default=None, help="the PNG to write (default world_examples.png); with --worldtasks or "
                   "--label_videos, the JSONL file")
    p.add_argument("--composition", default=None, metavar="PNG",
                   help="draw Fig. 3's prompt composition into PNG and print its counts (not with --n or --out)")
    p.add_argument("--dataset", action="append", default=None, metavar="JSONL",
                   help="with --composition: a WorldTasks JSONL file's composition instead of the toy's, one split "
                        "per file (repeat the flag: the training split, then the bench)")
    p.add_argument("--worldtasks", nargs="+", default=None, metavar="IMAGE",
                   help="write the WorldTasks JSONL file --out from these images (make_worldtasks: App. A.6's "
                        "filters, the VLM's task-solution pairs, the taxonomy)")
    p.add_argument("--label_videos", nargs="+", default=None, metavar="VIDEO",
                   help="write the +SFT file --out that train.py --sft_dataset reads: these videos (.npy; mp4, mov, "
                        "mkv, webm, avi through PyAV; animated GIF, PNG, WebP), each labelled by the VLM with the "
                        "task it shows (label_videos)")
    p.add_argument("--judge", default="qwen-vl", choices=("qwen-vl", "qwen-vl-tiny"),
                   help="with --worldtasks or --label_videos: the VLM (qwen-vl: --judge_path; qwen-vl-tiny: random "
                        "weights, for checks)")
    p.add_argument("--judge_path", default="", help="--judge qwen-vl: the local transformers directory")
    a = p.parse_args(argv)
    if a.dataset and not a.composition:
        p.error("--dataset is read with --composition only")
    build = "worldtasks" if a.worldtasks else "label_videos" if a.label_videos else None
    if (a.judge != "qwen-vl" or a.judge_path) and not build:
        p.error("--judge and --judge_path are read with --worldtasks or --label_videos only")
    if build:
        if a.worldtasks and a.label_videos or a.composition or a.n is not None:
            p.error("--worldtasks and --label_videos each write one file: not with each other, --composition or --n")
        if not a.out or (bad := bench.output_path_error(a.out, "--out", suffix=".jsonl")):
            p.error(bad if a.out else f"--{build} writes the JSONL file --out: give one")
        if a.judge == "qwen-vl" and not a.judge_path:
            p.error("--judge qwen-vl needs --judge_path (a local directory of the VLM; nothing is downloaded)")
        import models
        import train        # its VLM loader, as the training runs load it
        try:
            if any(v.lower().endswith(VIDEO_CONTAINERS) for v in a.label_videos or ()):
                models._require("av")       # before the VLM loads, not after it has labelled the first videos
            vlm = train.make_judge(train.Args(judge=a.judge, judge_path=a.judge_path))
        except (FileNotFoundError, ValueError, ImportError) as e:
            p.error(str(e))
        counts = (make_worldtasks if build == "worldtasks" else label_videos)(getattr(a, build), vlm, a.out)
        print(", ".join(f"{k} {v}" for k, v in counts.items()))
        return print(f"wrote {a.out}")
    if a.composition:
        if a.n is not None or a.out is not None:
            p.error("--n and --out choose the pairs drawn as videos: not with --composition")
        if bad := bench.output_path_error(a.composition, "--composition", suffix=".png"):
            p.error(bad)
        if not a.dataset:
            import train    # train.toy_pairs: the split a run trains on (its size and seed are train.py's)
            splits = {"training split (train.py --toy, seed 0)": train.toy_pairs(train.parse_args(["--toy"])),
                      "bench": bench_pairs(0.0), "crowded bench": crowded_pairs(0.0)}
            return draw_composition(a.composition, {k: composition(v) for k, v in splits.items()})
        try:
            rows = {path: load_dataset(path) for path in a.dataset}
        except ValueError as e:
            p.error(str(e))
        return draw_composition(a.composition, dataset_composition(rows))
    a.n, a.out = 6 if a.n is None else a.n, a.out or "world_examples.png"
    if not 1 <= a.n <= 200:
        p.error(f"--n must lie in 1..200 (the toy bench), got {a.n}")
    if bad := bench.output_path_error(a.out, "--out", suffix=".png"):
        p.error(bad)
    pairs = bench_pairs(0.0)[:a.n]
    bench.save_strip(np.stack([render(q.scene, simulate(q.scene, q.plan_oracle)) for q in pairs]), a.out, rows=a.n,
                     scale=8)
    for q in pairs:
        print(f"{q.task.family:12s} T = {q.task.text!r:45s} D = {q.d_oracle!r}")
    print(f"wrote {a.out}")


def draw_composition(path: str, counts: dict[str, dict[str, dict[str, int]]]) -> None:
    """Fig. 3: two panels, (a) the addressed agent's category and (b) the task type, each category's share of each
    split (counts as composition or dataset_composition return them: each panel sums to the split's pairs), into the
    PNG at `path`; the counts are printed."""
    import bench
    sizes = {name: sum(c["agent"].values()) for name, c in counts.items()}
    plt, fig, axes = bench.figure(2, width=5.6)
    w = 0.8 / len(counts)
    for ax, key, title in zip(axes, ("agent", "task"), ("(a) addressed agent", "(b) task type")):
        cats = list(next(iter(counts.values()))[key])
        for j, (name, c) in enumerate(counts.items()):
            ax.barh(np.arange(len(cats)) + (j - (len(counts) - 1) / 2) * w,
                    [100 * c[key][k] / sizes[name] for k in cats], height=w, label=f"{name}, {sizes[name]} pairs")
        ax.set_yticks(np.arange(len(cats)), cats)
        ax.invert_yaxis()
        ax.set_xlabel("share of the split's pairs (%)")
        ax.set_title(title)
    axes[1].legend(fontsize=7)
    bench.save_figure(plt, fig, path)
    for key in ("agent", "task"):
        print(f"{key:24s}" + "".join(f"{name.split(' (')[0][-15:]:>16s}" for name in counts))
        for k in next(iter(counts.values()))[key]:
            print(f"  {k[:22]:22s}" + "".join(f"{c[key][k]:>16d}" for c in counts.values()))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
