"""The whole-VIO benchmark runs at a small size and reports what it measured."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import bench_vio_persistence as persistence
from benchmarks import bench_vio_revision as revision
from benchmarks.bench_vio import main


@pytest.mark.slow  # renders and runs short flights through the benchmark (~50 s)
def test_bench_vio_runs(capsys) -> None:  # type: ignore[no-untyped-def]
    # 10 s: a 6 s loop reaches 43 m/s, beyond the divergence bound max_speed
    out = main(["--duration", "10", "--smart"])
    text = capsys.readouterr().out
    assert "real-time factor" in text and "inline front end / front-end process" in text
    assert len(out["runs"]) == 8  # dcc, scc x (front-end process, inline, offsets held, previous defaults)
    for r in out["runs"]:
        assert r["wall_s"] > 0 and r["data_s"] > 4.0 and r["failed_updates"] == 0
        assert r["real_time_factor"] == r["wall_s"] / r["data_s"]
        if r["estimate_offsets"]:  # synchronized flight, true offsets 0: the 1 ms
            assert max(abs(x) for x in r["time_offsets_ms"]) < 1.0, r["time_offsets_ms"]
    assert out["dcc_inline_over_parallel"] > 0 and out["scc_inline_over_parallel"] > 0
    assert out["dcc_offsets_estimated_over_held_time"] > 0 and "offsets estimated / held at 0" in text
    now = out["dcc_defaults_over_previous"]  # defaults (synchronized: none, 2.5 s) over all + 1.5 s, same flight
    assert set(now) == {"wall", "main_cpu", "translation_rmse", "joint_1_rmse", "joint_2_rmse"}
    assert all(v > 0 for v in now.values()) and "defaults (none persistent, 2.5 s) / previous defaults" in text
    resolved = {(r["persistent_requested"], r["persistent_landmarks"], r["lag"]) for r in out["runs"]}
    assert resolved == {("auto", "none", 2.5), ("all", "all", 1.5)}
    smart = out["smart"]  # the structureless-landmark run of the same flight
    assert smart["landmarks"] == "smart" and smart["failed_updates"] == 0 and "smart / explicit landmarks" in text
    assert out["dcc_smart_over_explicit_rmse"] > 0 and smart["joint_rmse_rad"] is not None


@pytest.mark.slow  # renders two 10 s flights and runs each twice (~1 min)
def test_bench_vio_persistence_over_flights(capsys) -> None:  # type: ignore[no-untyped-def]
    """Two short flights, each run with the defaults and without persistent landmarks: one line per flight
    and the ratios over both (pooled RMS and per-flight range) from the runs themselves."""
    out = persistence.main(["--seeds", "0-1", "--duration", "10"])
    text = capsys.readouterr().out
    assert text.count("seed ") == 2 and "2 flights, defaults (none persistent, 2.5 s) / previous defaults" in text
    pairs = out["runs"]
    assert [(r["persistent_landmarks"], r["lag"]) for pair in pairs for r in pair] == [("all", 1.5), ("none", 2.5)] * 2
    for pair in pairs:
        assert all(r["failed_updates"] == 0 and r["parallel"] and r["joint_rmse_rad"] is not None for r in pair)
    j1 = [pair[1]["joint_rmse_rad"][0] / pair[0]["joint_rmse_rad"][0] for pair in pairs]
    assert out["joint_1_rmse"]["min"] == min(j1) and out["joint_1_rmse"]["max"] == max(j1)


@pytest.mark.slow  # renders one 10 s flight and runs it twice in child processes (~40 s)
def test_bench_vio_revision_against_itself(capsys, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """This checkout as the "old" one: both children import this dcc_fg (checked by the benchmark) and, the
    front-end process being deterministic (to 1e-8 with the synchronized default), give the same accuracy;
    a folder without dcc_fg is refused before any work."""
    out = revision.main(["--old", str(revision.THIS_CHECKOUT), "--seeds", "0", "--duration", "10"])
    text = capsys.readouterr().out
    assert text.count("seed ") == 1 and "1 flights, this checkout / " in text
    ((before, after),) = out["runs"]
    assert before["code"] == after["code"] == str(revision.THIS_CHECKOUT)
    for key in ("translation_rmse", "joint_1_rmse", "joint_2_rmse"):
        assert out[key]["pooled"] == pytest.approx(1.0, abs=1e-4)
    assert out["wall_median"] > 0 and after["real_time_factor"] > 0
    with pytest.raises(SystemExit):
        revision.main(["--old", str(tmp_path)])
    assert "no dcc_fg package there" in capsys.readouterr().err


def test_revision_summary_without_joint_angles() -> None:
    """scc runs (no joint angles, as bench_vio_revision --mode scc gives): translation ratios only, pooled
    as RMS over the flights."""

    def run(t: float, wall: float) -> dict[str, object]:
        return {"normalized_translation_rmse_percent": t, "joint_rmse_rad": None, "wall_s": wall, "cpu_s": wall,
                "real_time_factor": wall / 60.0}  # fmt: skip

    out = persistence.summarize([(run(1.0, 20.0), run(2.0, 10.0)), (run(1.0, 30.0), run(1.0, 30.0))])
    assert set(out) == {"translation_rmse", "wall_median", "main_cpu_median", "real_time_factor_median"}
    assert out["translation_rmse"]["pooled"] == pytest.approx(np.sqrt(5.0 / 2.0) / 1.0)
    assert out["translation_rmse"]["min"] == 1.0 and out["translation_rmse"]["max"] == 2.0
    assert out["wall_median"] == pytest.approx(0.75)
    assert out["real_time_factor_median"] == pytest.approx([25.0 / 60.0, 20.0 / 60.0])


def test_persistence_summary_and_seeds() -> None:
    """The ratios of the persistence benchmark on made-up runs: pooled RMS ratio, mean, range, medians."""
    assert persistence.parse_seeds("0-3,7") == [0, 1, 2, 3, 7] and persistence.parse_seeds("5") == [5]

    def run(t: float, j1: float, wall: float) -> dict[str, object]:
        return {
            "normalized_translation_rmse_percent": t,
            "joint_rmse_rad": [j1, 1.0],
            "wall_s": wall,
            "cpu_s": wall,
            "real_time_factor": wall / 60.0,
        }

    s = persistence.summarize([(run(1.0, 3.0, 30.0), run(2.0, 3.0, 15.0)), (run(1.0, 4.0, 30.0), run(1.0, 4.0, 30.0))])
    assert s["translation_rmse"]["pooled"] == pytest.approx(np.sqrt(2.5))  # RMS(2, 1) / RMS(1, 1)
    assert s["translation_rmse"]["mean"] == pytest.approx(1.5) and s["translation_rmse"]["max"] == 2.0
    assert s["joint_1_rmse"]["pooled"] == pytest.approx(1.0) and s["joint_2_rmse"]["min"] == 1.0
    assert s["wall_median"] == pytest.approx(0.75) and s["real_time_factor_median"] == [0.5, pytest.approx(0.375)]
