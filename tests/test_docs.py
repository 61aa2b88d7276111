"""The docs as a manual: the model card's tables are what ``scripts/model_card.py`` makes of the stored reports and
the shipped models, and every relative link and picture of ``docs/*.md`` resolves (files and ``#anchors``)."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
CARD = DOCS / "model.md"
PAGES = sorted(DOCS.glob("*.md"))


def _script():  # noqa: ANN202
    spec = importlib.util.spec_from_file_location("model_card", ROOT / "scripts" / "model_card.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def model_card():  # noqa: ANN201
    return _script()


@pytest.fixture()
def copies(tmp_path: Path) -> tuple[Path, Path]:
    """A copy of the card and of the reports folder, to change."""
    card = tmp_path / "model.md"
    shutil.copy(CARD, card)
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")  # the script rewrites the README's table too
    reports = tmp_path / "eval"
    shutil.copytree(DOCS / "eval", reports)
    return card, reports


def _args(card: Path, reports: Path, *more: str) -> list[str]:
    return ["--card", str(card), "--readme", str(card.parent / "README.md"), "--reports", str(reports),
            "--models", str(ROOT / "train" / "data"), *more]


# ---------------------------------------------------------------------------------------------------- the card
def test_card_is_up_to_date(model_card, capsys: pytest.CaptureFixture[str]) -> None:
    assert model_card.main(["--check"]) == 0, capsys.readouterr().err


def test_card_has_every_table_and_fits_its_length() -> None:
    text = CARD.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 300
    for name in ("models", "architecture", "rules", "headline", "sets-ssz64", "sets-ssz128", "classes",
                 "camera-models", "camera-sets-ssz64-any"):
        assert f"<!-- generated: {name} -->" in text


def test_the_camera_aware_table_follows_each_camera_setting_of_its_reports(
        model_card, copies: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    """ssz64-any's rows are its reports' results under each camera setting: a change to the pose-unknown result of
    one report is found by --check in that table alone, and the rewrite shows it."""
    card, reports = copies
    path = reports / "ssz64-any-any-camera-2048.json"
    report = json.loads(path.read_text())
    counts = report["results"]["model@none"]["counts"]
    counts["own_correct"] = counts["own_hits"]
    path.write_text(json.dumps(report))
    assert model_card.main(_args(card, reports, "--check")) == 1
    err = capsys.readouterr().err
    assert "camera-sets-ssz64-any" in err and "headline" not in err and "sets-ssz64," not in err
    assert model_card.main(_args(card, reports)) == 0
    rows = [ln for ln in card.read_text().splitlines() if ln.startswith("| `any-camera` | model, camera known: none")]
    assert len(rows) == 1 and "| 100.00 |" in rows[0]


def test_check_fails_when_a_report_changes_and_the_rewrite_mends_it(
        model_card, copies: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    card, reports = copies
    path = reports / "ssz64-test-seed5-2048.json"
    report = json.loads(path.read_text())
    counts = report["results"]["model"]["counts"]
    counts["own_correct"] = counts["own_hits"]  # every own-view pixel right on this set
    path.write_text(json.dumps(report))
    before = card.read_text()
    assert model_card.main(_args(card, reports, "--check")) == 1
    err = capsys.readouterr().err
    assert "out of date" in err and "headline" in err and "sets-ssz64" in err and "sets-ssz128" not in err
    assert card.read_text() == before  # --check writes nothing

    assert model_card.main(_args(card, reports)) == 0
    assert model_card.main(_args(card, reports, "--check")) == 0
    assert "| seed 5 | 2,048 | 128 | 62.6 | 64.9 | 100.00 |" in card.read_text()
    assert "| seed 5 | 2,048 | 128 | 62.6 | 64.9 | 96.43 |" in before


def test_tables_of_sets_counted_together_agree_with_each_report(model_card) -> None:
    """A pool of one report gives back that report's own summary, and two pooled sets are their summed counts:
    the script counts as fruxel-eval does."""
    src = model_card.Sources(DOCS / "eval", ROOT / "train" / "data")
    names = src.report("ssz64-test8192.json")["classes"]["names"]
    for file in ("ssz64-test8192.json", "ssz128-test-seed3-2048.json", "paper128-test1024.json"):
        total, _ = src.pool(model_card.Pool("one", (file,)))
        stored = src.report(file)["results"]["model"]
        got = total.summary(tuple(names))
        for key in ("miou", "completion_iou", "own_view_accuracy", "novel_view_accuracy", "depth_error"):
            assert got[key] == pytest.approx(stored[key], rel=1e-12), (file, key)
    pair = ("ssz64-test-seed1-2048.json", "ssz64-test-seed2-2048.json")
    total, _ = src.pool(model_card.Pool("two", pair))
    counts = [src.report(f)["results"]["model"]["counts"] for f in pair]
    own = 100.0 * sum(c["own_correct"] for c in counts) / sum(c["own_hits"] for c in counts)
    assert total.summary(tuple(names))["own_view_accuracy"] == pytest.approx(own, rel=1e-12)
    assert total.samples == 4096


def test_shipped_models_are_read_from_their_files(model_card) -> None:
    src = model_card.Sources(DOCS / "eval", ROOT / "train" / "data")
    small, large = src.model("ssz64"), src.model("ssz128")
    assert 1_000_000 < small["parameters"] < large["parameters"]
    assert large["parameters"] - small["parameters"] == large["level_parameters"] > 0
    assert small["rules"]["flip_average"] is True and small["dtypes"] == ["F16"]


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace("<!-- generated: classes -->", "<!-- generated: klasses -->"), "no generated table"),
    (lambda t: t.replace("<!-- generated: rules -->", "<!-- generated rules -->"), "out of place"),
    (lambda t: t.replace("<!-- generated: level -->", "<!-- generated: headline -->"), "appears twice"),
    (lambda t: t[:t.rindex("<!-- end -->")], "has no <!-- end --> line"),
    (lambda t: re.sub(r"<!-- generated: level -->.*?<!-- end -->", "", t, flags=re.S), "has no generated table level"),
    (lambda t: t.replace("<!-- generated: level -->", ""), "a marker out of place"),
])
def test_a_broken_card_is_one_error_line_and_nothing_written(
        model_card, copies: tuple[Path, Path], capsys: pytest.CaptureFixture[str], edit, message: str) -> None:
    card, reports = copies
    broken = edit(card.read_text())
    card.write_text(broken)
    assert model_card.main(_args(card, reports)) == 2
    err = capsys.readouterr().err
    assert err.startswith("model_card.py: error: ") and str(card) in err and message in err, err
    assert err.count("\n") == 1 and card.read_text() == broken


@pytest.mark.parametrize("damage, message", [
    ("remove", "cannot read the report"),
    ("garbage", "cannot read the report"),
    ("other format", "not a fruxel-eval report"),
    ("no counts", "not a fruxel-eval report"),
])
def test_a_bad_report_is_one_error_line_naming_it(
        model_card, copies: tuple[Path, Path], capsys: pytest.CaptureFixture[str], damage: str, message: str) -> None:
    card, reports = copies
    path = reports / "ssz128-test-seed4-2048.json"
    report = json.loads(path.read_text())
    if damage == "remove":
        path.unlink()
    elif damage == "garbage":
        path.write_text("{not json")
    elif damage == "other format":
        path.write_text(json.dumps({**report, "format": "something-else"}))
    else:
        del report["results"]["model"]["counts"]
        path.write_text(json.dumps(report))
    before = card.read_text()
    assert model_card.main(_args(card, reports)) == 2
    err = capsys.readouterr().err
    assert str(path) in err and message in err and err.count("\n") == 1, err
    assert card.read_text() == before


def test_reports_of_other_samples_are_refused(model_card, copies: tuple[Path, Path],
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """A candidate whose reports are not on the shipped model's test sets cannot sit in the same table."""
    card, reports = copies
    path = reports / "ssz64-x1-test-seed6-2048.json"
    report = json.loads(path.read_text())
    report["data"]["seed"] = 7
    path.write_text(json.dumps(report))
    assert model_card.main(_args(card, reports, "--check")) == 2
    err = capsys.readouterr().err
    assert "x1" in err and "not on ssz64's test samples" in err, err


