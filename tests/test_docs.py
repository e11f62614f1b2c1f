"""The documentation's rules (README and docs/): pages small enough to read, the current truth rather than a lab
notebook (no commit hashes, no issue numbers or run histories), relative links that resolve, and every results
table made by a command the page shows (a grid under configs/, `uw-eval table`, or a benchmark script)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from uw3dgs.bench.grid import load_grid

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = sorted((ROOT / "docs").rglob("*.md"))
DOCS = [README, *PAGES]
PAGE_LIMIT = 20 * 1024
README_LIMIT = 10 * 1024

HASH = re.compile(r"(?<![#\w/.\-=:])[0-9a-f]{7,40}(?![\w/.\-])")
"""A commit-hash-looking token: 7-40 lowercase hex digits standing alone. Not a colour (#ffffff), not part of a
path, a file name or a longer word (a sha256 in `model-3f2a9c1d.pt`, `/0a1b2c3d/`), not a key=value."""
HISTORY = re.compile(r"\bissues? #?\d+|issue's bars?|\b(last|this|another|previous) session\b|another day",
                     re.IGNORECASE)
METRIC_HEADER = re.compile(r"psnr|ssim|lpips|floater|abs\.? ?rel|\bu[wr]i\b", re.IGNORECASE)
MAKES_TABLE = ("uw-bench configs/", "uw-eval table", "python benchmarks/")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def prose_lines(path: Path) -> list[tuple[int, str, bool]]:
    """(line number, text, inside a fenced code block) for every line."""
    out, fenced = [], False
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            out.append((number, line, True))
            continue
        out.append((number, line, fenced))
    return out


def is_hash(token: str) -> bool:
    """Hex digits with both a digit and a letter: '1234567' is a number, 'decade' a word, 'e831e00' a commit."""
    return bool(re.search(r"\d", token)) and bool(re.search(r"[a-f]", token))


def commit_hashes(text: str) -> list[str]:
    return [m.group(0) for m in HASH.finditer(text) if is_hash(m.group(0))]


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation but hyphens and underscores dropped, spaces to
    hyphens, a link by its text."""
    text = re.sub(r"[`*]|\[([^\]]*)\]\([^)]*\)", lambda m: m.group(1) or "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for _, line, fenced in prose_lines(path):
        match = re.match(r"#{1,6} (.+)", line)
        if fenced or not match:
            continue
        base = slug(match.group(1))
        count = seen.get(base, 0)
        seen[base] = count + 1
        out.add(base if count == 0 else f"{base}-{count}")
    return out


def history(path: Path) -> list[str]:
    found = []
    for number, line, _ in prose_lines(path):
        found += [f"{rel(path)}:{number}: commit hash {token!r}" for token in commit_hashes(line)]
        found += [f"{rel(path)}:{number}: {m.group(0)!r}" for m in HISTORY.finditer(line)]
    return found


def broken_links(path: Path) -> list[str]:
    broken = []
    for number, line, fenced in prose_lines(path):
        if fenced:
            continue
        for target in LINK.findall(line):
            if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
                continue
            file_part, _, anchor = target.partition("#")
            goal = (path.parent / file_part).resolve() if file_part else path
            if not goal.exists():
                broken.append(f"{rel(path)}:{number}: {target} (no such file)")
            elif anchor and goal.suffix == ".md" and anchor not in anchors(goal):
                broken.append(f"{rel(path)}:{number}: {target} (no heading #{anchor} in {goal.name})")
    return broken


def tables_without_command(path: Path) -> list[str]:
    """Tables with a metric column that no command making them (MAKES_TABLE) precedes in their section."""
    missing = []
    section: list[str] = []
    previous = ""
    for number, line, fenced in prose_lines(path):
        if not fenced and re.match(r"#{1,6} ", line):
            section = []
        is_header = line.startswith("|") and not previous.startswith("|")
        shown = any(marker in text for text in section for marker in MAKES_TABLE)
        if is_header and not fenced and METRIC_HEADER.search(line) and not shown:
            missing.append(f"{rel(path)}:{number}: {line[:80]}")
        section.append(line)
        previous = line
    return missing


def rel(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


# ---- the tests -------------------------------------------------------------------------------------------------------


def test_the_checks_see_what_they_look_for(tmp_path):
    assert commit_hashes("trained by commit e831e00 (and 6690f98)") == ["e831e00", "6690f98"]
    assert commit_hashes("colour #ffaa00, model-3f2a9c1d.pt, /cache/0a1b2c3d4e/, 1234567 points, a decade") == []
    assert HISTORY.search("met the issue's bar") and HISTORY.search("see issue 16") and not HISTORY.search("issues")
    assert slug("PAUP's masked render every N steps") == "paups-masked-render-every-n-steps"
    assert slug("SeaThru-NeRF scenes (`seathru-nerf`)") == "seathru-nerf-scenes-seathru-nerf"
    assert slug("The last three misses, and 9C") == "the-last-three-misses-and-9c"
    assert slug("`psnr_covisible` and [LPIPS](x.md)") == "psnr_covisible-and-lpips"
    page = tmp_path / "page.md"
    page.write_text("# A\n\n## Made\n\n    uw-bench configs/demo.yaml\n\n| method | PSNR |\n|---|---|\n| a | 1 |\n\n"
                    "## Not made\n\nTrained at commit 6690f98 (issue 16), see [b](b.md), [a](#made), [c](#nowhere)."
                    "\n\n| method | URI |\n|---|---|\n| a | 1 |\n")
    assert [m.split(": ")[0] for m in tables_without_command(page)] == [f"{page}:15"]
    assert [m.split(": ", 1)[1] for m in history(page)] == ["commit hash '6690f98'", "'issue 16'"]
    assert [m.split(": ", 1)[1] for m in broken_links(page)] == ["b.md (no such file)",
                                                                   "#nowhere (no heading #nowhere in page.md)"]


@pytest.mark.parametrize("path", DOCS, ids=rel)
def test_page_size(path):
    limit = README_LIMIT if path == README else PAGE_LIMIT
    size = len(path.read_bytes())
    assert size <= limit, (f"{rel(path)} is {size} bytes, over {limit}: keep one topic per page, conclusions in a "
                           "sentence with their evidence, history in git and CHANGELOG.md")


@pytest.mark.parametrize("path", DOCS, ids=rel)
def test_no_commit_hashes_or_run_history(path):
    found = history(path)
    assert not found, "docs state the current truth, history goes to git and CHANGELOG.md:\n" + "\n".join(found)


@pytest.mark.parametrize("path", DOCS, ids=rel)
def test_relative_links_resolve(path):
    broken = broken_links(path)
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize("path", DOCS, ids=rel)
def test_results_tables_show_the_command_that_makes_them(path):
    """A table with a metric column follows, in its section, the command that re-makes it."""
    missing = tables_without_command(path)
    assert not missing, ("a results table needs the command that makes it above it in its section "
                         f"({', '.join(MAKES_TABLE)}):\n" + "\n".join(missing))


def test_every_grid_the_docs_name_exists_and_loads():
    named = {m for path in DOCS for m in re.findall(r"uw-bench (configs/[\w.-]+\.yaml)", path.read_text())}
    assert named, "the docs name no grid"
    for grid in sorted(named):
        assert (ROOT / grid).is_file(), f"the docs name {grid}, which does not exist"
    for grid in sorted(ROOT.glob("configs/*.yaml")):
        assert load_grid(grid).cells(), grid
