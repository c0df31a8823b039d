"""Issue 35, item 7: messages that pointed wrong, each as the user met it."""

from __future__ import annotations

from click.testing import CliRunner

from wiredsl.cli import main

EIGHT_SECONDS = "\n".join(f"{100 + 0.5 * i:.4f} {0.1 * i:.4f} 0 0 0 0 0 1" for i in range(17)) + "\n"


def _check(tmp_path, path_block: str):
    (tmp_path / "t8.txt").write_text(EIGHT_SECONDS)
    f = tmp_path / "w.wd"
    f.write_text(f"wiredsl 1\npath run {{\n{path_block}\n}}\n")
    return CliRunner().invoke(main, ["check", str(f)])


def test_a_window_past_the_end_of_the_file_names_the_window_and_the_files_span(tmp_path):
    """Was: "the window from 10 s to 0 s holds no pose (the file spans 0 s)" for an 8 s file."""
    r = _check(tmp_path, '  read "t8.txt" from 10s')
    assert r.exit_code == 1
    assert "t8.txt: the window from 10 s holds no pose: the file spans 0 s to 8 s" \
        in r.stderr
    r = _check(tmp_path, '  read "t8.txt" from 10s to 12s')
    assert "the window from 10 s to 12 s holds no pose: the file spans 0 s to 8 s" in r.stderr


def test_pipeline_none_on_a_scene_without_pipelines_points_at_no_effects(tmp_path):
    """Was: "no pipeline 'none' ... (it has: none)"."""
    for command in (["render", "--edges", "none"], ["build"]):
        r = CliRunner().invoke(main, [command[0], "tests/data/table_box_cup.wd", "--pipeline", "none",
                                      "-o", str(tmp_path / command[0]), *command[1:]])
        assert r.exit_code == 2, r.output
        assert "no pipeline 'none' in tests/data/table_box_cup.wd (it has: the built-in paper); --no-effects " \
               "draws the ideal projection" in " ".join(r.output.split())