# ---------------------------------------------------------------------------------------------------- links
def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in _prose(page.read_text(encoding="utf-8")).splitlines():
        m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            slug = _slug(m.group(1))
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def _prose(text: str) -> str:
    """The text without fenced code blocks and HTML comments (inline code is kept for headings' anchors)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"<!--.*?-->", "", text, flags=re.S)


def _links(page: Path) -> list[str]:
    """The targets of the page's Markdown links and pictures, and of its HTML ``src``/``href`` attributes."""
    text = re.sub(r"`[^`\n]*`", "code", _prose(page.read_text(encoding="utf-8")))
    targets = re.findall(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", text)
    targets += re.findall(r"(?:src|href)=\"([^\"]+)\"", text)
    return targets


def test_there_are_pages_with_links() -> None:
    assert CARD in PAGES and DOCS / "experiments.md" in PAGES
    assert any(t.endswith(".png") for t in _links(CARD)) and any("#" in t for t in _links(DOCS / "experiments.md"))


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_every_relative_link_and_picture_resolves(page: Path) -> None:
    broken = []
    for target in _links(page):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto:: not ours to check
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{target}: no such file")
        elif anchor and file.suffix == ".md" and anchor not in _anchors(file):
            broken.append(f"{target}: no heading #{anchor} in {file.name}")
    assert not broken, f"{page.name}: " + "; ".join(broken)


def test_anchor_slugs_follow_github() -> None:
    assert _slug("Paper scale: 128^3 from 512^2 (shipped: `ssz128`)") == "paper-scale-1283-from-5122-shipped-ssz128"
    assert _slug("Mirror averaging and the own view at 97 %") == "mirror-averaging-and-the-own-view-at-97-"
    assert _slug("The own view's first hit: a loss and a rule") == "the-own-views-first-hit-a-loss-and-a-rule"


def test_every_picture_in_docs_is_used() -> None:
    """A picture in docs/ that no page, README, BENCHMARKS or code names is dead weight in every clone."""
    texts = [p.read_text(encoding="utf-8") for p in (ROOT / "README.md", ROOT / "BENCHMARKS.md", *PAGES)]
    for folder in ("fruxel", "kernels", "render", "train", "cli", "scripts", "benchmarks", "tests"):
        texts += [p.read_text(encoding="utf-8") for p in (ROOT / folder).rglob("*.py") if p.name != "test_docs.py"]
    pictures = sorted(p for p in DOCS.iterdir() if p.suffix in (".png", ".gif", ".jpg", ".svg"))
    assert pictures
    unused = [p.name for p in pictures if not any(p.name in t for t in texts)]
    assert not unused, unused


def test_conventions_are_in_step_with_the_spec() -> None:
    """docs/conventions.md is the project's copy of the conventions it was given (the developers' SPEC.md beside
    the repository); a clone without that file has only the copy, which the code cites."""
    spec = ROOT.parent / "shared" / "SPEC.md"
    if not spec.is_file():
        pytest.skip("no shared/SPEC.md beside this clone")
    assert (ROOT / "docs" / "conventions.md").read_text(encoding="utf-8") == spec.read_text(encoding="utf-8")


def test_readme_results_lead_with_the_default_model() -> None:
    """The README's results table opens with the model a command uses when none is named."""
    from fruxel.train.model_files import DEFAULT_MODEL

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    table = text[text.index("<!-- generated: results -->"):].split("<!-- end -->")[0]
    rows = [ln for ln in table.splitlines() if ln.startswith("| `")]
    assert rows and rows[0].startswith(f"| `{DEFAULT_MODEL}` |"), rows[:1]
