"""Saved benchmark results: their file names, and the README table made from them."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from spectral_fit.cli.commands.bench import results_path, results_table

META = {"date": "2026-12-05", "cpu": "AMD EPYC 9R14 Processor", "cores": 2, "backend": "cpu",
        "devices": ["TFRT_CPU_0"]}


def test_results_path_names_the_date_and_machine():
    p = results_path(META)
    assert p.parent.parts[-2:] == ("benchmarks", "results")
    assert p.name == "2026-12-05-amd-epyc-9r14-processor-2c.json"
    gpu = results_path({**META, "backend": "gpu", "devices": ["cuda:0 NVIDIA H100"]})
    assert gpu.name == "2026-12-05-amd-epyc-9r14-processor-2c-cuda-0-nvidia-h100.json"


def test_table_has_a_row_per_case_and_a_column_per_run():
    a = {"_meta": META, "frame_paper": {"median_ms": 16.71, "compile_s": 15.2, "n": 20},
         "cold_start_s": {"median_ms": 510.0, "compile_s": 22.4, "n": 3}}
    b = {"_meta": {**META, "date": "2026-12-06"},
         "frame_paper": {"median_ms": 17.0, "compile_s": 16.0, "n": 20}}
    lines = results_table([a, b]).splitlines()
    assert lines[0] == ("| case | 2026-12-05, AMD EPYC 9R14 Processor (2 cores, cpu) "
                        "| 2026-12-06, AMD EPYC 9R14 Processor (2 cores, cpu) |")
    assert lines[2] == "| `cold_start_s` | 510 ms (compile 22.4 s) | — |"
    assert lines[3] == "| `frame_paper` | 16.7 ms (compile 15.2 s) | 17 ms (compile 16 s) |"
    assert len(lines) == 4


@pytest.mark.parametrize("content, field", [("{not json", "line 1"),
                                            (json.dumps({"frame": {}}), "_meta")])
def test_a_bad_results_file_is_a_one_line_error(tmp_path, content, field):
    bad = tmp_path / "bad.json"
    bad.write_text(content)
    r = subprocess.run([sys.executable, "-m", "spectral_fit", "bench", "--table", str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert str(bad) in r.stderr and field in r.stderr and "Traceback" not in r.stderr


def test_a_second_run_of_the_day_adds_its_cases_to_the_file(tmp_path):
    from spectral_fit.cli.commands.bench import merged_results

    path = tmp_path / "day.json"
    first = {"_meta": META, "frame_paper": {"median_ms": 16.7, "compile_s": 15.2, "n": 20},
             "fit_demo": {"median_ms": 100.0, "compile_s": 1.7, "n": 20}}
    assert merged_results(path, first) is first  # no file yet
    path.write_text(json.dumps(first))
    gl = {"_meta": {**META, "gl_renderer": "llvmpipe"},
          "gl_paper": {"median_ms": 80.0, "compile_s": 9.0, "n": 20},
          "fit_demo": {"median_ms": 90.0, "compile_s": 1.5, "n": 20}}
    got = merged_results(path, gl)
    assert set(got) == {"_meta", "frame_paper", "fit_demo", "gl_paper"}
    assert got["fit_demo"]["median_ms"] == 90.0 and got["frame_paper"]["median_ms"] == 16.7
    assert got["_meta"]["gl_renderer"] == "llvmpipe" and got["_meta"]["cpu"] == META["cpu"]


def test_table_adds_the_speed_ratios_and_the_cold_start():
    run = {"_meta": META,
           "frame_paper": {"median_ms": 20.0, "compile_s": 15.0, "n": 20},
           "gl_paper": {"median_ms": 50.0, "compile_s": 0.2, "n": 20},
           "cold_start_s": {"median_ms": 7e4, "compile_s": 60.0, "n": 1,
                            "first_frame_after_import_cold_s": 69.8,
                            "first_frame_after_import_warm_s": 1.47}}
    lines = results_table([run]).splitlines()
    assert lines[2] == "| `cold_start_s` | 69.8 s cold, 1.47 s with warm caches |"
    assert lines[-1] == "| `gl_paper` / `frame_paper` | 2.50× |"  # 50 / 20
    assert len(lines) == 6  # no ratio row for cases the run lacks
