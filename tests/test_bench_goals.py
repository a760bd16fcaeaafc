"""bench/goals.py: the goals table in docs/BENCHMARKS.md matches the full runs in docs/bench,
every goal names a metric its suite's report has, and the statuses follow the comparisons."""

import json

import pytest

from bench import goals


def test_the_table_in_benchmarks_md_matches_the_reports():
    table = goals.markdown(goals.evaluate(goals.load_reports(goals.DEFAULT_DIR)))
    text = goals.BENCHMARKS_MD.read_text()
    assert goals.with_table(text, table) == text, "run: python -m bench.goals --write"


def test_every_goal_names_a_metric_of_its_suites_full_report():
    reports = goals.load_reports(goals.DEFAULT_DIR)
    for g in goals.GOALS:
        assert g.suite in reports, f"docs/bench/{g.suite}.json is missing"
        assert not reports[g.suite]["quick"], f"docs/bench/{g.suite}.json is a --quick run"
        assert g.metric in reports[g.suite]["metrics"], f"{g.suite} reports no {g.metric}"


@pytest.mark.parametrize("op, threshold, value, explained, expected", [
    ("<=", 3.0, 3.0, "", "met"), ("<=", 3.0, 3.01, "", "missed"), (">=", 30.0, 29.9, "", "missed"),
    (">=", 30.0, 30.0, "", "met"), ("==", 0.0, 0.0, "", "met"), ("==", 0.0, 1e-5, "why", "explained"),
    ("<=", 1.0, float("nan"), "", "no run"), ("<=", 1.0, None, "", "no run"),
])
def test_status(op, threshold, value, explained, expected):
    assert goals.status(goals.Goal(0, "s", "m", op, threshold, explained), value) == expected


def test_a_report_of_ones_own_is_read_the_same_way(tmp_path):
    (tmp_path / "store.json").write_text(json.dumps(
        {"suite": "store", "quick": True, "metrics": {"lossless_vs_zstd": 0.71, "roi_decode_msps": 60.0}}))
    rows = {r["metric"]: r for r in goals.evaluate(goals.load_reports(tmp_path))}
    assert rows["lossless_vs_zstd"]["status"] == "missed" and rows["lossless_vs_zstd"]["quick"]
    assert rows["roi_decode_msps"]["status"] == "met"
    assert rows["lossy_vs_delta_zstd"]["status"] == "no run"
    assert rows["height_msps"]["status"] == "no run"  # no terrain report there


def test_the_markers_are_required(tmp_path):
    with pytest.raises(ValueError, match="markers"):
        goals.with_table("no markers here", "| table |\n")
