"""The claims in brief: the page's compact table and the README's three-line summary."""

import re
from pathlib import Path

import pytest
from synthetic import write_run

from tamrm_experiments.configs import make_specs
from tamrm_experiments.markdown import render_report
from tamrm_experiments.summary import (
    README_BEGIN,
    README_END,
    VERDICTS,
    readme_block,
    readme_summary,
    update_readme,
)
from tamrm_experiments.verdicts import analyse

ROOT = Path(__file__).resolve().parents[2]


def test_update_readme_rewrites_only_the_generated_block(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(
        f"# title\n\nhand text\n{README_BEGIN}\nold\n{README_END}\n\nmore hand text\n"
    )
    readme.chmod(0o640)
    assert update_readme(readme, ["new line 1", "", "new line 2"])
    text = readme.read_text()
    assert readme_block(text) == "new line 1\n\nnew line 2"
    assert text.startswith("# title\n\nhand text\n") and text.endswith("\n\nmore hand text\n")
    assert readme.stat().st_mode & 0o777 == 0o640
    assert [p.name for p in tmp_path.iterdir()] == ["README.md"]  # no temporary file left
    assert not update_readme(readme, ["new line 1", "", "new line 2"])  # idempotent
    readme.write_text("no markers\n")
    with pytest.raises(ValueError, match="no lines"):
        update_readme(readme, ["x"])
    readme.write_text(f"{README_BEGIN}\na\n{README_END}\n{README_BEGIN}\nb\n{README_END}\n")
    with pytest.raises(ValueError, match="more than once"):
        update_readme(readme, ["x"])


def test_an_edit_made_while_the_summary_is_written_is_kept(tmp_path, monkeypatch):
    """Someone else saves the README between our read and our rename: their text stays,
    with our block in it."""
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{README_BEGIN}\nold\n{README_END}\noutro\n")
    real_read = Path.read_text
    reads = []

    def read_text(self, *args, **kwargs):
        text = real_read(self, *args, **kwargs)
        if self == readme:
            reads.append(text)
            if len(reads) == 1:  # right after our first read, another writer saves
                self.write_text(text.replace("outro", "outro, edited meanwhile"))
        return text

    monkeypatch.setattr(Path, "read_text", read_text)
    assert update_readme(readme, ["new"])
    monkeypatch.undo()
    want = f"intro\n{README_BEGIN}\nnew\n{README_END}\noutro, edited meanwhile\n"
    assert readme.read_text() == want


def test_the_readme_summary_counts_the_verdicts_of_the_claims_table(tmp_path):
    runs = tmp_path / "runs"
    for spec in make_specs("quick", seeds=3, experiments=["maze"], variants=["clean"]):
        steps = {"plain": 100, "pbrs": 90, "knn": 100, "tamrm": 20}[spec.arm] + spec.seed
        write_run(runs, spec, [steps] * spec.budget.episodes)
    an = analyse(runs)
    summary = readme_summary(an, "docs/reproduction.md")
    assert len(summary) == 3
    words = [row.judge()[0] for row in an.rows]
    counts = re.search(r"(\d+) hold, (\d+) do not hold, (\d+) cannot be decided yet", summary[0])
    assert counts is not None
    assert [int(c) for c in counts.groups()] == [words.count(w) for w in VERDICTS]
    assert f"tested in {len(an.rows)} rows" in summary[0]
    holding = [r for r in an.rows if r.judge()[0] == "holds"]
    assert holding and all(r.claim.text in summary[1] for r in holding)
    assert summary[2].endswith("(docs/reproduction.md#claims).")
    # The page's brief table has one row per claim row, under the Claims heading.
    text = render_report(runs, tmp_path / "r.md", tmp_path / "r")[0]
    brief = text.split("### In brief")[1].split("### In detail")[0]
    assert len([line for line in brief.splitlines() if line.startswith("| ")]) == 1 + len(an.rows)
    assert "\n## Claims\n" in text


def test_the_committed_page_and_readme_summary_follow_the_committed_runs():
    """docs/reproduction.md and README.md's summary are what the report computes from
    docs/reproduction/runs (and runs-v1): regenerate both and compare."""
    from tamrm_experiments.args import ARCHIVE, ARCHIVE_V1

    page = ROOT / "docs" / "reproduction.md"
    text, plots, an = render_report(ARCHIVE, page, page.with_suffix(""), ARCHIVE_V1)
    fix = "run `python -m tamrm_experiments report --readme README.md` from the repository"
    committed = page.read_text().splitlines()
    for i, (want, got) in enumerate(zip(text.splitlines(), committed, strict=False)):
        assert want == got, f"docs/reproduction.md is stale from line {i + 1}: {fix}"
    assert len(text.splitlines()) == len(committed), f"docs/reproduction.md is stale: {fix}"
    assert all(png.is_file() for _e, _r, png, _t in plots), f"a plot is missing: {fix}"
    block = readme_block((ROOT / "README.md").read_text())
    assert block is not None, "README.md lost its reproduction-summary markers"
    assert block.splitlines() == readme_summary(an, "docs/reproduction.md"), (
        f"README.md's reproduction summary is stale: {fix}"
    )
