"""The README and docs/: every relative link and anchor resolves, every code name and flag they quote is in the code,
CI runs the README's test command, the README's Tables 1 and 4 are results/report.md's, each mean ± sd and each
score a summary quotes stands on a page that measured it, and a mean ± sd given with its seeds' values, or a score
with its counts, adds up."""
import os
import re

from conftest import per_seed, table_after

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGES = ["README.md"] + [os.path.join("docs", f) for f in sorted(os.listdir(os.path.join(ROOT, "docs")))
                         if f.endswith(".md")]


def read(*path: str) -> str:
    """A file of the repository, by its path's parts from the root."""
    return open(os.path.join(ROOT, *path), encoding="utf-8").read()


def given_t_brief(given_t: str) -> str:
    """docs/given-t.md's brief: its section "What each base and setting adds, in brief", which quotes the others."""
    return given_t[given_t.index("## What each base and setting adds, in brief"):given_t.index("## A base that")]


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, each space a hyphen."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(text: str) -> set:
    return {slug(h) for h in re.findall(r"^#+ (.*)$", text, re.M)} | set(re.findall(r'<a id="([^"]+)"', text))


def links(text: str) -> list:
    """Markdown link and image targets outside fenced code, web addresses left out."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    return [t for t in re.findall(r"\]\(([^)\s]+)\)", text) if not re.match(r"[a-z]+:", t)]


def test_slug_matches_githubs_rule():
    assert slug("A third control: T's words as a goal caption (base (f)) — the form") == \
        "a-third-control-ts-words-as-a-goal-caption-base-f--the-form"


def test_every_link_and_anchor_resolves():
    text = {p: read(p) for p in PAGES}
    bad, n = [], 0
    for page, t in text.items():
        for target in links(t):
            n += 1
            path, _, anchor = target.partition("#")
            dest = os.path.normpath(os.path.join(os.path.dirname(page), path)) if path else page
            if not os.path.exists(os.path.join(ROOT, dest)):
                bad.append(f"{page}: {target} (no such file)")
            elif anchor and (dest not in text or anchor not in anchors(text[dest])):
                bad.append(f"{page}: {target} (no such anchor)")
    assert n > 50 and not bad, "\n".join(bad)


def test_ci_runs_the_readmes_test_command():
    readme = read("README.md")
    command = re.search(r"## Tests\s+```bash\n(.+?)\n```", readme).group(1).strip()
    ci = read(".ci", "run").strip().splitlines()
    assert ci[-1].strip() == command


def test_readme_installs_what_ci_installs():
    """The README's install block: the same torch pin as .ci/run, installed before the requirements, which are
    installed under a constraints file that holds that pin (else pip may swap in a CUDA build of torch)."""
    readme = read("README.md")
    block = re.search(r"## Install\n.*?```bash\n(.+?)\n```", readme, re.S).group(1)
    steps = [line.split("#")[0].split() for line in block.splitlines()]
    ci = read(".ci", "run")
    pin = re.search(r"pip install [^\n]*?(torch==[0-9.]+)", ci).group(1)
    torch_at = next(i for i, s in enumerate(steps) if s[:2] == ["pip", "install"] and pin in s)
    req_at = next(i for i, s in enumerate(steps) if "requirements.txt" in s)
    constraints = steps[req_at][steps[req_at].index("-c") + 1]
    assert torch_at < req_at and steps[req_at][:2] == ["pip", "install"]
    assert any(s[:3] == ["echo", pin, ">"] and s[3] == constraints for s in steps[:req_at])


MODULES = ("flow", "models", "distill", "rl", "reward", "world", "bench", "train", "report")


def code_names(text: str) -> list:
    """The repository's names a page quotes as code: `module.attr[.attr]` (a call's arguments allowed) for the modules
    above, and `tests/file.py::test_name`; file names such as `rl.jsonl` or `train.py` are not names."""
    names = re.findall(r"`((?:%s)\.[A-Za-z_][\w.]*)(?:\([^`]*\))?`" % "|".join(MODULES), text)
    return ([n for n in names if not re.search(r"\.(py|jsonl|json|pt|png|gif|md)$", n)]
            + re.findall(r"`(tests/test_\w+\.py::\w+)", text))


def test_code_names_in_the_docs_resolve():
    """A reader follows a name from the README or docs/ into the code: each must still be there (a renamed function
    leaves no stale name behind). Older stops' pages name what the code held then in words, not as code."""
    import importlib
    bad, n = [], 0
    for page in PAGES:
        for name in code_names(read(page)):
            n += 1
            if "::" in name:
                path, test = name.split("::")
                ok = re.search(rf"^def {test}\(", read(path), re.M)
            else:
                module, *attrs = name.split(".")
                obj, ok = importlib.import_module(module), True
                for a in attrs:
                    ok = ok and hasattr(obj, a)
                    obj = getattr(obj, a, None)
            if not ok:
                bad.append(f"{page}: {name}")
    assert n > 100 and not bad, "\n".join(bad)


