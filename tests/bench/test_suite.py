"""Suite files: the shipped suites load, rows are selected by id, bad files are refused naming file, row and key."""

from __future__ import annotations

import pytest

from nerf_lightning.bench.suite import SuiteError, load_suite, shipped_suites


def test_the_shipped_suites_load_with_the_presets_they_name():
    from nerf_lightning.config import compose_config

    assert {"cpu-quick", "cpu", "gpu"} <= set(shipped_suites())
    for name in shipped_suites():
        suite = load_suite(name)
        for row in suite.rows:
            assert row.marks[-1] == row.minutes and list(row.marks) == sorted(row.marks)
            # every row composes: its preset exists and its overrides name real keys
            compose_config([f"experiment={row.preset}", *([f"data.root=/nowhere/{row.data}"] if row.data else []), *row.overrides])


def test_the_cpu_quick_suite_has_a_row_that_needs_no_data():
    assert any(row.data is None for row in load_suite("cpu-quick").rows)


def test_rows_are_selected_by_glob_on_their_id():
    suite = load_suite("cpu")
    assert [row.id for row in suite.select(["fern/*"])] == ["fern/nerfacto_forward_cpu/10min/seed0", "fern/splat_forward_cpu/10min/seed0"]
    assert [row.id for row in suite.select(["*/nerfacto_forward_cpu/*"])] == ["fern/nerfacto_forward_cpu/10min/seed0"]
    assert len(suite.select(None)) == len(suite.rows)
    with pytest.raises(SuiteError, match="matches no row of suite 'cpu'; its rows: lego/fast_blender"):
        suite.select(["chair/*"])


def write(tmp_path, text):
    path = tmp_path / "suite.yaml"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize("text, message", [
    ("rows: []", "non-empty list 'rows'"),
    ("rows:\n  - {scene: a, preset: fast, minutes: 1, speed: 2}", r"row 1: unknown key\(s\) speed"),
    ("rows:\n  - {scene: a, preset: fast}", "row 1: missing minutes"),
    ("rows:\n  - {scene: a, preset: fast, minutes: -1}", "minutes must be a number > 0, got -1"),
    ("rows:\n  - {scene: a, preset: fast, minutes: 1, marks: [0]}", "marks must be a list of minutes > 0"),
    ("rows:\n  - {scene: a, preset: fast, minutes: 1, overrides: [nokey]}", "overrides must be a list of Hydra overrides"),
    ("rows:\n  - {scene: a, preset: fast, minutes: 1}\n  - {scene: a, preset: fast, minutes: 1}", "a/fast/1min/seed0 appear twice"),
    ("rows: [\n", "is not valid YAML"),
    ("machine: fast\nrows:\n  - {scene: a, preset: fast, minutes: 1}", r"unknown key\(s\) machine"),
])
def test_a_bad_suite_file_is_refused_naming_what_is_wrong(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(SuiteError, match=message) as raised:
        load_suite(path)
    assert path in str(raised.value)


def test_a_missing_suite_names_the_shipped_ones():
    with pytest.raises(SuiteError, match="no suite 'cpu-slow': expected one of cpu, cpu-quick, gpu"):
        load_suite("cpu-slow")


def test_seeds_make_one_row_each_and_marks_past_the_end_are_dropped(tmp_path):
    suite = load_suite(write(tmp_path, "seeds: [0, 1]\nmarks: [1, 2, 5]\nrows:\n  - {scene: a, preset: fast, minutes: 3}"))
    assert [row.id for row in suite.rows] == ["a/fast/3min/seed0", "a/fast/3min/seed1"]
    assert suite.rows[0].marks == (1.0, 2.0, 3.0)
