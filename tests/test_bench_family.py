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


def test_misses_are_grouped_by_the_attribute_that_concentrates_them():
    """Misses that follow one attribute are named with Fisher's exact p (scipy's, against the
    independent hypergeometric tail written here) and whether the finding survives Bonferroni over
    every attribute value tested; misses spread evenly name nothing."""
    import math

    from bench.bench_family import ATTRIBUTES, misses_by_attribute

    def drive(j, encoder):
        d = {k: "x" for k in ATTRIBUTES}
        d.update(encoder=encoder, inverter=("switched", "averaged")[j % 2])
        return d

    rows = [(drive(j, False), j % 7 != 0) for j in range(35)] + [(drive(j, True), j % 8 == 0) for j in range(25)]
    found = misses_by_attribute(rows)
    assert found and found[0].startswith("encoder=False: 30/35 against 4/25"), found
    # two-sided Fisher p: the hypergeometric probabilities no larger than the table's, summed
    n1, n2, m = 35, 25, 34
    prob = [math.comb(m, k) * math.comb(n1 + n2 - m, n1 - k) / math.comb(n1 + n2, n1) for k in range(0, n1 + 1)
            if 0 <= n1 - k <= n1 + n2 - m]
    lo = max(0, n1 - (n1 + n2 - m))
    p = sum(q for q in prob if q <= prob[30 - lo] * (1 + 1e-9))
    assert f"p = {p:.2g}" in found[0] and "holds over all" in found[0]
    even = [(drive(j, j % 2 == 0), j % 3 == 0) for j in range(60)]
    assert misses_by_attribute(even) == []


def test_the_table_counts_the_first_ranked_misses_whose_records_were_named():
    """A first-ranked, revealable, not significant effect for which explain named how many records
    like these would settle it counts in its own column; one it named none for (records would not
    settle it, or another cause), one named for another candidate, or a significant one, do not."""
    from bench.bench_family import ATTRIBUTES, table

    def result(seed, significant, named):
        row = {"effect": "current_offset", "rank": 1, "revealable": True, "significant": significant,
               "answer": None, "gain": 3.0, "error": 0.1, "wrong_claims": [], "note": "", "records_named": named}
        return {"seed": seed, "drive": {k: "x" for k in ATTRIBUTES}, "rows": [row],
                "null": {"claims": [], "answer": None}}

    results = [result(1, False, {"current_offset": 5}), result(2, False, {"current_offset": None}),
               result(3, False, {"voltage_delay": 6}), result(4, True, {})]
    line = next(x for x in table(results, ["current_offset"]).splitlines() if x.startswith("| current_offset"))
    assert line.split(" | ")[3:5] == ["1/4 = 25%", "1"], line


def test_the_census_of_figures_said_counts_each_figure_against_its_truth_on_its_own_scale():
    """figure_errors: a magnitude relative, a delay and its rotation against max(|d|, 1 sample), a
    harmonic's phase against PHASE_MAX and only for a harmonic a fifth of the largest or more;
    a figure not said (None) or without a truth is not counted; whether the truth is outside the
    bound explain gave. The table counts the figures of significant claims only."""
    import math

    from bench.bench_family import ATTRIBUTES, ERROR_MAX, PHASE_MAX, figure_errors, table

    true = {"psi_5_Wb": 0.01, "phase_5_rad": 3.1, "psi_7_Wb": 0.001, "phase_7_rad": 0.0,
            "delay_samples": -1.5, "advance_samples": 0.5, "offset_A": 0.2}
    said = {"psi_5_Wb": 0.013, "phase_5_rad": -3.1, "psi_7_Wb": 0.005, "phase_7_rad": 2.0, "delay_samples": -1.2,
            "advance_samples": 0.5, "rotation_samples": -0.2, "offset_A": None, "lambda_H": 0.1}
    err = figure_errors(said, true, {"psi_5_Wb": 0.002, "delay_samples": 0.5})
    assert set(err) == {"psi_5_Wb", "phase_5_rad", "delay_samples", "advance_samples", "rotation_samples"}
    assert math.isclose(err["psi_5_Wb"][0], 0.3) and err["psi_5_Wb"][1] is True  # 0.003 off, bound 0.002
    assert math.isclose(err["phase_5_rad"][0], (2 * math.pi - 6.2) / PHASE_MAX * ERROR_MAX)  # across +-pi: 0.083 rad
    assert math.isclose(err["delay_samples"][0], 0.3 / 1.5) and err["delay_samples"][1] is False
    assert math.isclose(err["rotation_samples"][0], 0.8 / 1.0) and err["rotation_samples"][1] is None

    def result(seed, significant, offset, bound=0.05):
        row = {"effect": "current_offset", "rank": 1, "revealable": True, "significant": significant,
               "answer": None, "gain": 3.0, "error": 0.1, "wrong_claims": [], "note": "", "records_named": {},
               "truth": {"offset_A": 0.2}, "said": {"offset_A": offset}, "bound": {"offset_A": bound}}
        return {"seed": seed, "drive": {k: "x" for k in ATTRIBUTES}, "rows": [row],
                "null": {"claims": [], "answer": None}}

    results = [result(1, True, 0.21), result(2, True, 0.1), result(3, True, 0.29, 0.1), result(4, True, None),
               result(5, False, 0.5)]
    line = next(x for x in table(results, ["current_offset"]).splitlines() if x.startswith("| current_offset"))
    assert line.split(" | ")[8] == "2 of 3 (1 outside their bound)", line


def test_the_settle_check_takes_the_sets_with_records_named_and_counts_what_they_settled():
    """bench.bench_settle reruns every set where explain named at most ``most`` records (effect and
    null sets alike, the largest count of the set) and counts, per hidden effect, where it is now
    significant (and among the sets where it had been first), and every other effect claimed; on a
    null set every claim is another effect's."""
    from bench.bench_settle import named_sets, table

    def row(effect, rank, named):
        return {"effect": effect, "rank": rank, "records_named": named}

    results = [{"seed": 1, "null": {"records_named": {"voltage_delay": 6}},
                "rows": [row("current_offset", 1, {"current_offset": 5, "voltage_delay": 7}),
                         row("resistance_drift", 2, {"resistance_drift": 30})]},
               {"seed": 2, "null": {"records_named": {}}, "rows": [row("current_offset", 3, {"current_offset": 9})]}]
    named = named_sets(results, most=12)
    assert sorted(named) == [(1, "current_offset", 7), (1, "null", 6), (2, "current_offset", 9)]
    first = {(1, "current_offset"): True, (2, "current_offset"): False}
    done = {(1, "current_offset"): {"claims": ["current_offset"]},
            (2, "current_offset"): {"claims": ["magnetic_saturation"]},
            (1, "null"): {"claims": ["voltage_delay"]}}
    lines = table(named, done, first).splitlines()
    offset = next(x for x in lines if x.startswith("| current_offset"))
    assert offset.strip("| ").split(" | ")[1:5] == ["2 (1)", "9 (7-9)", "1 of 2 (1 of 1)", "1 (2: magnetic_saturation)"], offset
    null = next(x for x in lines if x.startswith("| null"))
    assert null.strip("| ").split(" | ")[3:5] == ["-", "1 (1: voltage_delay)"], null