def test_code_names_reads_names_not_files():
    assert code_names("`rl.awm` and `bench.evaluate(model, pairs)`, `rl.jsonl`, `train.py`, `RL.x`, "
                      "`tests/test_rl.py::test_awm_weight` and `flow.sde_step`") == \
        ["rl.awm", "bench.evaluate", "flow.sde_step", "tests/test_rl.py::test_awm_weight"]


def cited(doc: str) -> set:
    """Equation numbers a docstring cites: "Eq. 9", "Eqs. 3, 4, 9, 11", "Eqs. 19/21", "Eqs. 21-22" (a range)."""
    nums = set()
    for group in re.findall(r"Eqs?\.\s*([0-9][0-9,/\-– ]*(?:and [0-9]+)?)", doc):
        for part in re.split(r"[,/ ]|and", group):
            a, _, b = part.replace("–", "-").partition("-")
            if a.isdigit():
                nums |= set(range(int(a), int(b) + 1)) if b.isdigit() else {int(a)}
    return nums


def test_cited_reads_lists_and_ranges():
    assert cited("Eq. 9: r = ...; Eqs. 3, 4, 9, 11 and Eqs. 19/21, Eqs. 13–15; Eq. 2, d x") == \
        {2, 3, 4, 9, 11, 13, 14, 15, 19, 21}


def test_equation_index_names_functions_that_cite_them():
    """README's "Every equation" table: each name resolves to a function whose docstring cites the row's equations
    (or App./Alg./reference label), together the row's functions cite all of them, and Eqs. 1-22 all have a row."""
    import importlib
    readme = read("README.md")
    table = readme.split("### Every equation, and the function that holds it", 1)[1].split("\n\n")[2]
    rows = [r.split(" | ") for r in table.splitlines()[2:]]
    covered, bad = set(), []
    for paper, _, where in rows:
        paper, names = paper.strip("| "), re.findall(r"`([\w.]+)`", where)
        want = cited(paper) or {paper}
        got = set()
        for name in names:
            module, _, attr = name.rpartition(".")
            doc = getattr(importlib.import_module(module), attr).__doc__ or ""
            have = cited(doc) if paper.startswith("Eq") else ({paper} if paper in doc else set())
            if not have & want:
                bad.append(f"{name} cites none of {paper}")
            got |= have
        if not want <= got:
            bad.append(f"{paper}: {sorted(map(str, want - got))} cited by none of {names}")
        covered |= want
    assert not bad, "\n".join(bad)
    assert set(range(1, 23)) <= covered, sorted(set(range(1, 23)) - covered)


# flags the pages quote for other programs: pytest, pip, torchrun
OUTSIDE_FLAGS = {"--durations", "--index-url", "--master_port", "--nproc_per_node"}


def quoted_flags(text: str) -> set:
    """The `--flag`s a page quotes in code: in fenced blocks and in `inline code`."""
    fenced = re.findall(r"```[a-z]*\n(.*?)```", text, re.S)
    inline = re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))
    return {f for code in fenced + inline for f in re.findall(r"(?<![\w-])(--[a-z][\w-]*)", code)}


def script_flags(main) -> set:
    """The flags a script's parser takes, read from its --help: the option lines only, not its description."""
    import contextlib
    import io
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        try:
            main(["--help"])
        except SystemExit:
            pass
    lines = [re.split(r"\s{2,}", line.strip())[0] for line in out.getvalue().split("options:")[-1].splitlines()
             if re.match(r"\s+(-\w, )?--", line)]
    return {f for line in lines for f in re.findall(r"--[a-z][\w-]*", line)}


