"""The front-end benchmark runs (small size) and measures something plausible."""

from __future__ import annotations

from benchmarks.bench_frontend import main


def test_bench_frontend_runs(capsys) -> None:  # type: ignore[no-untyped-def]
    out = main(["--frames", "8"])
    text = capsys.readouterr().out
    assert "front end / bare KLT" in text and "real-time factor" in text
    assert out["cpu_ms"] > 0 and out["klt_ms"] > 0 and out["render_ms"] > 0
    assert out["cpu_ms"] > out["klt_ms"]  # the front end does more than bare forward KLT
