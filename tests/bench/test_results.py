"""Benchmark result rows (dla.bench/1), the Pareto frontier and the report, on toy inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dlacli.bench.results import (FORMAT, append_rows, check_row, draw_chart, make_row, pareto_front, points,
                                  read_rows, report_markdown)  # fmt: skip
from dlacli.errors import DlaInputError


def _metrics(masked: float) -> dict:
    return {"psnr": masked + 8.0, "psnr_masked": masked, "ssim": 0.95, "iou": 0.93}


def _toy_rows() -> list[dict]:
    """Three settings x two subjects x two splits; steps=50 is slower and better than steps=0,
    steps=100 slower than 50 and no better (off the frontier)."""
    rows = []
    for subject, bump in ((1, 0.0), (2, 0.4)):
        for split, shift in (("novel_views", 0.0), ("novel_poses", -0.5)):
            for steps, seconds, masked in ((0, 3.0, 18.7), (50, 44.0, 19.9), (100, 80.0, 19.8)):
                method = "unproject" if steps == 0 else "unproject+refine"
                rows.append(make_row(method, {"steps": steps}, split, seconds + subject, None,
                                     _metrics(masked + bump + shift), subject=subject, device="cpu (2 threads)"))  # fmt: skip
    return rows


def test_rows_round_trip_and_bad_rows_are_refused(tmp_path):
    rows = _toy_rows()
    path = tmp_path / "r.jsonl"
    append_rows(path, rows[:5])
    append_rows(path, rows[5:])  # a second run adds to the first
    assert read_rows(path) == json.loads(json.dumps(rows))
    good = rows[0]
    for change, needle in (({"format": "dla.bench/9"}, "format"), ({"split": "sideways"}, "split"),
                           ({"seconds": float("nan")}, "seconds"), ({"seconds": -1.0}, "seconds"),
                           ({"metrics": {**good["metrics"], "iou": True}}, "iou"),
                           ({"metrics": {"psnr": 1.0}}, "psnr_masked"), ({"method": 3}, "method")):  # fmt: skip
        with pytest.raises(DlaInputError, match=needle):
            check_row({**good, **change})
    (tmp_path / "bad.jsonl").write_text(json.dumps(good) + "\n{not json\n")
    with pytest.raises(DlaInputError, match="bad.jsonl:2"):
        read_rows(tmp_path / "bad.jsonl")
    assert good["format"] == FORMAT


def test_points_aggregate_over_subjects():
    pts = {p["label"]: p for p in points(_toy_rows(), "novel_views")}
    assert set(pts) == {"unproject steps=0", "unproject+refine steps=50", "unproject+refine steps=100"}
    p = pts["unproject+refine steps=50"]
    assert p["subjects"] == 2 and p["seconds"] == pytest.approx(45.5) and p["value"] == pytest.approx(20.1)


def test_pareto_front_on_a_toy_set():
    pts = [{"label": k, "seconds": s, "value": v} for k, s, v in
           (("a", 1, 10), ("b", 2, 12), ("c", 3, 11), ("d", 4, 15), ("e", 4, 14), ("f", 0.5, 9), ("g", 2, 12))]
    front = [p["label"] for p in pareto_front(pts)]
    # c is beaten by b (faster, better), e by d (as fast, better); b and g tie (both kept)
    assert front == ["f", "a", "b", "g", "d"]
    assert pareto_front([]) == []


def test_chart_and_report_from_a_toy_run(tmp_path):
    from PIL import Image

    pytest.importorskip("matplotlib")
    rows = _toy_rows()
    png = draw_chart(rows, tmp_path / "chart.png")
    image = np.asarray(Image.open(png).convert("RGB"))
    assert image.shape[1] > 1.5 * image.shape[0]  # two panels side by side: novel views, novel poses
    assert image.std() > 10  # something is drawn
    md = report_markdown(rows, "chart.png")
    assert "![time against masked PSNR](chart.png)" in md
    assert "| **unproject+refine steps=50** | 2 |" in md and "| unproject+refine steps=100 | 2 |" in md
    assert md.count("## ") == 2


def test_bench_report_command(tmp_path, capsys):
    from dlacli.cli.app import main

    pytest.importorskip("matplotlib")
    results = tmp_path / "r.jsonl"
    append_rows(results, _toy_rows())
    with pytest.raises(SystemExit) as info:
        main(["bench", "report", str(results), "-o", str(tmp_path / "bench.md")])
    assert info.value.code == 0
    assert (tmp_path / "bench.png").is_file() and "## novel views" in (tmp_path / "bench.md").read_text()
    with pytest.raises(SystemExit) as info:
        main(["bench", "report", str(results), "-o", str(tmp_path / "bench.txt")])
    assert info.value.code == 2 and "bench.txt" in capsys.readouterr().err


def test_pipeline_results_become_rows():
    from dlacli.bench.pipeline import result_rows

    scores = {"psnr": 28.0, "psnr_masked": 20.0, "ssim": 0.95, "iou": 0.94}
    result = {"res": 512, "rows": [{"seed": 7, "steps": 0, "lift_s": 2.0, "novel_views": scores, "novel_poses": scores},
                                   {"seed": 7, "steps": 50, "lift_s": 40.0, "novel_views": scores, "novel_poses": scores}]}
    rows = result_rows(result)
    assert [(r["method"], r["config"]["steps"], r["split"]) for r in rows] == [
        ("unproject", 0, "novel_views"), ("unproject", 0, "novel_poses"),
        ("unproject+refine", 50, "novel_views"), ("unproject+refine", 50, "novel_poses")]
    assert all(r["subject"] == 7 and r["peak_mb"] is None for r in rows)