def test_quoted_flags_reads_code_only_and_script_flags_reads_options_only():
    assert quoted_flags("a --word in prose, `train.py --toy --no-eval_crowded`\n```bash\nbench.py --n 6\n```") == \
        {"--toy", "--no-eval_crowded", "--n"}
    import world
    flags = script_flags(world.main)
    assert {"--n", "--out", "--composition", "--dataset", "--help"} <= flags and "--bench" not in flags


def test_every_flag_the_docs_quote_is_a_flag_of_ours():
    """Every flag a command in the README or docs/ quotes is a flag of train.py, bench.py, report.py, world.py or
    tests/mutants.py (or of pytest, pip, torchrun): a renamed or dropped flag leaves no stale command behind."""
    import bench
    import mutants
    import report
    import train
    import world
    ours = set().union(*(script_flags(m.main) for m in (train, bench, report, world, mutants)))
    quoted = {page: quoted_flags(read(page)) for page in PAGES}
    bad = [f"{page}: {f}" for page in PAGES for f in sorted(quoted[page] - ours - OUTSIDE_FLAGS)]
    assert len(ours) > 100 and not bad, "\n".join(bad)


def test_table_after_reads_the_first_table_after_its_marker():
    text = "x\n| a | b |\n|---|---|\n| no | 0 |\n## T\nsome words\n\n| m | s |\n|---|---|\n| A | 1 | 2 |\n| B | 3 |\n"
    assert table_after(text, "## T") == {"A": ["1", "2"], "B": ["3"]}


def test_readmes_tables_1_and_4_are_the_reports():
    """The README's Table 1 and Table 4 are results/report.md's, the numbers `python report.py results` wrote: the
    same rows in the same order, each README row the start of the report's (Table 4 in the README leaves out
    `solved`). A report rerun that changes a number, or a hand edit of one side, fails here."""
    readme = read("README.md")
    report = read("results", "report.md")
    for ours, theirs in (("**Table 1**", "## Table 1:"), ("**Table 4**", "## Table 4:")):
        a, b = table_after(readme, ours), table_after(report, theirs)
        assert list(a) == list(b) and len(a) >= 5, (ours, list(a), list(b))
        for model, cells in a.items():
            assert len(cells) >= 4 and b[model][:len(cells)] == cells, (ours, model, cells, b[model])


def test_every_mean_and_spread_a_summary_quotes_is_on_the_page_that_measured_it():
    """Each "mean ± sd" the README quotes (about 200) stands in results/report.md or a page of docs/, where its runs
    and commands are (whitespace folded: a number may wrap across lines); each that docs/given-t.md's brief quotes
    stands in its sections or another page. A number typed into a summary alone, or left behind when its page was
    remeasured, fails here."""
    fold = lambda p: re.sub(r"\s+", " ", read(p))  # noqa: E731
    brief = given_t_brief(fold(os.path.join("docs", "given-t.md")))
    sources = " ".join(fold(p) for p in [os.path.join("results", "report.md")] + PAGES[1:])
    for summary, pages in ((fold("README.md"), sources), (brief, sources.replace(brief, ""))):
        quoted = re.findall(r"\d\.\d{3} ± \d\.\d{3}", summary)
        assert len(quoted) > 40 and not [q for q in quoted if q not in pages], \
            sorted({q for q in quoted if q not in pages})


def numbers(text: str) -> set:
    """The numbers with three decimals a text holds, as written ("0.458"; "10.458" and "0.4581" are not it)."""
    return set(re.findall(r"(?<![\d.])\d\.\d{3}(?![\d])", text))


def test_numbers_reads_three_decimals_whole():
    assert numbers("0.458, 10.458 and 0.4581; 1.000 ± 0.020 (3/200; 0.0%) 0.45") == {"0.458", "1.000", "0.020"}


