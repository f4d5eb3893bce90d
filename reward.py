"""Rule-based judges standing in for the VLM (Sec. 4.1 "Rewards", App. A.7 Figs. 15-17).

They read only the generated frames -- sprites are found by colour, never looked up in the simulator -- and answer
the three WorldTasks-Bench questions:

  judge_task        (Fig. 15) is the instructed task solved by the end?  Looks at the end state only. Like a VLM
                    asked about the outcome, it is satisfied if *some* blob of the agent's colour is where the task
                    wants it -- so a video that spawns a copy of the agent at the goal fools it. That is on purpose:
                    the separate consistency judge is what catches it, and that separation is what lets reward
                    hacking appear and be cured later (paper Fig. 8).
  judge_agent       (Fig. 16) did the addressed agent act, and only it? For "[first-person view]" the camera must
                    move: every sprite shifts by the same vector.
  judge_consistency (Fig. 17) physical consistency: no sprite appearing, vanishing (except across the border) or
                    duplicated, no teleport, no change of size or shape, a stable background.

Each returns a Judgment: a binary decision and a graded score in the role of log p(yes) - log p(no) (positive iff
yes, its size growing with the margin), or yes = score = None when no judgment can be made (a malformed video, or
an agent/target named by the task that the first frame does not show) -- counted as invalid, never a crash, as the
paper discards malformed VLM answers (App. A.4, Tab. 4).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import world
from world import COLOURS, FIRST_PERSON, H, SHAPE_OFFSET, W

SLACK = 0.35        # px of extra tolerance on the task rules for sub-pixel blur in generated frames
MAX_STEP = world.MAX_SPEED + 0.6  # px per frame (Chebyshev) above which a move is a teleport
MIN_BLOB = 3        # px: smaller specks of a colour are ignored as noise
SCORE_CLIP = 6.0    # graded scores live in [-6, 6], like a confident VLM's log-odds


@dataclass
class Judgment:
    yes: bool | None
    score: float | None  # > 0 iff yes; None iff no judgment could be made
    why: str = ""


INVALID = Judgment(None, None, "no judgment possible")


def _graded(margin: float, why: str = "") -> Judgment:
    s = float(np.clip(2.0 * margin, -SCORE_CLIP, SCORE_CLIP))
    if s == 0.0:
        s = -1e-3  # the boundary counts as "no"
    return Judgment(s > 0, s, why)


@dataclass
class Reading:
    """What a judge sees in a video: the sprites of frame 0 and, per frame and colour, the blobs of that colour."""
    sprites: list          # list[world.Sprite] read from frame 0
    blobs: list            # blobs[f][colour] -> list[world.Blob], largest first, each >= MIN_BLOB px
    frames: np.ndarray     # (F, H, W, 3) float32 in [0, 255]

    def sprite(self, name: str):
        return next((s for s in self.sprites if s.name == name), None)

    def centres(self, name: str, f: int, all_blobs: bool = False) -> list[np.ndarray]:
        """Centres (x, y) of the blobs of `name`'s colour in frame f (the largest only unless all_blobs),
        corrected for the shape's centroid offset."""
        s = self.sprite(name)
        off = np.array(SHAPE_OFFSET[s.shape])
        bs = self.blobs[f][s.colour]
        return [np.array([b.cx, b.cy]) - off for b in (bs if all_blobs else bs[:1])]


