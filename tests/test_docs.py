"""The README and docs/: every relative link and anchor resolves, and CI runs the README's test command."""
import os
import re

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGES = ["README.md"] + [os.path.join("docs", f) for f in sorted(os.listdir(os.path.join(ROOT, "docs")))
                         if f.endswith(".md")]


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
    text = {p: open(os.path.join(ROOT, p), encoding="utf-8").read() for p in PAGES}
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
    readme = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    command = re.search(r"## Tests\s+```bash\n(.+?)\n```", readme).group(1).strip()
    ci = open(os.path.join(ROOT, ".ci", "run"), encoding="utf-8").read().strip().splitlines()
    assert ci[-1].strip() == command
