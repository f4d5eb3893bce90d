"""Can the tests fail? Change one line of an equation or its wiring at a time, run the tests that guard that file,
and report each change the tests let through ("survived"). Not part of the suite (it runs the suite's files again
and again: about two hours on two cores -- stop 84's 128 changes took 43 min, stop 85's 38 took 41, stop 86's 22 took
29 -- most of it train.py's); run it after changing a formula or its tests:

    python tests/mutants.py                 # every change below
    python tests/mutants.py --only rl.py    # the changes to some files (comma-separated)
    python tests/mutants.py --what "Eq. 9"  # the changes whose description says this

Each change is (old line(s), new line(s), what it breaks): a sign, a factor, an axis, a threshold, a flag that does
not arrive. The changes are made in a copy of the tracked files, never here. A change whose tests run past --timeout
(a loop it made endless) is stopped and reported. Exit status 1 if any change survives, times out or no longer
matches the code (then update the list beside the code it follows)."""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
UNIT = ["tests/test_rl.py", "tests/test_distill.py", "tests/test_flow.py"]
JUDGES = ["tests/test_models.py", "tests/test_world_reward.py", "tests/test_distill.py"]
SCORES = [f"tests/test_report.py::test_{name}" for name in (
    "denominators_count_discarded_judgments", "still_videos_counts_videos_where_nothing_moved",
    "mean_and_spread_over_seeds", "pull_is_a_against_y_standardised_within_its_group", "subgroup_scores_for_fig7")] + [
    f"tests/test_scripts.py::test_{name}" for name in (
        "compare_runs_on_fake_runs", "rank_rdistill_ranks_within_groups_the_rollouts_it_draws")]
REPORT = [f"tests/test_report.py::test_{name}" for name in (
    "denominators_count_discarded_judgments", "a_finished_run_is_reused_only_for_the_same_command_and_base",
    "each_experiment_sets_what_its_figure_says_it_does")]

