"""The short form of the drive-family benchmark (``make bench-workbench`` runs the long one): two
random drives, each with every library effect hidden in turn and once with nothing hidden. What
must hold on every drive, whatever its draw: a null drive claims nothing, and no effect other
than the hidden one is ever claimed significant; every set ends in an answer (a ranking, or the
"no dynamics" note), never an error."""

import pytest

from agent.effects import EFFECTS
from bench.bench_family import FIRST_SEED, run_drive


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_family_short_form_claims_nothing_false(full_form):
    n = 6 if full_form else 2
    for seed in range(FIRST_SEED, FIRST_SEED + n):
        r = run_drive((seed, 0.6, True, tuple(EFFECTS), True, False))
        assert "error" not in r, r.get("traceback")
        assert r["null"]["claims"] == [], (seed, r["drive"], r["null"])
        assert [row["effect"] for row in r["rows"]] == list(EFFECTS)
        wrong = [(row["effect"], row["wrong_claims"]) for row in r["rows"] if row["wrong_claims"]]
        assert not wrong, (seed, r["drive"], wrong)
        for row in r["rows"]:
            assert row["rank"] is not None or row["answer"], (seed, row["effect"])
