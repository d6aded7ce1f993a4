"""Package-level behaviour: lazy imports, the public names, the CLI entry point."""

import json
import subprocess
import sys

import pytest

import spectral_fit
from spectral_fit.cli import COMMANDS, main


def test_import_is_light():
    """`import spectral_fit` must not start JAX, colour-science, OpenEXR or matplotlib."""
    code = (
        "import sys, spectral_fit, spectral_fit._runtime.errors, spectral_fit.color;"
        "heavy = [m for m in ('jax', 'colour', 'OpenEXR', 'matplotlib', 'equinox') "
        "if m in sys.modules]; print(heavy)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("name", spectral_fit.__all__)
def test_every_public_name_resolves(name):
    assert getattr(spectral_fit, name) is not None


def test_unknown_attribute():
    with pytest.raises(AttributeError):
        spectral_fit.no_such_thing  # noqa: B018


def test_cli_help_lists_commands(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def _bench_case_names() -> list[str]:
    from spectral_fit.bench import discover_cases

    return sorted(discover_cases())


def test_bench_one_case_json_schema(capsys):
    """One cheap benchmark case runs at its quick size and reports the bench JSON schema (the
    slow tier runs every case)."""
    assert "raster_paper" in _bench_case_names()
    assert main(["bench", "--quick", "--repeats", "2", "--json", "--cases", "raster_paper"]) == 0
    result = json.loads(capsys.readouterr().out)
    figures = result["raster_paper"]
    assert figures["n"] == 2
    assert 0 < figures["min_ms"] <= figures["median_ms"] <= figures["max_ms"]
    assert figures["compile_s"] > 0
    assert result["_meta"]["quick"] is True


@pytest.mark.slow
def test_bench_quick_json_schema(capsys):
    """Every benchmark case runs at its quick size and reports the bench JSON schema."""
    assert main(["bench", "--quick", "--repeats", "2", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    cases = {k: v for k, v in result.items() if not k.startswith("_")}
    for name, figures in cases.items():
        if "median_ms" not in figures:
            continue
        assert figures["n"] == 2, name
        assert 0 < figures["min_ms"] <= figures["median_ms"] <= figures["max_ms"], name
        assert figures["compile_s"] > 0, name
    # the live step on the benchmark scene (the live target's scene) beside the video's own
    bs = result["live_paper"]["benchmark_scene"]
    assert 0 < bs["min_ms"] <= bs["median_ms"] and bs["compile_s"] > 0
    assert bs["covered_pixels"] > 0 and not bs["overflow"]
    # ... and its whole loop on the benchmark video (markers found: the spheres are drawn)
    for e2e in (bs["end_to_end"], result["live_in_flight"]["benchmark_scene"]["end_to_end"]):
        assert e2e["covered_pixels"] > 0 and e2e["recompiles"] == 0
    assert bs["end_to_end"]["end_to_end_fps"] > 0
    assert result["_meta"]["quick"] is True


def test_bench_unknown_case_is_a_clear_error(capsys):
    assert main(["bench", "--cases", "nope"]) == 2
    assert "unknown case" in capsys.readouterr().err
