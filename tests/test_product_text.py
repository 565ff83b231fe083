"""The product speaks only of itself: no references to internal work tracking, to the sittings the work was
done in, to dates or to commits in the README, the docs, the code, the tests or the examples (this file
included: its forbidden words are assembled from parts)."""

import re
from pathlib import Path

REPO = Path(__file__).parents[1]
FOLDERS = ("docs", "lerobot_jept", "dataset_builders", "scripts", "tests", "examples", "benchmarks")
MONTHS = "January|February|March|April|May|June|July|August|September|October|November|December"
TRACKER, SITTING, REVISION = "iss" + "ue", "sess" + "ion", "com" + "mit"
FORBIDDEN = {
    "a tracker number or wording": re.compile(rf"\b{TRACKER}(?:s|'s)?\s*#?\d+|\bthe {TRACKER}\b", re.I),
    "a work sitting": re.compile(rf"\b{SITTING}s?\b", re.I),
    "a date": re.compile(rf"\b(?:{MONTHS})\s+\d{{1,4}}\b"),
    "a commit": re.compile(rf"\b{REVISION}\s+[0-9a-f]{{7,40}}\b"),
}
ALLOWED = (re.compile(rf"""scope=["']{SITTING}["']"""),)  # pytest's fixture scope


def product_files() -> list[Path]:
    files = [REPO / "README.md", REPO / "Makefile", REPO / "pyproject.toml"]
    for folder in FOLDERS:
        files += [p for p in (REPO / folder).rglob("*") if p.suffix in (".md", ".py", ".json", ".toml")]
    return [p for p in files if p.is_file() and "__pycache__" not in p.parts]


def test_no_internal_references_in_the_product():
    found = []
    for path in product_files():
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            for allowed in ALLOWED:
                line = allowed.sub("", line)
            for what, pattern in FORBIDDEN.items():
                if pattern.search(line):
                    found.append(f"{path.relative_to(REPO)}:{number}: {what}: {line.strip()[:100]}")
    assert not found, "Write what the product does, not how it was made:\n" + "\n".join(found)


def test_the_check_catches_each_kind():
    month = MONTHS.split("|")[-1]
    samples = [f"as {TRACKER} 13 asks", f"{TRACKER.title()} #4", f"this {SITTING}'s run", f"({month} 2026)"]
    samples.append(f"at {REVISION} 9a86492")
    for sample in samples:
        assert any(p.search(sample) for p in FORBIDDEN.values()), sample
    assert not any(p.search("a progress bar with ETA, 20 episodes") for p in FORBIDDEN.values())
