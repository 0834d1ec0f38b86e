"""Physics simulator of the paper's test rig (Tables 2-3, Figs. 2 and 4-6).

Closed-loop interior PMSM drive (eq. 5, field-oriented control with i_d = 0, speed PI), two-mass
transmission (eqs. 7-9) with gear or chain faults, DAQ at 25 kHz, optional physical effects::

    from agent.simulator import simulate, CONDITIONS, EFFECTS, RigParams
    rec = simulate(profile, "gear_severe_wear", load_pct=80.0, seconds=4.0, seed=1)

Modules: ``rig`` (parameters, operating point), ``conditions`` (fault table, effects),
``plant`` (numba kernel), ``simulation`` (``simulate``).
"""

from agent.simulator.conditions import CONDITIONS, EFFECTS, HEALTHY_RIPPLE, conditions_for
from agent.simulator.rig import RigParams
from agent.simulator.simulation import simulate

__all__ = ["simulate", "CONDITIONS", "EFFECTS", "RigParams", "HEALTHY_RIPPLE", "conditions_for"]
