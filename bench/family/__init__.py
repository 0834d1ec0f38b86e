"""Randomised but physical PMSM drives: the ground truth for validating the model workbench.

Written from first principles, independently of the workbench's model (it imports nothing of
agent.model, agent.workbench, agent.effects, agent.simulator, agent.frames or agent.identify; only
the output types agent.records.Record and agent.profile.parse_profile).

    drive = draw_drive(seed)                                  # every attribute drawn
    hidden = {"flux_harmonics": draw_effect(drive, "flux_harmonics", seed=1)}
    recs = [simulate(drive, hidden, load, 2.5, seed=j) for j, load in enumerate((40, 60, 90, 100))]
    truth(drive, "flux_harmonics", hidden["flux_harmonics"], recs)
    revealable(drive, "flux_harmonics", (40, 60, 90, 100))
    profile(drive, nameplate=True)

Modules: ``machine`` (flux map from one energy function, magnet harmonics), ``drive`` (Drive,
draw_drive, profile), ``kernel`` (the numba loop), ``effects`` (EFFECTS, draw_effect, truth,
revealable), ``simulate``.
"""

from bench.family.drive import EXCITATIONS, Drive, draw_drive, profile
from bench.family.effects import EFFECTS, draw_effect, revealable, truth, voltage_path
from bench.family.simulate import simulate, simulate_detail

__all__ = ["EFFECTS", "EXCITATIONS", "Drive", "draw_drive", "draw_effect", "profile", "revealable", "simulate",
           "simulate_detail", "truth", "voltage_path"]
