"""The documentation's numbers come from generated files, never typed by hand.

- The reference page is the rendering of the stored reference tables, and the benchmark page the rendering of
  the stored benchmark results: a hand edit of either page, or a table or result changed without its page,
  fails here.
- Every `measured` role on every page resolves in its generated file (``make docs`` refuses one that does not;
  this finds it without building the docs).
- The pages link only to pages that exist.
(``make docs``, run by CI, builds the whole site with warnings as errors and runs the examples.)
"""
from __future__ import annotations

import re
import sys

import pytest

from conftest import ROOT

DOCS = ROOT / "docs"
PAGES = sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts and "auto_examples" not in p.parts)


def test_the_reference_page_is_the_stored_tables():
    from pmask.pipeline.reference import DOCS_PAGE, docs_page

    assert DOCS_PAGE.read_text() == docs_page(), "run `make reference` (it rewrites docs/generated/reference.md)"


def test_the_benchmark_page_is_the_stored_results():
    sys.path.insert(0, str(ROOT / "bench"))
    import report

    assert report.PAGE.read_text() == report.page(*report.stored()), \
        "run `python bench/report.py` (make bench writes it) after changing bench/*.json or the bench's markdown"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(DOCS)))
def test_every_measured_number_resolves(page):
    sys.path.insert(0, str(DOCS / "_ext"))
    import pmask_numbers

    for spec in re.findall(r"\{measured\}`([^`]+)`", page.read_text()):
        pmask_numbers.render(spec)  # raises when the generated file no longer has it


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(DOCS)))
def test_links_between_pages_lead_somewhere(page):
    text = page.read_text()
    for target in re.findall(r"\{doc\}`(?:[^`<]*<)?([^`>]+)>?`", text):
        base = DOCS if target.startswith("/") else page.parent
        assert (base / (target.lstrip("/") + ".md")).exists() or (base / (target.lstrip("/") + ".rst")).exists(), target
