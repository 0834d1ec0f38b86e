"""The short form of the plant-scale benchmark (``make bench-plant`` runs the full one): tiny
sizes, a real router and a real PostgreSQL on loopback; every figure is there, positive and finite."""

import json
import math

import pytest

from bench import bench_plant

REQUIRED = {
    "payloads": ("state_gear_normal", "state_gear_caution", "state_chain_normal", "state_chain_warning",
                 "state_mean", "diagnostics", "health"),
    "ingest": ("cpu_us_per_sample", "wall_us_per_sample", "append_wall_us", "samples_per_cpu_s"),
    "postgres": ("rows_per_s", "historian_cpu_us_per_row"),
}


def numbers(x, path=""):
    """Every number in ``x`` (nested dicts and lists) with its path."""
    if isinstance(x, bool):
        return
    if isinstance(x, (int, float)):
        yield path, x
    elif isinstance(x, dict):
        for k, v in x.items():
            yield from numbers(v, f"{path}/{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            yield from numbers(v, f"{path}/{i}")


@pytest.mark.timeout(120)
def test_the_smoke_form_gives_every_figure(tmp_path, capsys):
    from pg_support import pg_bindir

    if pg_bindir() is None:
        pytest.skip("PostgreSQL's initdb is not installed (Debian: apt-get install postgresql)")
    out = tmp_path / "plant.json"
    bench_plant.main(["--smoke", "--out", str(out)])
    fig = json.loads(out.read_text())
    for section, keys in REQUIRED.items():
        for key in keys:
            assert fig[section][key] > 0, (section, key)
    for key in ("server_backend_cpu_us_per_row", "retention_backend_cpu_us_per_row"):  # None: under two of /proc's ticks
        assert fig["postgres"][key] is None or fig["postgres"][key] > 0, key
    assert fig["router"] and all(r["delivered"] > 0 for r in fig["router"])
    for table in ("evidence_trend", "drive_event"):
        assert fig["postgres"]["tables"][table]["bytes_per_row"] > 0
    plant = fig["plant"]
    assert set(plant["routers"]) == {"1", "3", "10"}
    assert plant["storage_gb"]["trend_at_retention"] > 0 and plant["historian"]["ingest_cores"] > 0
    bad = [(p, v) for p, v in numbers(fig) if not math.isfinite(v) or v < 0]
    assert not bad, bad
    table = capsys.readouterr().out
    assert "| figure | value | basis |" in table and "routers" in table