def test_every_score_a_summary_quotes_is_on_a_page_that_measured_it():
    """The rule above for every number with three decimals (about 240 in the README, a single seed's score or a
    difference too): each stands in results/report.md (its per-seed table included) or a page of docs/, and each in
    docs/given-t.md's brief in its sections or another page. The one kind of number a summary may compute itself is
    the shipped base table's Avg, the mean of its task, agent and consistency scores: checked here instead."""
    readme, brief = read("README.md"), given_t_brief(read("docs", "given-t.md"))
    base = table_after(readme, "### The shipped base (issue 2)")
    avgs = set()
    for condition, (task, agent, cons, avg) in base.items():
        scores = [float(c.split(" (")[0]) for c in (task, agent, cons)]
        assert f"{sum(scores) / 3:.3f}" == avg, (condition, scores, avg)
        avgs.add(avg)
    assert len(avgs) == 3, base
    sources = [read(p) for p in [os.path.join("results", "report.md")] + PAGES[1:]]
    for summary, pages in ((readme, sources), (brief, [s.replace(brief, "") for s in sources])):
        found = set().union(*map(numbers, pages))
        quoted = numbers(summary) - (avgs if summary is readme else set())
        assert len(quoted) > 80 and not quoted - found, sorted(quoted - found)


# "mean ± sd (seed values)": two to six values, comma- or "and"-separated
WITH_SEEDS = re.compile(r"(\d\.\d{3}) ± (\d\.\d{3}) \(((?:\d\.\d{3}(?:, | and )){1,5}\d\.\d{3})\)")


def test_with_seeds_reads_a_mean_its_spread_and_its_values():
    m = WITH_SEEDS.findall("0.152 ± 0.015 (0.135, 0.165, 0.155); 0.1 ± 0.2 (0.3); 0.476 ± 0.039 (0.521 and 0.458)")
    assert m == [("0.152", "0.015", "0.135, 0.165, 0.155"), ("0.476", "0.039", "0.521 and 0.458")]


def test_each_mean_and_spread_quoted_with_its_seeds_adds_up():
    """Where a page gives a mean ± sd with the values behind it ("0.152 ± 0.015 (0.135, 0.165, 0.155)", about 60 in
    the README and docs/), the mean and the sample sd (bench.mean_sd's) of those values are the quoted ones, to
    the rounding of three decimals. A value or a mean mistyped on one side fails here."""
    import bench
    bad, n = [], 0
    for page in PAGES:
        text = re.sub(r"\s+", " ", read(page))
        for mean, sd, values in WITH_SEEDS.findall(text):
            n += 1
            m, s = bench.mean_sd(float(v) for v in re.split(r", | and ", values))
            if abs(m - float(mean)) > 1.1e-3 or abs(s - float(sd)) > 1.1e-3:
                bad.append(f"{page}: {mean} ± {sd} ({values}): the values give {m:.4f} ± {s:.4f}")
    assert n > 40 and not bad, "\n".join(bad)


def test_the_reports_table_1_and_fig_7_are_the_means_of_their_rows_per_seed():
    """results/report.md as committed: each of Table 1's means ± sds is that of its per-seed rows, and each of Fig. 7's
    that of its own rows per seed (to the rounding of three decimals), so the tables per seed and the tables above
    them come from the same runs."""
    import bench
    report, n = read("results", "report.md"), 0
    for marker, section, k in (("## Table 1:", "## Per seed", 4), ("## Fig. 7:", "## Fig. 7", None)):
        seeds = per_seed(report, section)
        for model, cells in table_after(report, marker).items():
            rows = [seeds[(model, s)] for s in (0, 1, 2)]
            for i, cell in enumerate(cells[:k]):   # Table 1: task, agent, consistency, avg; Fig. 7: every subgroup
                m, s = bench.mean_sd(float(r[i].split(" (")[0]) for r in rows)
                mean, sd = map(float, cell.split(" ± "))
                assert abs(m - mean) < 1.1e-3 and abs(s - sd) < 1.1e-3, (model, i, cell, [r[i] for r in rows])
                n += 1
    assert n == 5 * 4 + 3 * 5, n


def test_each_score_quoted_with_its_counts_is_their_ratio():
    """A score given as Tab. 4 gives it, "0.090 (18/200; 0%)" (about 50 in the README, results/report.md and docs/):
    successes / valid judgments is the score, to the rounding of three decimals (and of the successes, where they
    are an average's, to one decimal)."""
    bad, n = [], 0
    for page in PAGES + [os.path.join("results", "report.md")]:
        text = read(page)
        for score, successes, valid in re.findall(r"(\d\.\d{3}) \((\d+(?:\.\d)?)/(\d+)[;)]", text):
            n += 1
            if int(valid) and abs(float(successes) / int(valid) - float(score)) > 5e-4 + 0.05 / int(valid):
                bad.append(f"{page}: {score} ({successes}/{valid})")
    assert n > 40 and not bad, "\n".join(bad)
