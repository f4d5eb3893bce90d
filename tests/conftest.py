import os
import subprocess
import sys

import pytest
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import models  # noqa: E402

models.use_cpu(2)     # as the scripts do: 2 threads, and freed memory kept for reuse

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run(*args, env=None):
    """Run a script of the repository (or a module, '-m ...') with this interpreter; capture its output."""
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env={**os.environ, **(env or {})})


def per_seed(md: str, section: str = "## Per seed") -> dict:
    """A table per seed of report.md, the rows of `section` (up to the next heading) whose second cell is a seed:
    (model or run, seed) -> its other cells. "## Per seed": task, agent, consistency, avg, peaks; "## Fig. 7": the
    subgroups' scores."""
    rows = {}
    for line in md.split("\n" + section)[1].split("\n## ")[0].splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[1].isdigit():
            rows[(cells[0], int(cells[1]))] = cells[2:]
    return rows


def table_after(text: str, marker: str) -> dict:
    """The first Markdown table after the line that starts with `marker`: {first cell: [the other cells]}, header
    and separator rows left out."""
    lines = ("\n" + text).split("\n" + marker, 1)[1].splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    rows = lines[start + 2:end]
    cells = [[c.strip() for c in r.strip("|").split(" | ")] for r in rows]
    return {c[0]: c[1:] for c in cells}


def exit_2(main, argv: list, capsys, code: int = 2) -> str:
    """Call a script's main(argv) in this process, which spares an interpreter and torch start-up (~2 s) per bad
    input; expect it to stop with exit status 2 (bad input; or `code`, e.g. 1 for a failed run) and return what it
    wrote to stderr. The subprocess `run` stays the check that a script's bad input ends in one line and no
    traceback."""
    capsys.readouterr()
    threads = torch.get_num_threads()   # a script sets its --threads; the other tests keep theirs
    try:
        with pytest.raises(SystemExit) as e:
            main([str(a) for a in argv])
    finally:
        torch.set_num_threads(threads)
    assert e.value.code == code, e.value.code
    return capsys.readouterr().err


@pytest.fixture(scope="session")
def tiny_ckpt(tmp_path_factory):
    d = tmp_path_factory.mktemp("pretrain")
    ckpt = str(d / "tiny.pt")
    r = run("train.py", "--stage", "pretrain", "--pretrain_steps", "3", "--pretrain_batch", "4", "--width", "8",
            "--log_every", "1", "--out", ckpt, "--run_dir", str(d))
    assert r.returncode == 0, r.stderr
    assert "step     3/3" in r.stdout and "ETA" in r.stdout
    assert len(open(d / "pretrain.jsonl").read().splitlines()) == 3
    return ckpt


@pytest.fixture(scope="session")
def shipped():
    """The shipped base, loaded once: unlike a fresh model, whose zero output layer predicts frame 0 whatever the
    noise and the text, its velocity reads both."""
    return models.load_checkpoint(None)[0].eval()
