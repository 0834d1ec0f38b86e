"""The agent's detection on motulator's drive (bench/bench_thirdparty_detection.py, short form):
a 0.5 % load-torque ripple at the driving shaft's rotation frequency is a spectrum warning naming
the driving gear's family; fresh healthy records raise no spectrum alarm."""

import pytest


@pytest.mark.slow
def test_detection_on_a_drive_nobody_here_wrote():
    pytest.importorskip("motulator")
    from bench.bench_thirdparty_detection import run

    res = run(n_healthy=4, n_fresh=2, n_faulty=1, seconds=1.0, say=lambda s: None, amplitudes=(0.07,))
    faulty = res["faulty"][0]
    assert faulty["spectrum"] == ["warning"] and "gear_driving" in faulty["families"]
    assert res["fresh"]["records"] == 2 and res["fresh"]["spectrum"] == ["normal"] * 2
