"""`wiredsl fmt`: canonical, idempotent, keeps comments, compiles to the same scene."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import compile_text

from wiredsl.language.ast import parse_text
from wiredsl.language.compile import compile_file
from wiredsl.language.fmt import format_text

FILES = sorted(Path("scenes").rglob("*.wd"))


@pytest.mark.parametrize("path", FILES, ids=[str(p) for p in FILES])
def test_committed_scenes_are_canonical(path):
    text = path.read_text()
    assert format_text(text, str(path)) == text


MESSY = """wiredsl   1   # version

# a model
model bin {   # opens
  line a from (0,0,
     0) to (1m,2,3)  # trailing



  # before e
  ellipse   e centre (0,0,0) normal (0,0,1) axis (1,0,0) radii (1,1) range (0deg,90deg)
  # last in block
}  # closes
place bin as b1 at (1,2,0) rotate z 30deg rotate x 5deg
camera c { focal 600px
  size (640px, 480px) }
"""


def test_formatting_keeps_every_comment_and_is_idempotent():
    text = MESSY
    once = format_text(text)
    assert format_text(once) == once
    comments = [c.text for c in parse_text(text).comments]
    assert [c.text for c in parse_text(once).comments] == comments
    assert "\n\n\n" not in once
    assert "line a from (0, 0, 0) to (1m, 2, 3)  # trailing" in once


def test_formatted_text_compiles_to_the_same_scene():
    text = MESSY
    assert compile_text(format_text(text))[0] == compile_text(text)[0]


@pytest.mark.parametrize("path", [p for p in FILES if p.parent.name == "scenes"], ids=lambda p: p.stem)
def test_scrambled_scene_formats_back(path, tmp_path):
    """Collapse the layout of a real scene; fmt must restore an equivalent canonical file."""
    text = path.read_text()
    scrambled = "\n".join("    " + line.replace(", ", " ,  ") for line in text.splitlines()) + "\n"
    out = format_text(scrambled)
    assert format_text(out) == out
    copy = tmp_path / path.name
    copy.write_text(out)
    for aux in path.parent.iterdir():
        if aux.name != path.name:
            (tmp_path / aux.name).symlink_to(aux.resolve())
    a = compile_file(path)[0].model_dump(exclude={"source"})
    b = compile_file(copy)[0].model_dump(exclude={"source"})
    assert a == b


def test_a_long_list_of_points_wraps_between_points_never_inside_one():
    """Issue 15: fmt split a point mid-tuple (`(\\n -0.5, 0.3, 0.72,\\n )`)."""
    points = " ".join(f"({x / 10 - 0.5:.1f}, 0.3, 0.72)" for x in range(40))
    text = f"wiredsl 1\nmodel m {{\n  polyline p through {points}\n}}\n"
    once = format_text(text)
    assert format_text(once) == once
    body = once.splitlines()[2:-1]
    assert len(body) > 3 and all(len(line) <= 100 for line in body)
    for line in body:  # every line holds whole points only
        assert line.count("(") == line.count(")"), line
    assert compile_text(once)[0] == compile_text(text)[0]
