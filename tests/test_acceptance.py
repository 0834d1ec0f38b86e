"""Acceptance experiment (issue: foundation, part 10): the paper's Table 4 and Table 5 patterns on
the rig simulator, and the false-alarm rate on fresh healthy records. The short form runs by
default; ``PMSM_SLOW=full`` runs the full one (30 healthy + 30 faulty per condition, 4 s records)."""

import pytest

from bench.acceptance import TABLE4, run


@pytest.fixture(scope="module")
def result(full_form):
    return run(quick=not full_form, say=lambda s: None)


@pytest.mark.slow
@pytest.mark.parametrize("kind, condition", [(k, c) for k in TABLE4 for c in TABLE4[k]])
def test_table4_pattern(result, kind, condition):
    got = result[kind]["conditions"][condition]
    assert got["majority"] == got["expected"], got


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(TABLE4))
def test_fresh_healthy_records_are_normal(result, kind, full_form):
    # The full form (40 fresh records) must meet the 95 % target. The short form has 30: the
    # decision's false-alarm rate is ~4 % (docs/method.md), so one false alarm more or less is
    # sampling luck there, and its bound is 90 %.
    assert result[kind]["fresh_normal_fraction"] >= (0.95 if full_form else 0.90), result[kind]["fresh_states"]


@pytest.mark.slow
def test_table5_diagonal_is_lowest(result):
    m = result["table5"]["nrmse"]
    for r, row in enumerate(m):
        assert min(range(len(row)), key=row.__getitem__) == r, m
    assert all(row[r] < 0.08 for r, row in enumerate(m))