# file (and what part of it) -> (the test files to run, [(old, new, what it breaks)])
MUTANTS = {
    "flow.py": (UNIT, [
        ("    mu = x + dt * (v - sb.pow(2) * (x - tb * v) / (2 * (1 - tb)))",
         "    mu = x + dt * (v + sb.pow(2) * (x - tb * v) / (2 * (1 - tb)))", "the SDE's score term, its sign"),
        ("    mu = x + dt * (v - sb.pow(2) * (x - tb * v) / (2 * (1 - tb)))",
         "    mu = x + dt * (v - sb.pow(2) * (x - tb * v) / (1 - tb))", "the SDE's score term, its 1/2"),
        ("    s = sig * dt ** 0.5 ", "    s = sig * dt ", "the SDE step's std sigma sqrt(dt)"),
        ("    log_prob = (-0.5 * z2 - _bcast(s.log(), x) - 0.5 * math.log(2 * math.pi)).flatten(1).mean(1)",
         "    log_prob = (-0.5 * z2 - _bcast(s.log(), x)).flatten(1).mean(1)", "the Gaussian log-density's constant"),
        ("    return noise_level * ((1 - t) / t).sqrt()", "    return noise_level * (t / (1 - t)).sqrt()",
         "sigma_t in Flow-GRPO's time convention"),
        ("        x = x + (ts[k + 1] - ts[k]) * v_theta(x, t)",
         "        x = x + (ts[k + 1] - ts[k]) * v_theta(x, ts[k + 1].expand(x.shape[0]))", "Euler at the step's end"),
        ("        return v_u + scale * (v_cond(x, t) - v_u)",
         "        return v_cond(x, t) + scale * (v_cond(x, t) - v_u)",
         "guidance from the conditional field"),
        ("    return (1 - t) * x_0 + t * x_1", "    return t * x_0 + (1 - t) * x_1", "Eq. 2's path run backwards"),
        ("    err = (v_theta(x_t, t) - (x_1 - x_0)).pow(2)", "    err = (v_theta(x_t, t) - (x_0 - x_1)).pow(2)",
         "the flow-matching target's sign"),
        ("    t = t.clamp(min=t_min)\n", "    t = t.clamp(min=t_min / 10)\n", "sigma_t clamped below the first step"),
        ("            x_next = mu + _bcast(s, x) * noises[k]", "            x_next = mu + noises[k]",
         "given noises not scaled by the step's std"),
    ]),
    "distill.py": (UNIT, [
        ("    return torch.cat([to_go[:, 1:], torch.zeros_like(to_go[:, :1])], 1)", "    return to_go",
         "App. A.3's credit to go includes its own term"),
        ("    return terms if per_step else terms.sum(1)", "    return terms if per_step else terms.mean(1)",
         "Eq. 9 as a mean, not the Riemann sum"),
        ("        terms.append(-(ts[k + 1] - ts[k]) * l_k)", "        terms.append((ts[k + 1] - ts[k]) * l_k)",
         "Eq. 9's sign"),
        ("    ks = torch.arange(S)\n", "    ks = torch.arange(S + 1)\n", "a state draw that can pick x_1"),
        ("        g = (mu_fake - mu_real) / norm", "        g = (mu_real - mu_fake) / norm", "DMD's direction"),
        ("    return x_t + flow._bcast(1 - t, x_t) * model(x_t, t, c)",
         "    return x_t + flow._bcast(t, x_t) * model(x_t, t, c)", "the clean estimate in the other convention"),
        ("            m.lora_B.data.zero_()", "            pass", "a fake score that keeps the Executor's LoRA"),
        ("        x_hat = x_t + flow._bcast(1 - t, x_t) * v_D ", "        x_hat = x_t + flow._bcast(t, x_t) * v_D ",
         "the motion weight's clean estimate"),
        ("    return (model if teacher is None else teacher)(x_t, t, c_D)", "    return model(x_t, t, c_D)",
         "Alg. 2's teacher ignored"),
        ("    return discrepancy(model, x_t, t, c_E, c_D, teacher, motion_weight).mean()",
         "    return discrepancy(model, x_t, t, c_D, c_D, teacher, motion_weight).mean()", "Eq. 3's student under c_D"),
        ("    x_t, t = xs[k, rows].detach(), ts[k]", "    x_t, t = xs[k, rows], ts[k]", "Eq. 11 without sg(x_t)"),
        ("        v_D = teacher_velocity(model, xs[k], t, c_D, teacher) if teacher_v is None else teacher_v[k]",
         "        v_D = teacher_velocity(model, xs[k], t, c_E, teacher) if teacher_v is None else teacher_v[k]",
         "Eq. 9's Demonstrator under c_E"),
        ("        t = ts[k].expand(B)\n        v_E", "        t = ts[k + 1].expand(B)\n        v_E",
         "Eq. 9's terms at the step's end"),
        ("    with torch.no_grad(), (models.adapters_disabled(model) if teacher is None else contextlib.nullcontext"
         "()):",
         "    with torch.no_grad():", "the Demonstrator with the Executor's LoRA on"),
        ("        ks = ks[(t_grid >= window[0] - 1e-6) & (t_grid < window[1] - 1e-6)]",
         "        ks = ks[(t_grid >= window[0] - 1e-6)]", "a state window without its upper end"),
        ("        x_t = flow.interpolate(eps, x.detach(), t) ", "        x_t = flow.interpolate(x.detach(), eps, t) ",
         "DMD's re-noising in the other convention"),
        ("        mu_fake = _denoise(fake, x_t, t, c_E)", "        mu_fake = _denoise(fake, x_t, t, c_D)",
         "DMD's fake score under c_D"),
        ("    return (_denoise(fake, x_t, t, c_E) - x.detach()).pow(2).mean()",
         "    return (_denoise(fake, x_t, t, c_E) - x_t).pow(2).mean()", "Eq. 18's target the noisy state"),
        ('        p.requires_grad_("lora_" in n)', "        p.requires_grad_(True)",
         "the fake score training the base"),
    ]),
    "rl.py": (UNIT, [
        ("        A[m] = (x - x.mean()) / (x.std(unbiased=False) + eps)",
         "        A[m] = (x - x.mean()) / (x.std() + eps)", "the group std with 1/(G-1)"),
        ("            A = torch.where(good, (A - a.mean()) / (a.std(unbiased=False) + eps), torch.zeros_like(A))",
         "            pass", "gdpo without its batch standardisation"),
        ("    return A.clamp(-clip, clip) if clip else A", "    return A", "no advantage clip"),
        ("    return torch.maximum(-A * ratio, -A * ratio.clamp(1 - eps, 1 + eps))",
         "    return torch.minimum(-A * ratio, -A * ratio.clamp(1 - eps, 1 + eps))", "PPO's max as a min"),
        ("    return _sq(mu_p - mu_q) / (2 * s.pow(2))", "    return _sq(mu_p - mu_q) / (s.pow(2))",
         "the Gaussian KL's 1/2"),
        ("        return s * ((err + 1e-10).pow(power) - 1e-10 ** power) / power",
         "        return s * ((err + 1e-10).pow(power) - 1e-10 ** power)", "generalised Huber without 1/p"),
        ('    if kind == "t":\n        return s * err', '    if kind == "t":\n        return err', "AWM's t weighting"),
        ("        return s * (err + 1e-10).sqrt()", "        return (err + 1e-10).sqrt()", "AWM's Huber weighting"),
        ("            t = 0.98 * strata", "            t = 0.98 * torch.rand_like(strata)", "unstratified times"),
        ("    pos, neg = (1 - b) * v_old + b * v, (1 + b) * v_old - b * v",
         "    pos, neg = (1 + b) * v_old - b * v, (1 - b) * v_old + b * v", "NFT's implicit policies swapped"),
        ("        ratio = (logp.mean(0) - old.mean(0)).exp() ", "        ratio = (logp - old).exp().mean(0) ",
         "AWM's sum_first as exp_first"),
        ("    loss = -(_per_step(A) * lp).sum(1).mean()", "    loss = -(_per_step(A) * lp).mean()",
         "GRPO's log p(tau) as a mean over steps"),
        ("        A = A.T.gather(0, k)", "        A = A.T.gather(0, k.clamp(max=0))", "AWM's per-step A at step 0"),
        ("    return l_rl if (l_anchor is None or beta_d == 0) else l_rl + beta_d * l_anchor",
         "    return l_rl if (l_anchor is None or beta_d == 0) else l_rl + l_anchor", "Eq. 12 without beta_d"),
        ("    terms = [weights[k] * r for k, r in rewards.items() if weights.get(k, 0) != 0]",
         "    terms = [r for k, r in rewards.items() if weights.get(k, 0) != 0]", "Eq. 10 without its lambdas"),
        ("        m = (groups == g) & ok", "        m = groups == g", "a NaN reward entering its group's mean"),
        ("    ratio = (lp - ro.log_probs).exp()", "    ratio = (ro.log_probs - lp).exp()",
         "Flow-GRPO's ratio inverted"),
        ("        kl = torch.stack(kls).mean()\n        loss = loss + cfg.kl_beta * kl",
         "        kl = torch.stack(kls).mean()\n        loss = loss - cfg.kl_beta * kl", "Flow-GRPO's KL rewarded"),
        ("        kl = _sq(v - _reference(model, x_t, t, c)).mean()\n        loss = loss + cfg.kl_beta * kl",
         "        kl = _sq(v - _reference(model, x_t, t, c)).mean()\n        loss = loss - cfg.kl_beta * kl",
         "AWM's KL rewarded"),
        ("    with torch.no_grad(), models.adapters_disabled(model):\n        return model(x, t, c)",
         "    with torch.no_grad():\n        return model(x, t, c)", "the reference policy = the current one"),
        ('        ro.draws["awm_old"] = logp.detach()\n    old = ro.draws["awm_old"]',
         '        pass\n    old = logp.detach()', "AWM's theta_old moving with theta"),
        ('        ro.draws["renoise"] = (flow.interpolate(eps, x1, t), t, x1 - eps)',
         '        ro.draws["renoise"] = (flow.interpolate(eps, x1, t), t, eps - x1)', "AWM's target's sign"),
        ("    r = (0.5 + 0.5 * (A / 5.0).clamp(-1, 1)).repeat(n_t)",
         "    r = (0.5 - 0.5 * (A / 5.0).clamp(-1, 1)).repeat(n_t)",
         "NFT's optimality reversed"),
    ]),
    "models.py": (JUDGES, [
        ("self.base, self.scale, self.enabled = base, alpha / rank, True",
         "self.base, self.scale, self.enabled = base, alpha, True", "LoRA's alpha / r"),
        ("            return self.base(x) + self.scale * (x @ self.lora_A.T) @ self.lora_B.T",
         "            return self.base(x) + (x @ self.lora_A.T) @ self.lora_B.T", "a Linear LoRA without its scale"),
        ("                m.base.weight.data += m.delta().detach()", "                pass",
         "merge_lora drops the LoRA"),
        ("            if m.enabled:\n                m.base.weight.data += m.delta().detach()",
         "            m.base.weight.data += m.delta().detach()", "merge_lora merges switched-off adapters"),
        ("        for m, e in zip(layers, before):\n            m.enabled = e",
         "        for m, e in zip(layers, before):\n            m.enabled = True", "adapters_disabled not nesting"),
        ("    moving = (x_1 - frame0[:, None]).abs().sum(2, keepdim=True) > 0.05 ",
         "    moving = (x_1 - frame0[:, None]).abs().sum(2, keepdim=True) > 5 ", "the moving-pixel threshold"),
        ("    return 1 + (weight - 1) * moving.float()", "    return weight * moving.float()",
         "the still pixels' weight"),
        ('        return self.base._conv_forward(x, self.base.weight + self.delta(), self.base.bias)',
         '        return self.base._conv_forward(x, self.base.weight, self.base.bias)',
         'a conv LoRA that does nothing'),
        ('F_.embedding(x, self.lora_B, self.base.padding_idx)',
         'F_.embedding(x, self.lora_B)', 'an embedding LoRA that trains the padding row'),
        ('    return torch.randn(n, *model.latent_shape(), generator=torch.Generator().manual_seed(seed))',
         '    return torch.randn(n, *model.latent_shape())', "the bench's noise unseeded"),
        ('        x_1 = flow.sample_ode(field, x_0[i:i + batch].to(dev), steps)',
         '        x_1 = flow.sample_ode(field, x_0[:len(prompts)].to(dev), steps)', 'each batch from the first noise'),
        ('        c_u = model.condition(frames, [""] * len(prompts)) if guidance != 1 else None',
         '        c_u = model.condition(frames, prompts) if guidance != 1 else None',
         'guidance against the prompt itself'),
        ('        gen = ((x_1.detach().float().clamp(-1, 1) + 1) * 127.5)',
         '        gen = ((x_1.detach().float().clamp(0, 1)) * 255)', 'decode in another pixel range than encode'),
    ]),
    "reward.py": (JUDGES, [
        ('        s = -1e-3  # the boundary counts as "no"', "        s = 1e-3", "the boundary a yes"),
        ("    return _graded(margin + SLACK)", "    return _graded(margin)", "the task judge without its slack"),
        ("    margin = max(world.task_margin(task.kind, task.target, a, t) for a in agents for t in targets)",
         "    margin = min(world.task_margin(task.kind, task.target, a, t) for a in agents for t in targets)",
         "the worst blob instead of the best"),
        ("        return _graded(min(_max_disp(tracks[task.agent]) - 0.75, 1.25 - max(others, default=0.0)))",
         "        return _graded(_max_disp(tracks[task.agent]) - 0.75)", "the agent judge ignores bystanders"),
        ("    return _graded(min(shift - 0.75, 1.25 - spread))", "    return _graded(shift - 0.75)",
         "a camera pan without the spread test"),
        ("    return Judgment(bool(jt.yes and ja.yes), min(jt.score, ja.score), jt.why or ja.why)",
         "    return Judgment(bool(jt.yes and ja.yes), max(jt.score, ja.score), jt.why or ja.why)",
         "Fig. 10's AND as a max"),
        ("                if min(x0, y0) > 1 and max(x1, y1) < W - 2:", "                if True:",
         "leaving the view counted as vanishing"),
        ("            if not bs[0].touches_border and not 0.6 <= bs[0].size / size0[c] <= 1.6:",
         "            if not bs[0].touches_border and not 0.3 <= bs[0].size / size0[c] <= 3:", "the reshape range"),
        ("                if max(abs(bs[0].cx - prev[0].cx), abs(bs[0].cy - prev[0].cy)) > MAX_STEP:",
         "                if max(abs(bs[0].cx - prev[0].cx), abs(bs[0].cy - prev[0].cy)) > 3 * MAX_STEP:",
         "the teleport threshold"),
        ("        if (off_bg & off_palette).sum() > 4:", "        if (off_bg & off_palette).sum() > 40:",
         "the smear threshold"),
        ("    return Judgment(not bad, 3.0 - 3.0 * len(bad), why)",
         "    return Judgment(not bad, 3.0 - 3.0 * min(len(bad), 1), why)", "3 points a fault"),
        ("    score = float(logp[yes_id] - logp[no_id])", "    score = float(logp[yes_id])",
         "the VLM score without log p(no)"),
        ("    if int(logits.argmax()) not in (yes_id, no_id):", "    if False:", "a malformed answer judged"),
        ('            if len(bs) > 1:\n                bad.add(("duplicate", c))',
         '            if len(bs) > 2:\n                bad.add(("duplicate", c))',
         'a duplicate only at three blobs'),
        ('                if bs:\n                    bad.add(("appears", c))',
         '                if False:\n                    bad.add(("appears", c))', 'a new colour never appearing'),
        ('        off_bg = np.abs(px - bg).max(-1) > 40',
         '        off_bg = np.abs(px - bg).max(-1) > 400', 'no pixel off the background: no smear'),
        ('    return b.touches_border and b.size < 0.8 * size0',
         '    return b.size < 0.8 * size0', 'a shrunk blob away from the border counted as clipped'),
        ('        return _graded(-SCORE_CLIP, "agent or target not visible in the final frame")',
         '        return INVALID', 'an agent out of view as no judgment'),
        ('v.shape[0] < 2 or not np.isfinite(v).all():',
         'v.shape[0] < 2:', 'a video with NaNs read'),
    ]),
    "world.py": (JUDGES, [
        ("        return 4.0 - np.abs(a - np.asarray(target_xy, float)).max(-1)",
         "        return 4.0 - np.abs(a - np.asarray(target_xy, float)).sum(-1)", "move_to's Chebyshev distance"),
        ("        return pos - steps[:, None, :]", "        return pos + steps[:, None, :]",
         "a pan moving the world with it"),
        ("    steps = np.minimum(np.arange(F), plan.k)[:, None]", "    steps = np.arange(F)[:, None]",
         "a plan that never stops"),
        ("""        parts.append(f"{'right' if plan.vx > 0 else 'left'} {abs(plan.vx)}")""",
         """        parts.append(f"{'left' if plan.vx > 0 else 'right'} {abs(plan.vx)}")""",
         "D's left and right swapped"),
        ("    return inside & (np.abs(others - p[..., None, :]).max(-1) >= 3).all((-2, -1))",
         "    return inside & (np.abs(others - p[..., None, :]).max(-1) >= 2).all((-2, -1))", "sprites that may touch"),
        ("        if new != plan and plan_is_valid(scene, new)", "        if plan_is_valid(scene, new)",
         "a VLM mistake equal to the solution"),
        ("    return corrupt(scene, plan, err_rng) if err_rng.random() < error_rate else (plan, \"\")",
         "    return corrupt(scene, plan, err_rng) if err_rng.random() > error_rate else (plan, \"\")",
         "the error rate as the rate of correct D"),
        ("        return 0.5 - np.abs(a[..., 1] - np.asarray(target_xy, float)[..., 1])",
         "        return 0.5 - np.abs(a[..., 0] - np.asarray(target_xy, float)[..., 0])", "level_with's axis"),
        ('    return {"left": 1.0 - a[..., 0], "right": a[..., 0] - (W - 2), "top": 1.0 - a[..., 1],',
         '    return {"left": 1.0 - a[..., 0], "right": a[..., 0] - (W - 2), "top": 1.0 - a[..., 0],', "top's axis"),
        ("        return 1.0 - np.abs(np.asarray(target_xy, float) - CENTRE).max(-1)",
         "        return 1.0 - np.abs(np.asarray(target_xy, float) - CENTRE).min(-1)", "centre on one axis"),
        ('        if exclude and scene_key(scene) in exclude:\n            continue\n        frame0 = render',
         '        if False:\n            continue\n        frame0 = render', "training scenes that are the bench's"),
        ('    ok = (margins[np.arange(len(k)), k] >= 0) & (margins[np.arange(len(k)), k - 1] < 0) & valid',
         '    ok = (margins[np.arange(len(k)), k] >= 0) & valid', 'solutions that solve the task before they stop'),
        ('    if task.kind == "level_with":\n        ok &= _MOTIONS[:, 0] == 0',
         '    if task.kind == "level_with":\n        pass', 'level_with solved by a sideways move'),
        ('    return min(sols, key=lambda p: (p.k, abs(p.vx) + abs(p.vy), p.vx, p.vy))',
         '    return max(sols, key=lambda p: (p.k, abs(p.vx) + abs(p.vy), p.vx, p.vy))', "the VLM's D arriving last"),
        ('        if gaps.min() >= 4:', '        if gaps.min() >= 3:', 'scenes with touching sprites'),
        ('            if t != a:\n', '            if True:\n', 'tasks relative to the agent itself'),
        ('np.random.default_rng([seed, i]))', 'np.random.default_rng([seed, 0]))', 'one error draw for every pair'),
        ('        out.append((scene, task, describe(scene, plan_vlm), describe(scene, plan), plan_vlm, plan, err))',
         '        out.append((scene, task, describe(scene, plan), describe(scene, plan), plan_vlm, plan, err))',
         "the toy VLM's D always the solution's"),
        ('    return "camera pans" if plan.mover == -1 else f"{scene.sprites[plan.mover].name} moves"',
         '    return "camera pans" if plan.mover == -1 else "something moves"', 'a vague caption without its mover'),
    ]),
    "bench.py": (SCORES, [
        ("    succ = {k: sum(bool(j[k].yes) for j in judgments) for k in KEYS}",
         "    succ = {k: sum(j[k].yes is not False for j in judgments) for k in KEYS}", "no judgment as a success"),
        ("        succ[name], valid[name] = sum(bool(j[a].yes and j[b].yes) for j in both), len(both)",
         "        succ[name], valid[name] = sum(bool(j[a].yes or j[b].yes) for j in both), len(both)",
         "solved and by_agent as an or"),
        ('    out["avg"] = float(np.mean([out[k] for k in KEYS]))',
         '    out["avg"] = succ["avg"] / valid["avg"] if valid["avg"] else float("nan")',
         "Avg over the fully judged videos, not the columns' mean"),
        ("        counts += (diff[..., None] > levels).sum((1, 2))",
         "        counts += (diff[..., None] >= levels).sum((1, 2))", "a pixel at the level counted as moved"),
        ("        diff = (np.maximum(frame, first) - np.minimum(frame, first)).max(-1) ",
         "        diff = (np.maximum(frame, first) - np.minimum(frame, first)).min(-1) ", "moved in every channel"),
        ("    return int((moved_pixels(videos, level) == 0).sum())",
         "    return int((moved_pixels(videos, level) <= 1).sum())", "a video with one pixel moved as still"),
        ("    return float(xs.mean()), float(xs.std(ddof=1)) if len(xs) > 1 else 0.0",
         "    return float(xs.mean()), float(xs.std()) if len(xs) > 1 else 0.0", "the population sd over seeds"),
        ("    return float((A * rl.group_advantages(torch.tensor(y, dtype=torch.float32), ids)).mean())",
         "    return float((A * torch.tensor(y, dtype=torch.float32)).mean())", "pull without standardising y"),
        ('    return [{"step": r["step"], "still": float(m)} for r, m in zip(steps[window - 1:], means)]',
         '    return [{"step": r["step"], "still": float(m)} for r, m in zip(steps, means)]',
         "a trailing mean labelled at its first step"),
        ("        if j[key].yes is not None:\n            g[0] += int(j[key].yes)",
         "        if True:\n            g[0] += int(bool(j[key].yes))", "subgroups counting no judgment"),
        ("        for u in np.unique(v):\n            r[v == u] = r[v == u].mean()",
         "        for u in []:\n            r[v == u] = r[v == u].mean()", "Spearman without tied ranks"),
        ('    return family_scores(pairs, judgments, "task", lambda p: "D wrong" if p.error else "D right")',
         '    return family_scores(pairs, judgments, "task", lambda p: "D right" if p.error else "D wrong")',
         'D right and D wrong swapped'),
        ('    return family_scores(pairs, judgments, "agent", lambda p: "first-person view"',
         '    return family_scores(pairs, judgments, "task", lambda p: "first-person view"',
         'Fig. 7 right on the task score'),
        ('            c_D = model.condition(frame0, [p.d_vlm for p in ps])',
         '            c_D = model.condition(frame0, [p.d_oracle for p in ps])',
         "rank_rdistill's Demonstrator given the error-free D"),
        ('    judges = {k: w for k, w in RANK_WEIGHTS.items() if k != "distill"}',
         '    judges = RANK_WEIGHTS', 'A_judges with r_distill'),
        ('    mixed = [g for g in groups if None not in task[g] and 0 < sum(task[g]) < group]',
         '    mixed = [g for g in groups if None not in task[g]]', 'rho_task over groups with one outcome'),
    ]),
    "bench.py (evaluate)": (["tests/test_scripts.py"], [
        ('    field = {"task": lambda p: p.task.text, "vlm": lambda p: p.d_vlm, "oracle": lambda p: p.d_oracle,',
         '    field = {"task": lambda p: p.task.text, "vlm": lambda p: p.d_vlm, "oracle": lambda p: p.d_vlm,',
         "the error-free D as the toy VLM's"),
        ('        judgments = [reward.judge_all(v, p.task.text) for v, p in zip(videos, pairs)]',
         '        judgments = [reward.judge_all(v, p.task.text) for v, p in zip(videos, pairs[1:] + pairs[:1])]',
         "videos judged against the next pair's task"),
        ('still=still_videos(videos) / max(len(pairs), 1))',
         'still=still_videos(videos))', 'still as a count, not a share'),
        ('    return lambda x, t: model(x, t, c_a if float(t[0]) < t_switch else c_b)',
         '    return lambda x, t: model(x, t, c_a if float(t[0]) <= t_switch else c_b)', 'the handoff one step late'),
        ('                hits[role].append(d[head] <= 1)',
         '                hits[role].append(d.min() <= 1)', "pointing's supervised head as the best head"),
    ]),
    "report.py": (REPORT, [
        ('    score = succ / valid if valid else float("nan")', '    score = succ / n if n else float("nan")',
         "Tab. 4's score over every video, not the judged ones"),
        ("{100 * (n - valid) / max(n, 1):.1f}%", "{100 * valid / max(n, 1):.1f}%",
         "Tab. 4's failure rate as the valid share"),
        ('    "no_anchor": ("rl", ["--beta_d", "0", "--lambda_distill", "0"]),',
         '    "no_anchor": ("rl", ["--beta_d", "0"]),', "Fig. 5 (i) keeping r_distill"),
        ('    "teacher_rl": ("rl", ["--alternate", "2", "--executor_update", "off"]),',
         '    "teacher_rl": ("rl", ["--alternate", "2"]),', "Fig. 5 (iii) as Alg. 2"),
        ('BETAS = {"beta_0": 0.0, "beta_0.01": 0.01, "beta_0.1": 0.1, "wmsd": 1.0}',
         'BETAS = {"beta_0": 0.0, "beta_0.01": 0.1, "beta_0.1": 0.01, "wmsd": 1.0}', "Fig. 4 right's betas swapped"),
        ('ERRORS = {"err_0": 0.0, "wmsd": DEFAULT_ERROR_RATE, "err_0.5": 0.5}',
         'ERRORS = {"err_0": 0.0, "wmsd": 0.5, "err_0.5": DEFAULT_ERROR_RATE}', "the error rates swapped"),
        ('    return rec["cmd"] == cmd and rec.get("base") == base', '    return rec["cmd"] == cmd',
         "a run from another base reused"),
    ]),
    "train.py": (["tests/test_train.py"], [
        ("        return rl.final_loss(l_rl, l_anchor, args.beta_d), info",
         "        return rl.final_loss(l_rl, l_anchor, 1.0), info", "--beta_d not reaching Eq. 12"),
        ('            local["distill"] = distill.distill_reward_to_go(terms)', '            local["distill"] = terms',
         "per-step r_distill without the credit to go"),
        ('        local["distill"] = local["r_distill"] = terms.sum(1)',
         '        local["distill"] = local["r_distill"] = terms.mean(1)', "r_distill as a mean of Eq. 9's terms"),
        ('    weights = {"task": args.lambda_task, "distill": args.lambda_distill, "consistency": args.lambda_cons}',
         '    weights = {"task": args.lambda_task, "distill": 1.0, "consistency": args.lambda_cons}',
         "--lambda_distill not reaching Eq. 10"),
        ("        l_anchor = (distill.anchor_loss(model, (p.ro.xs, p.ro.ts), p.c_E, p.c_D, gen, teacher, p.shard,",
         "        l_anchor = (distill.anchor_loss(model, (p.ro.xs, p.ro.ts), p.c_D, p.c_D, gen, teacher, p.shard,",
         "the anchor's Executor under c_D"),
        ("                    distill.rollout(model, b.x_0[p.rows], p.c_D, train_steps(args), demonstrator=True))",
         "                    distill.rollout(model, b.x_0[p.rows], p.c_E, train_steps(args), demonstrator=True))",
         "Fig. 5 (iii)'s states under c_E"),
        ("        p.vD = distill.teacher_velocities(model, (p.ro.xs, p.ro.ts), p.c_D, teacher) if args.lambda_distill",
         "        p.vD = distill.teacher_velocities(model, (p.ro.xs, p.ro.ts), p.c_D, None) if args.lambda_distill",
         "Alg. 2's teacher ignored by Eq. 9"),
        ("    for _ in range(args.inner_epochs):", "    for _ in range(1):", "--inner_epochs ignored"),
        ("off_policy_loss(model, distill.rollout(model, x_0, c_D, train_steps(args), True),",
         "off_policy_loss(model, distill.rollout(model, x_0, c_E, train_steps(args)),",
         "--variant off on the Executor's states"),
        ("on_policy_loss(model, distill.rollout(model, x_0, c_E, train_steps(args)),",
         "on_policy_loss(model, distill.rollout(model, x_0, c_D, train_steps(args), True),",
         "--variant on on the Demonstrator's states"),
        ("dmd_generator(model, distill.rollout(model, x_0, c_E, train_steps(args)), c_E, gen)",
         "dmd_generator(model, distill.rollout(model, x_0, c_D, train_steps(args)), c_E, gen)",
         "DMD's generator from states under c_D"),
        ("fake_loss = distill.dmd_fake_score_loss(fake, x.detach(), c_E, gen)",
         "fake_loss = distill.dmd_fake_score_loss(fake, x.detach(), c_D, gen)", "Eq. 18 under c_D"),
        ("model.condition(frame0, tasks), model.condition(frame0, descs)",
         "model.condition(frame0, tasks), model.condition(frame0, [pairs[i].d_oracle for i in idx])",
         "the Demonstrator given the error-free D"),
        ("world.simulate(p.scene, p.plan_oracle)) for p in ps])", "world.simulate(p.scene, p.plan_vlm)) for p in ps])",
         "paired SFT on the toy VLM's plans"),
        ("loss = video_loss(model, videos, labels, args)", "loss = video_loss(model, videos, tasks, args)",
         "+SFT's videos under the batch's tasks"),
        ("        return rl.final_loss(l_rl, l_base, args.beta_phi), {}",
         "        return rl.final_loss(l_rl, l_base, 0.0), {}", "--beta_phi ignored"),
        ("            e.lerp_(p, 1 - decay)", "            e.lerp_(p, decay)", "the EMA's weights swapped"),
        ("                p.copy_(w)", "                pass", "the averaged weights left in training"),
        ("            if args.alternate > 0 and step % args.alternate == 0:",
         "            if args.alternate > 0 and step % args.alternate == 1:", "Alg. 2's rounds on the wrong steps"),
        ('        if ema is not None and not rec.get("demo_round") and ',
         "        if ema is not None and ", "the Executor's EMA updated in phi's rounds"),
        ('        opt.load_state_dict(state["opt"])\n', '        pass\n', "a resumed run's optimizer restarted"),
        ('        gen.set_state(state["gen"])\n', '        pass\n', "a resumed run's sampling noise restarted"),
        ('        rng.bit_generator.state = state["rng_numpy"]\n',
         '        pass\n', "a resumed run's task draws restarted"),
        ('            demo_net.load_state_dict(state["demo_lora"], strict=False)',
         '            pass', "a resumed Alg. 2 run's Demonstrator phi reset"),
        ('    if step >= args.steps:\n', '    if step > args.steps:\n', 'a finished run resumed'),
        ('                 bench.DEMO_ROW: base_evaluation(model, args, demonstrator=True)}',
         '                 bench.DEMO_ROW: base_evaluation(model, args)}', 'the Demonstrator row given T'),
        ('        if step % args.eval_every == 0 and step < args.steps:',
         '        if step % args.eval_every == 1 and step < args.steps:', "evaluations off --eval_every's steps"),
        ('            merged = models.merge_lora(model)\n',
         '            merged = model\n', 'the Executor saved unmerged'),
        ('                with weights_swapped(params, ema):\n                    res = evaluate_executor(model, args)',
         '                if True:\n                    res = evaluate_executor(model, args)',
         'mid-run evaluations without the EMA'),
        ('groups=torch.arange(N) // G,', 'groups=torch.arange(N) % G,', 'a group of G different tasks'),
        ('            p.grad /= _world()\n    gnorm = torch.nn.utils.clip_grad_norm_(params, 1.0)',
         '            p.grad /= _world()\n    gnorm = torch.nn.utils.clip_grad_norm_(params, 1e9)',
         'no gradient clipping (Table 3: 1)'),
        ('    weights = {"task": args.lambda_task, "consistency": args.lambda_cons}',
         '    weights = {"task": args.lambda_task}', "phi's rounds without the consistency reward"),
        ('           "solved": [np.nan if a.yes is None else float(a.yes and bool(b.yes)) for a, b in zip(jts, jcs)],',
         '           "solved": [np.nan if a.yes is None else float(bool(a.yes)) for a, b in zip(jts, jcs)],',
         'solved without consistency'),
        ('    res["invalid"] = torch.isnan(res["task"]) | torch.isnan(res["consistency"])',
         '    res["invalid"] = torch.isnan(res["task"])', 'an unjudged consistency not counted invalid'),
        ('        if step % args.eval_every == 0 or step == args.steps:',
         '        if step % args.eval_every == 0:', 'a distill run without its last evaluation'),
    ]),
    "train.py (pretrain)": (["tests/test_train.py", "tests/test_models.py"], [
        ('    w = (1 - t).clamp(min=model.cfg.min_one_minus_t)',
         '    w = t.clamp(min=model.cfg.min_one_minus_t)', "pretraining's weight in t, not 1 - t"),
        ('.reshape(-1, 1, 1, 1, 1) ** args.loss_power \\',
         '.reshape(-1, 1, 1, 1, 1) \\', '--loss_power ignored'),
        ('models.moving_pixel_weight(x_1, c["frame0"], args.motion_weight)',
         'models.moving_pixel_weight(x_1, c["frame0"], 1.0)', '--motion_weight ignored'),
        ('    c = model.condition(videos[:, 0], captions)\n',
         '    c = model.condition(videos[:, 0], [""] * len(captions))\n', 'the video loss without its captions'),
        ('    exclude = world.bench_scene_keys()',
         '    exclude = set()', "the bench's scenes in pretraining"),
        ('    models.save_checkpoint(ema, out,',
         '    models.save_checkpoint(model, out,', 'the trained weights saved, not their average'),
        ('min(args.ema, step / (step + 10)))',
         'args.ema)', 'the EMA without its warm-up'),
        ('args.p_goal, exclude, places=True,',
         '0.0, exclude, places=True,', '--p_goal not reaching pretraining'),
        ('            loss = loss + args.point_weight * point',
         '            loss = loss + point', '--point_weight as 1'),
        ('point = pointing_loss(model, videos[:, 0], captions, places, args.point_goal_only)',
         'point = pointing_loss(model, videos[:, 0], captions, places)', '--point_goal_only ignored'),
        ('    idx = (pl[..., 1].nan_to_num() * model.cfg.size + pl[..., 0].nan_to_num()).long()',
         '    idx = (pl[..., 0].nan_to_num() * model.cfg.size + pl[..., 1].nan_to_num()).long()',
         "the pointing target's pixel transposed"),
        ('    return -(logp * valid).sum() / valid.sum().clamp(min=1)',
         '    return -(logp * valid).mean()', 'the pointing loss averaged over terms it does not have'),
    ]),
    "models.py (real backends)": (["tests/test_real_backends.py"], [
        ("        return z * s / k + m if inverse else (z - m) * k / s",
         "        return (z - m) * k / s if inverse else z * s / k + m", "LTX-2's latent normalisation inverted"),
        ("        sigma = (1 - t).float() * self.transformer", "        sigma = t.float() * self.transformer",
         "LTX-2's sigma = t"),
        ("        per_token[:, :h * w] = 0 ", "        per_token[:, :h * w] = 1 ", "LTX-2's first frame as noise"),
        ("[:, :, 1:]   # drop the first frame", "[:, :, :-1]   # drop the first frame",
         "LTX-2 dropping the last frame"),
        ("        return -v_sigma ", "        return v_sigma ", "LTX-2's velocity in sigma's direction"),
        ("        mask[:, :, 0] = 1\n", "        mask[:, :, :] = 1\n", "HunyuanVideo-1.5's mask on every frame"),
        ("        sigma = (1 - t).float()  ", "        sigma = t.float()  ", "HunyuanVideo-1.5's sigma = t"),
        ('    rows = [index.index(j) for j in range(len(slot))]',
         '    rows = list(range(len(slot)))', "distinct_condition's rows not the first of each"),
        ('        if missing:\n', '        if False:\n', 'a LoRA file for another model loaded silently'),
    ]),
}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", default="", help="comma-separated files of MUTANTS, e.g. rl.py,distill.py")
    p.add_argument("--what", default="", help="only the changes whose description contains this, e.g. \"Eq. 9\"")
    p.add_argument("--timeout", type=int, default=1200, help="seconds one change's tests may run (default 1200)")
    args = p.parse_args(argv)
    only = [f for f in args.only.split(",") if f]
    file_of = {key: key.split()[0] for key in MUTANTS}          # "models.py (real backends)" -> models.py
    unknown = [f for f in only if f not in file_of.values()]
    if unknown:
        choices = ", ".join(dict.fromkeys(file_of.values()))
        p.error(f"--only: no changes listed for {', '.join(unknown)}; choose from {choices}")
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    todo = [(file_of[key], *m, tests) for key, (tests, ms) in MUTANTS.items() if not only or file_of[key] in only
            for m in ms if args.what in m[2]]
    bad, t0 = [], time.time()
    with tempfile.TemporaryDirectory() as tree:
        for f in files:
            os.makedirs(os.path.join(tree, os.path.dirname(f)), exist_ok=True)
            shutil.copy2(os.path.join(ROOT, f), os.path.join(tree, f))
        for i, (f, old, new, what, tests) in enumerate(todo, 1):
            path = os.path.join(tree, f)
            with open(path) as fh:
                src = fh.read()
            if src.count(old) != 1:
                verdict = f"STALE ({src.count(old)} matches)"
            else:
                with open(path, "w") as fh:
                    fh.write(src.replace(old, new))
                # its own process group: a change that makes a loop endless (a scene that never gets a valid plan)
                # is stopped after --timeout with the runs its tests started, and reported
                r = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests],
                                     cwd=tree, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     start_new_session=True)
                try:
                    code = r.wait(timeout=args.timeout)
                    verdict = "failed a test" if code == 1 else ("SURVIVED" if code == 0 else f"pytest exit {code}")
                except subprocess.TimeoutExpired:
                    os.killpg(r.pid, signal.SIGKILL)
                    r.wait()
                    verdict = f"TIMED OUT after {args.timeout} s"
                with open(path, "w") as fh:
                    fh.write(src)
            if verdict != "failed a test":
                bad.append(f"{f}: {what}: {verdict}")
            print(f"[{i:2d}/{len(todo)}] {time.time() - t0:6.0f} s  {f}: {what}: {verdict}", flush=True)
    print(f"{len(todo) - len(bad)} of {len(todo)} changes fail a test" + "".join(f"\n  {b}" for b in bad))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
