"""The whole-VIO benchmark runs at a small size and reports what it measured."""

from __future__ import annotations

import pytest

from benchmarks.bench_vio import main

pytestmark = pytest.mark.slow  # renders and runs short flights through the benchmark (~50 s)


def test_bench_vio_runs(capsys) -> None:  # type: ignore[no-untyped-def]
    out = main(["--duration", "10", "--smart"])  # a 6 s loop reaches 43 m/s, beyond the divergence bound max_speed
    text = capsys.readouterr().out
    assert "real-time factor" in text and "inline front end / front-end process" in text
    assert len(out["runs"]) == 6  # dcc, scc x (front-end process, inline, offsets held)
    for r in out["runs"]:
        assert r["wall_s"] > 0 and r["data_s"] > 4.0 and r["failed_updates"] == 0
        assert r["real_time_factor"] == r["wall_s"] / r["data_s"]
        if r["estimate_offsets"]:  # synchronized flight, true offsets 0: the 1 ms
            assert max(abs(x) for x in r["time_offsets_ms"]) < 1.0, r["time_offsets_ms"]
    assert out["dcc_inline_over_parallel"] > 0 and out["scc_inline_over_parallel"] > 0
    assert out["dcc_offsets_estimated_over_held_time"] > 0 and "offsets estimated / held at 0" in text
    smart = out["smart"]  # the structureless-landmark run of the same flight
    assert smart["landmarks"] == "smart" and smart["failed_updates"] == 0 and "smart / explicit landmarks" in text
    assert out["dcc_smart_over_explicit_rmse"] > 0 and smart["joint_rmse_rad"] is not None