def read_video(video) -> Reading | None:
    """(F, H, W, 3) uint8 or float in [0, 255] -> Reading, or None if the array is malformed. A video at an integer
    multiple of the world's 16x16 (the toy world through a real backend, e.g. LTX-2 at 32x32) is read block-averaged.
    A Reading passes through, so judge_all reads a video once for its three judges."""
    if isinstance(video, Reading):
        return video
    v = np.asarray(video)
    if v.ndim == 4 and v.shape[3] == 3 and v.shape[1:3] != (H, W) and v.shape[1] % H == 0 and v.shape[2] % W == 0:
        # the toy world rendered at a multiple of its size (a real backend's resolution): block-average it down
        v = v.astype(np.float32).reshape(v.shape[0], H, v.shape[1] // H, W, v.shape[2] // W, 3).mean((2, 4))
    if v.ndim != 4 or v.shape[1:] != (H, W, 3) or v.shape[0] < 2 or not np.isfinite(v).all():
        return None
    v = np.clip(v.astype(np.float32), 0, 255)
    masks = world.colour_masks(v)
    bl = [{c: [b for b in world.blobs(masks[c][f]) if b.size >= MIN_BLOB] for c in COLOURS} for f in range(len(v))]
    return Reading(world.read_sprites(v[0].astype(np.uint8)), bl, v)


def _task_of(task_text: str, r: Reading):
    task = world.parse_task(task_text)  # a malformed prompt is the caller's bug: it raises ValueError
    needed = ([task.agent] if task.agent != FIRST_PERSON else []) + ([task.target] if task.kind != "edge" else [])
    return task if all(r.sprite(n) is not None for n in needed) else None


def judge_task(video, task_text: str) -> Judgment:
    """Fig. 15: is the task solved by the final frame? margin = max over blobs of the agent's (and target's) colour
    of world.task_margin(...) + SLACK; yes iff margin > 0. The agent not visible at the end is a clear no."""
    r = read_video(video)
    task = _task_of(task_text, r) if r is not None else None
    if task is None:
        return INVALID
    last = len(r.frames) - 1
    agents = [None] if task.kind == "centre" else r.centres(task.agent, last, all_blobs=True)
    targets = [None] if task.kind == "edge" else r.centres(task.target, last, all_blobs=True)
    if not agents or not targets:
        return _graded(-SCORE_CLIP, "agent or target not visible in the final frame")
    margin = max(world.task_margin(task.kind, task.target, a, t) for a in agents for t in targets)
    return _graded(margin + SLACK)


def _clipped(b, size0: int) -> bool:
    """A blob cut by the border of the view: touching it and smaller than the whole sprite."""
    return b.touches_border and b.size < 0.8 * size0


def _track(r: Reading, name: str) -> list:
    """Per frame the centre of `name`'s largest blob, or None where it is missing or cut by the border."""
    c = r.sprite(name).colour
    size0 = r.blobs[0][c][0].size
    return [r.centres(name, f)[0] if r.blobs[f][c] and not _clipped(r.blobs[f][c][0], size0) else None
            for f in range(len(r.frames))]


def _max_disp(track: list) -> float:
    return max([float(np.abs(p - track[0]).max()) for p in track[1:] if p is not None], default=0.0)


def judge_agent(video, task_text: str) -> Judgment:
    """Fig. 16: did the addressed agent act, and no one else?
    Sprite agent: d_agent = max_f |c_agent(f) - c_agent(0)|_inf must be >= 1 and every other sprite's d <= 1:
      margin = min(d_agent - 0.75, 1.25 - max_other d).
    First-person view: the camera moves, so all sprites shift together: with s_f the mean displacement over visible
      sprites, margin = min(max_f |s_f|_inf - 0.75, 1.25 - max_f max pairwise |disp_i - disp_j|_inf)."""
    r = read_video(video)
    task = _task_of(task_text, r) if r is not None else None
    if task is None:
        return INVALID
    tracks = {s.name: _track(r, s.name) for s in r.sprites}
    if task.agent != FIRST_PERSON:
        others = [_max_disp(t) for n, t in tracks.items() if n != task.agent]
        return _graded(min(_max_disp(tracks[task.agent]) - 0.75, 1.25 - max(others, default=0.0)))
    shift, spread = 0.0, 0.0
    for f in range(1, len(r.frames)):
        d = [t[f] - t[0] for t in tracks.values() if t[0] is not None and t[f] is not None]
        if not d:
            continue
        d = np.stack(d)
        shift = max(shift, float(np.abs(d.mean(0)).max()))
        spread = max(spread, float(np.abs(d[:, None] - d[None]).max()))
    return _graded(min(shift - 0.75, 1.25 - spread))


def judge_consistency(video, task_text: str | None = None) -> Judgment:
    """Fig. 17: physically consistent? Counts violations (each kind once per sprite), yes iff none:
      appears   -- a blob of a colour that frame 0 does not have
      duplicate -- a second blob of a sprite's colour
      vanishes  -- a sprite missing in a frame although it was last seen more than 1 px from the border
      reshaped  -- a sprite (away from the border) whose pixel count leaves [0.6, 1.6] x its frame-0 count
      teleports -- a centre moving more than MAX_STEP px between consecutive frames
      smear     -- more than 4 pixels in a frame that are neither background nor a palette colour
    score = 3 - 3 * n_violations (so one violation is a confident no). `task_text` is unused: the judgment is
    about the video alone."""
    r = read_video(video)
    if r is None or not r.sprites:
        return INVALID
    seen = {s.colour: s for s in r.sprites}
    size0 = {c: r.blobs[0][c][0].size for c in seen}
    bg = np.median(r.frames[0].reshape(-1, 3), axis=0)
    palette = np.array(list(COLOURS.values()), np.float32)
    bad = set()
    last = {c: r.blobs[0][c][0] for c in seen}  # last blob seen of each sprite
    for f in range(1, len(r.frames)):
        for c in COLOURS:
            bs = r.blobs[f][c]
            if c not in seen:
                if bs:
                    bad.add(("appears", c))
                continue
            if len(bs) > 1:
                bad.add(("duplicate", c))
            prev = r.blobs[f - 1][c]
            if not bs:
                x0, y0, x1, y1 = last[c].box  # leaving the view is fine for a sprite last seen at its border
                if min(x0, y0) > 1 and max(x1, y1) < W - 2:
                    bad.add(("vanishes", c))
                continue
            last[c] = bs[0]
            if not bs[0].touches_border and not 0.6 <= bs[0].size / size0[c] <= 1.6:
                bad.add(("reshaped", c))
            if prev and not _clipped(prev[0], size0[c]) and not _clipped(bs[0], size0[c]):
                if max(abs(bs[0].cx - prev[0].cx), abs(bs[0].cy - prev[0].cy)) > MAX_STEP:
                    bad.add(("teleports", c))
        px = r.frames[f].reshape(-1, 3)
        off_bg = np.abs(px - bg).max(-1) > 40
        off_palette = np.linalg.norm(px[:, None] - palette[None], axis=-1).min(-1) >= world.COLOUR_TOL
        if (off_bg & off_palette).sum() > 4:
            bad.add(("smear", ""))
    why = ", ".join(f"{k} {c}".strip() for k, c in sorted(bad))
    return Judgment(not bad, 3.0 - 3.0 * len(bad), why)


JUDGES = {"task": judge_task, "agent": judge_agent, "consistency": judge_consistency}


def judge_all(video, task_text: str) -> dict[str, Judgment]:
    """All three WorldTasks-Bench judgments of one video (App. A.7)."""
    r = read_video(video)
    return {k: (j(r, task_text) if r is not None else INVALID) for k, j in JUDGES.items()}
