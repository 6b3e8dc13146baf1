"""The whole-VIO benchmark runs at a small size and reports what it measured."""

from __future__ import annotations

import pytest

from benchmarks.bench_vio import main

pytestmark = pytest.mark.slow  # renders and runs short flights through the benchmark (~50 s)


def test_bench_vio_runs(capsys) -> None:  # type: ignore[no-untyped-def]
    # 10 s: a 6 s loop reaches 43 m/s, beyond the divergence bound max_speed
    out = main(["--duration", "10", "--smart", "--fast"])
    text = capsys.readouterr().out
    assert "real-time factor" in text and "inline front end / front-end process" in text
    assert len(out["runs"]) == 8  # dcc, scc x (front-end process, inline, offsets held, no persistent landmarks)
    for r in out["runs"]:
        assert r["wall_s"] > 0 and r["data_s"] > 4.0 and r["failed_updates"] == 0
        assert r["real_time_factor"] == r["wall_s"] / r["data_s"]
        if r["estimate_offsets"]:  # synchronized flight, true offsets 0: the 1 ms
            assert max(abs(x) for x in r["time_offsets_ms"]) < 1.0, r["time_offsets_ms"]
    assert out["dcc_inline_over_parallel"] > 0 and out["scc_inline_over_parallel"] > 0
    assert out["dcc_offsets_estimated_over_held_time"] > 0 and "offsets estimated / held at 0" in text
    fast = out["dcc_fast_over_default"]  # no persistent landmarks, 2.5 s window, on the same flight
    assert set(fast) == {"wall", "main_cpu", "translation_rmse", "joint_1_rmse", "joint_2_rmse"}
    assert all(v > 0 for v in fast.values()) and "no persistent landmarks, 2.5 s / defaults" in text
    assert {(r["persistent_landmarks"], r["lag"]) for r in out["runs"]} == {("all", 1.5), ("none", 2.5)}
    smart = out["smart"]  # the structureless-landmark run of the same flight
    assert smart["landmarks"] == "smart" and smart["failed_updates"] == 0 and "smart / explicit landmarks" in text
    assert out["dcc_smart_over_explicit_rmse"] > 0 and smart["joint_rmse_rad"] is not None
