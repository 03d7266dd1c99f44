"""The house rules a reader relies on: import layering, and a product that speaks only of itself."""

from __future__ import annotations

import ast
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tracked(*patterns: str) -> list[Path]:
    out = subprocess.run(["git", "ls-files", *patterns], cwd=ROOT, capture_output=True, text=True, check=True)
    return [ROOT / line for line in out.stdout.splitlines() if line]


def test_core_library_never_imports_envs_or_algorithms() -> None:
    # a3cqp_rl/ is the core: envs/ and algorithms/ build on it, never the other way round (the CLI dispatches to
    # them by "module:function" strings, which are not imports)
    offenders = []
    for path in (ROOT / "a3cqp_rl").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else []
            offenders += [f"{path.relative_to(ROOT)}:{node.lineno} imports {n}" for n in names
                          if n.split(".")[0] in ("envs", "algorithms")]
    assert not offenders, "\n".join(offenders)


# Words about how the project is worked on, not about what it is: a reader has no such documents.
PROCESS_WORDS = re.compile(r"\bsessions? (?:\d+|report|notes?|of \d)|\bissues? (?:#?\d+|notes?)\b|\(issue\b|"
                           r"\bstop \d+\b|\bhelper (?:session|agent)s?\b", re.IGNORECASE)


def test_no_words_about_the_work_process() -> None:
    hits = []
    for path in _tracked():
        if path.suffix in (".png", ".pdf", ".so") or path.name == Path(__file__).name or not path.is_file():
            continue
        for i, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if PROCESS_WORDS.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()[:100]}")
    assert not hits, "\n".join(hits)


def test_the_process_word_check_can_fail() -> None:
    for text in ("see session 11", "the session report", "(issue 6)", "issue notes", "Issue 12 says"):
        assert PROCESS_WORDS.search(text), text
    for text in ("a training session", "this issue of the journal", "TorchRL's stop criterion"):
        assert not PROCESS_WORDS.search(text), text


def test_every_benchmark_is_registered_and_dispatched_by_name() -> None:
    from a3cqp_rl.bench_cli import BENCHES

    files = {p.stem for p in (ROOT / "bench").glob("*.py") if p.stem != "__init__"}
    helpers = {"point_mass_gym", "arm_loop"}  # imported by the benchmarks, not ones themselves
    assert {m.split(".")[1] for m in BENCHES.values()} == files - helpers
    text = (ROOT / "a3cqp_rl" / "bench_cli.py").read_text()
    assert "Path(" not in text and "runpy" not in text  # no path lookups of the checkout
