"""Benchmark result rows (dla.bench/1), the Pareto frontier and the report, on toy inputs; the
bench package's modules import one way (rows <- suites <- charts, report)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dlacli.bench.charts import draw_chart
from dlacli.bench.report import report_markdown
from dlacli.bench.rows import (
    FORMAT,
    append_rows,
    check_row,
    label,
    make_row,
    pareto_front,
    points,
    read_rows,
    stability_row,
)
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
                rows.append(
                    make_row(
                        "unproject",
                        {"steps": steps},
                        split,
                        seconds + subject,
                        None,
                        _metrics(masked + bump + shift),
                        subject=subject,
                        device="cpu (2 threads)",
                    )
                )
    return rows


def test_rows_round_trip_and_bad_rows_are_refused(tmp_path):
    rows = _toy_rows()
    path = tmp_path / "r.jsonl"
    append_rows(path, rows[:5])
    append_rows(path, rows[5:])  # a second run adds to the first
    assert read_rows(path) == json.loads(json.dumps(rows))
    good = rows[0]
    for change, needle in (
        ({"format": "dla.bench/9"}, "format"),
        ({"split": "sideways"}, "split"),
        ({"seconds": float("nan")}, "seconds"),
        ({"seconds": -1.0}, "seconds"),
        ({"metrics": {**good["metrics"], "iou": True}}, "iou"),
        ({"metrics": {"psnr": 1.0}}, "psnr_masked"),
        ({"method": 3}, "method"),
    ):
        with pytest.raises(DlaInputError, match=needle):
            check_row({**good, **change})
    (tmp_path / "bad.jsonl").write_text(json.dumps(good) + "\n{not json\n")
    with pytest.raises(DlaInputError, match="bad.jsonl:2"):
        read_rows(tmp_path / "bad.jsonl")
    assert good["format"] == FORMAT


def test_points_aggregate_over_subjects():
    pts = {p["label"]: p for p in points(_toy_rows(), "novel_views")}
    assert set(pts) == {"unproject steps=0", "unproject steps=50", "unproject steps=100"}
    p = pts["unproject steps=50"]
    assert p["subjects"] == 2 and p["seconds"] == pytest.approx(45.5) and p["value"] == pytest.approx(20.1)


def test_points_of_two_kinds_of_subject_keep_apart():
    """The same method on lit and on albedo subjects are two points with two labels (one table
    row each); with one kind of subject the labels stay short."""
    rows = []
    for appearance, masked in (("lit", 20.0), ("albedo", 18.0)):
        for subject in (1, 2):
            config = {"steps": 0, "appearance": appearance, "wardrobe": "heldout", "res": 512}
            rows.append(make_row("unproject", config, "novel_views", 5.0, None, _metrics(masked), subject=subject))
    pts = {p["label"]: p for p in points(rows, "novel_views")}
    assert set(pts) == {"unproject steps=0 (lit, heldout, 512 px)", "unproject steps=0 (albedo, heldout, 512 px)"}
    assert pts["unproject steps=0 (albedo, heldout, 512 px)"]["value"] == pytest.approx(18.0)
    assert pts["unproject steps=0 (lit, heldout, 512 px)"]["subjects"] == 2
    assert [p["label"] for p in points(rows[:2], "novel_views")] == ["unproject steps=0"]


def test_pareto_front_on_a_toy_set():
    pts = [
        {"label": k, "seconds": s, "value": v}
        for k, s, v in (
            ("a", 1, 10),
            ("b", 2, 12),
            ("c", 3, 11),
            ("d", 4, 15),
            ("e", 4, 14),
            ("f", 0.5, 9),
            ("g", 2, 12),
        )
    ]
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
    assert "| **unproject steps=50** | 2 |" in md and "| unproject steps=100 | 2 |" in md
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
    result = {
        "res": 512,
        "rows": [
            {"seed": 7, "steps": 0, "lift_s": 2.0, "novel_views": scores, "novel_poses": scores},
            {"seed": 7, "steps": 50, "lift_s": 40.0, "novel_views": scores, "novel_poses": scores},
        ],
    }
    rows = result_rows(result)
    assert [(r["method"], r["config"]["steps"], r["split"]) for r in rows] == [
        ("unproject", 0, "novel_views"),
        ("unproject", 0, "novel_poses"),
        ("unproject", 50, "novel_views"),
        ("unproject", 50, "novel_poses"),
    ]
    assert all(r["subject"] == 7 and r["peak_mb"] is None for r in rows)


def test_rows_from_before_the_registry_read_under_its_names(tmp_path):
    """Rows that said "refine", "unproject+refine" or "learned+refine" (docs/benchmarks.jsonl
    holds some) are read as the registry names them; an unprojection that recorded no steps
    made none. Other rows are read as they are."""
    m = _metrics(19.0)
    old = [
        make_row("unproject+refine", {"steps": 50, "res": 512}, "novel_views", 40.0, None, m, device="cpu"),
        make_row("learned+refine", {"checkpoint": "ab" * 8, "steps": 20}, "novel_views", 9.0, None, m, device="cpu"),
        make_row("unproject", {"steps": 0}, "novel_views", 2.0, None, m, device="cpu"),
        stability_row("refine", {"steps": 50, "subject_fill": 0.8}, "novel_views", 3.0, None, m, "pose_noise", 0.0),
        stability_row("unproject", {"res": 48}, "novel_views", 3.0, None, m, "pose_noise", 0.0, device="cpu"),
        make_row("m", {}, "novel_views", 1.0, None, m, device="cpu"),
    ]
    append_rows(tmp_path / "old.jsonl", old)
    rows = read_rows(tmp_path / "old.jsonl")
    assert [(r["method"], r["config"]) for r in rows] == [
        ("unproject", {"steps": 50, "res": 512}),
        ("learned", {"checkpoint": "ab" * 8, "steps": 20}),
        ("unproject", {"steps": 0}),
        ("unproject", {"steps": 50, "subject_fill": 0.8}),
        ("unproject", {"res": 48, "steps": 0}),
        ("m", {}),
    ]
    labels = ["unproject steps=50", "learned steps=20", "unproject steps=0", "unproject steps=50", "unproject steps=0"]
    assert [label(r) for r in rows] == [*labels, "m"]


def test_bench_modules_import_one_way():
    """No import cycle in the bench package (imports inside functions count too): rows and score
    import no other bench module but metrics, the suites neither charts nor report."""
    import ast
    from pathlib import Path

    import dlacli.bench

    folder = Path(dlacli.bench.__file__).parent
    graph = {}
    for path in folder.glob("*.py"):
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            names = [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
            names += [a.name for a in node.names] if isinstance(node, ast.Import) else []
            found |= {n.split(".")[2] for n in names if n.startswith("dlacli.bench.")}
        graph[path.stem] = found
    assert graph["rows"] <= {"score"} and graph["score"] <= {"metrics"}
    for suite in ("accuracy", "budget", "pipeline", "speed", "stability"):
        assert not graph[suite] & {"charts", "report"}, suite

    def reach(start, seen):
        for nxt in graph.get(start, ()):
            assert nxt not in seen, f"import cycle through {seen + [nxt]}"
            reach(nxt, seen + [nxt])

    for module in graph:
        reach(module, [module])
