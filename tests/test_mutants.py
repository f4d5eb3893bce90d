"""tests/mutants.py's list stays runnable as the code moves: each change's old text is in its file exactly once, and
each test it runs exists. Running the changes takes hours and is not part of the suite; this takes a second, so a
refactor that leaves a change stale, or renames a test one runs, fails here, not at the next mutation run."""
import os
import re

import mutants

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_every_change_matches_its_file_once():
    stale = []
    for key, (_, changes) in mutants.MUTANTS.items():
        src = open(os.path.join(ROOT, key.split()[0]), encoding="utf-8").read()   # "train.py (pretrain)" -> train.py
        stale += [f"{key}: {what} ({src.count(old)} matches)" for old, new, what in changes if src.count(old) != 1]
    assert not stale, "\n".join(stale)


def test_every_test_a_change_runs_exists():
    missing = []
    for key, (tests, _) in mutants.MUTANTS.items():
        for t in tests:
            path, _, name = t.partition("::")
            path = os.path.join(ROOT, path)
            text = open(path, encoding="utf-8").read() if os.path.isfile(path) else ""
            if not text or name and not re.search(rf"^def {name}\(", text, re.M):
                missing.append(f"{key}: {t}")
    assert not missing, "\n".join(missing)


def test_each_change_changes_something_and_says_what():
    assert sum(len(changes) for _, changes in mutants.MUTANTS.values()) > 400
    for key, (_, changes) in mutants.MUTANTS.items():
        for old, new, what in changes:
            assert old != new and what.strip(), (key, what)
