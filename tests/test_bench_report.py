"""benchmarks/RESULTS.md is regenerated from the JSONs, and the sections written by hand survive it."""

from __future__ import annotations

import json

from benchmarks import run


def test_rewriting_the_results_keeps_the_sections_written_by_hand(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    machine = {"cpu": "test cpu", "cpus": 2, "python": "3", "platform": "p", "numpy": "2", "torch": "2"}
    (results / "probe.json").write_text(json.dumps({"machine": machine, "frames_per_s": 12.5}))
    hand = f"## An A/B timing\n{run.BY_HAND}\n\nratio 1.01, measured in alternating pairs.\n"
    report = tmp_path / "RESULTS.md"
    report.write_text(f"# Benchmark results\n\n## A stale generated section\n\nold numbers\n\n{hand}")

    run.write_report("python -m benchmarks.run --report-only", results, report)
    first = report.read_text()
    assert hand in first
    assert "old numbers" not in first  # generated sections are generated anew
    assert "frames_per_s" in first and first.index("frames_per_s") < first.index("## An A/B timing")
    run.write_report("python -m benchmarks.run --report-only", results, report)
    assert report.read_text() == first  # and again: nothing doubles, nothing is lost
