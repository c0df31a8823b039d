"""The committed JSON Schemas: current with the models, valid 2020-12, and what compile emits validates."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest
from click.testing import CliRunner

from wiredsl.cli import main
from wiredsl.io import schema


@pytest.mark.parametrize("name", schema.NAMES)
def test_committed_schema_matches_models(name):
    committed = Path(f"schema/{name}.schema.json").read_text()
    assert committed == schema.render(name), f"schema/{name}.schema.json is stale: regenerate it"


@pytest.mark.parametrize("name", schema.NAMES)
def test_schema_is_valid_2020_12(name):
    doc = json.loads(Path(f"schema/{name}.schema.json").read_text())
    assert doc["$schema"] == "https://json-schema.org/draft/2020-12/schema" and doc["$id"]
    jsonschema.Draft202012Validator.check_schema(doc)


@pytest.mark.parametrize("path", sorted(Path("scenes").glob("*.wd")), ids=lambda p: p.stem)
def test_compiled_scene_validates(path, tmp_path):
    out = tmp_path / "scene.json"
    result = CliRunner().invoke(main, ["compile", str(path), "-o", str(out)])
    assert result.exit_code == 0, result.output
    doc = json.loads(out.read_text())
    assert schema.problems(doc) == []
    assert doc["schema_version"] == "1"


def test_schema_rejects_an_out_of_range_stage(tmp_path):
    result = CliRunner().invoke(main, ["compile", "scenes/lab.wd"])
    doc = json.loads(result.stdout)
    doc["pipelines"][0]["stages"][1]["params"]["fraction"] = 1.5
    assert any("1.5 is greater than the maximum of 1" in p for p in schema.problems(doc))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    result = CliRunner().invoke(main, ["validate", str(bad)])
    assert result.exit_code == 1 and "pipelines/0/stages/1/params/fraction" in result.stderr


def test_the_grammars_comments_cite_files_that_exist():
    """Issue 15: they cited wiredsl/language.py and wiredsl/parse.py, long since moved."""
    import re

    text = Path("grammar/wiredsl.lark").read_text()
    cited = re.findall(r"[\w/]+\.(?:py|md|lark|json)", text)
    assert cited and all(Path(c).is_file() for c in cited), cited
