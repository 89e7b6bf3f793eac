"""The documentation stays a guide: docs/ is small, every file in it is linked from a Markdown page, every relative
link resolves (anchors included), the model card names the shipped model, and no text labels work by numbered
sessions."""

from __future__ import annotations

import json
import pathlib
import re
import shutil
import subprocess

import pytest

from conftest import ROOT

DOCS = ROOT / "docs"
MAX_DOCS_BYTES = 5_000_000
"""docs/ may hold at most this many bytes (5 MB)."""

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
"""A Markdown link or image: its target."""

NUMBERED_SESSIONS = re.compile(r"session[ _-]?[0-9]|sessions [0-9]|session (of|from) ", re.IGNORECASE)
"""What labels work by numbered sessions (the developers' brief's search)."""

IGNORED_DIRS = {".git", ".venv", "build", "dist", "runs", "codecsplat-demo", "__pycache__", ".pytest_cache"}


def markdown_pages() -> list[pathlib.Path]:
    """Every Markdown file of the repository (outside virtual environments and build output)."""
    return sorted(p for p in ROOT.rglob("*.md") if not IGNORED_DIRS.intersection(p.relative_to(ROOT).parts))


def links(page: pathlib.Path) -> list[tuple[pathlib.Path, str]]:
    """(resolved path, anchor) of every relative link in ``page`` (web links left out)."""
    out = []
    for target in LINK.findall(page.read_text(encoding="utf-8")):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        out.append(((page.parent / path).resolve() if path else page.resolve(), anchor))
    return out


def heading_anchors(page: pathlib.Path) -> set[str]:
    """GitHub's anchors of the headings of ``page``: lower case, punctuation dropped, spaces as hyphens."""
    headings = re.findall(r"^#+\s+(.+?)\s*$", page.read_text(encoding="utf-8"), re.MULTILINE)
    return {re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-") for heading in headings}


def test_docs_stay_under_5_mb():
    size = sum(p.stat().st_size for p in DOCS.rglob("*") if p.is_file())
    assert size <= MAX_DOCS_BYTES, f"docs/ holds {size:,d} bytes, more than {MAX_DOCS_BYTES:,d}"


def test_every_file_in_docs_is_linked_from_a_page():
    linked = {path for page in markdown_pages() for path, _ in links(page)}
    unlinked = [p.relative_to(ROOT).as_posix() for p in sorted(DOCS.rglob("*")) if p.is_file() and p.resolve() not in linked]
    assert unlinked == []


def test_every_relative_link_resolves():
    broken = []
    for page in markdown_pages():
        for path, anchor in links(page):
            if not path.exists():
                broken.append(f"{page.relative_to(ROOT)}: {path}")
            elif anchor and path.suffix == ".md" and anchor not in heading_anchors(path):
                broken.append(f"{page.relative_to(ROOT)}: {path.name}#{anchor}")
    assert broken == []


def test_the_link_check_sees_a_broken_link_and_an_unknown_anchor(tmp_path):
    (tmp_path / "a.md").write_text("# Title: one\n[x](b.md) [y](#title-one) [z](#nowhere) ![p](img/p.png)\n")
    found = {(path.name, anchor) for path, anchor in links(tmp_path / "a.md")}
    assert found == {("b.md", ""), ("a.md", "title-one"), ("a.md", "nowhere"), ("p.png", "")}
    assert heading_anchors(tmp_path / "a.md") == {"title-one"}


def test_the_model_card_names_the_shipped_model():
    from codecsplat_warp.model.codecsplat import model_id
    from codecsplat_warp.model.pretrained import load_pretrained

    shipped = model_id(load_pretrained(device="cpu"))
    card = (DOCS / "model-card.md").read_text(encoding="utf-8")
    assert f"model_id: {shipped}" in card, "front matter"
    assert f"# Model card: CodecSplat {shipped}" in card, "title"
    assert f"| model id | **{shipped}**" in card, "model details"
    assert "docs/model-card.md" in (ROOT / "README.md").read_text(encoding="utf-8"), "the README links the card"


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="needs a git checkout")
def test_no_text_labels_work_by_numbered_sessions():
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    hits = []
    for name in files:
        path = ROOT / name
        if NUMBERED_SESSIONS.search(name):
            hits.append(name)
        if not path.is_file():
            continue
        text = path.read_bytes()
        if b"\0" in text[:4096]:  # binary
            continue
        for number, line in enumerate(text.decode("utf-8", errors="replace").splitlines(), 1):
            if NUMBERED_SESSIONS.search(line):
                hits.append(f"{name}:{number}: {line.strip()[:80]}")
    assert hits == []


REDISTRIBUTABLE = re.compile(r"\bCC BY(-SA)? 4\.0\b")
"""A recorded scene licence that lets the docs show the scene's photographs, with attribution (not NC, not ND)."""


def scenes_in_picture_name(name: str, scenes: list[str]) -> list[str]:
    """The scenes whose name, or whose name without its source prefix (``bmvs_``, ``llff_``, ...), a picture's file
    name holds (hyphens read as underscores)."""
    name = name.replace("-", "_")
    return [s for s in scenes if s in name or ("_" in s and s.split("_", 1)[1] in name)]


def test_scene_names_are_found_in_picture_names_with_or_without_their_prefix():
    scenes = ["bmvs_stone_horse", "nerd_mary_rose", "llff_horns"]
    assert scenes_in_picture_name("rdo-stone-horse-2views.jpg", scenes) == ["bmvs_stone_horse"]
    assert scenes_in_picture_name("failure-thin-foreground-bmvs-stone-horse.jpg", scenes) == ["bmvs_stone_horse"]
    assert scenes_in_picture_name("heldout-rate-distortion-re10k.png", scenes) == []


def test_pictures_in_the_docs_show_only_scenes_whose_licence_lets_us_redistribute_them(data_root):
    """Each picture in docs/images that names a real scene shows one whose recorded licence is CC BY (or BY-SA) 4.0,
    and the docs name that scene's source beside it. Catches: a comparison picture of a scene with no licence,
    or a non-commercial one, committed into the docs."""
    licences = {p.name: json.loads((p / "cameras.json").read_text())["source"]["license"]
                for p in data_root.iterdir() if (p / "cameras.json").is_file()}
    pages = "\n".join(page.read_text(encoding="utf-8") for page in markdown_pages())
    refused = []
    for picture in sorted((DOCS / "images").iterdir()):
        for scene in scenes_in_picture_name(picture.name, sorted(licences)):
            licence = licences[scene]
            if not REDISTRIBUTABLE.search(licence) or "NC" in licence.replace("NCC", ""):
                refused.append(f"{picture.name}: {scene} ({licence})")
    assert refused == []
    assert "CC BY 4.0" in pages and "BlendedMVS" in pages
