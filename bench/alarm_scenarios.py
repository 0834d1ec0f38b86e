"""A simulated drive in continuous operation, with the nuisances a plant has, streamed through the
real pipeline (agent.pipeline.DriveMonitor): the material of the false-alarm benchmark
(bench/bench_alarms.py) and of its short form in the tests (tests/test_alarms.py).

Nuisances (:class:`Plant`):

* thermal drift: winding and magnet temperature follow the load with a first-order lag
  (``thermal_tau_s``); from a cold start at the top setpoint R_s rises ``r_rise`` (+30 %) within
  the first hour and psi_m falls with the magnet temperature (``magnet_share`` of the winding's rise);
* load wander within the tolerance band: an Ornstein-Uhlenbeck process (``wander_pct`` sd,
  ``wander_tau_s``), clipped at 2 sd;
* operating-point changes: the load setpoint steps between ``setpoints`` at ``changes_per_hour``
  (Poisson), inside a segment (the simulator's load step: the drive's speed loop answers it in the
  stream, as in a plant);
* healthy mesh ripple that differs from stretch to stretch: each segment of operation
  (``segment_s`` uniform) is a new simulator session with its own ripple amplitudes, load and
  temperature spread;
* sensor noise (the simulator's DAQ noise).

Consecutive segments are separate streams (the pipeline restarts its windows, as after a gap);
a fault starts *inside* a segment (healthy and faulty records of the same seed spliced), so its
onset is not a jump in the signal.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from agent.library import ModelLibrary
from agent.pipeline import DriveMonitor, PipelineConfig
from agent.simulator import simulate
from agent.simulator.rig import RigParams
from protocols.base import Block

BLOCK = 2500  #: samples per block handed to the pipeline (0.1 s at 25 kS/s)


@dataclass(frozen=True)
class Plant:
    """How the simulated drive is operated (see the module docstring)."""

    setpoints: tuple[float, ...] = (80.0, 60.0)  #: load setpoints, % of rated torque
    changes_per_hour: float = 3.0
    wander_pct: float = 1.0  #: sd of the load wander, %-points (clipped at 2 sd: within the +-5 % band)
    wander_tau_s: float = 300.0
    segment_s: tuple[float, float] = (20.0, 90.0)  #: length of one session of operation, s
    r_rise: float = 0.30  #: R_s rise from cold to hot at the top setpoint
    magnet_share: float = 0.6  #: magnet temperature rise / winding temperature rise
    thermal_tau_s: float = 1200.0  #: s, first-order thermal lag (hot within an hour)
    cold_start: bool = True


@dataclass
class Segment:
    index: int  #: segment number since the start of operation (its simulator seed derives from it)
    t0: float  #: s since the start of operation
    seconds: float
    load_pct: float
    condition: str
    t_winding_rise: float  #: K over ambient
    onset_s: float | None = None  #: fault onset within the segment, s (None: no onset in it)
    step: tuple[float, float] | None = None  #: (s into the segment, load % after): a setpoint change in it


class Operation:
    """A drive's operation over time: segments with load, temperature and condition."""

    def __init__(self, plant: Plant, seed: int, fault: str | None = None, fault_at_s: float | None = None,
                 start_setpoint: float | None = None, changes: bool = True):
        self.plant, self.rng = plant, np.random.default_rng(seed)
        self.fault, self.fault_at = fault, fault_at_s
        self.setpoint = plant.setpoints[0] if start_setpoint is None else start_setpoint
        self.changes = changes
        top = max(plant.setpoints) / 100.0
        self.dT_w_top = plant.r_rise / RigParams().alpha_cu  # K at the top setpoint
        self.k_thermal = self.dT_w_top / top ** 2  # K per load^2
        self.t, self.wander, self.count = 0.0, 0.0, 0
        self.seed = seed
        self.T_w = 0.0 if plant.cold_start else self.k_thermal * (self.setpoint / 100) ** 2

    def segments(self, seconds: float) -> Iterator[Segment]:
        p, rng = self.plant, self.rng
        while self.t < seconds - 1e-9:
            dur = min(float(rng.uniform(*p.segment_s)), seconds - self.t)
            a = math.exp(-dur / p.wander_tau_s)
            self.wander = a * self.wander + math.sqrt(1 - a * a) * p.wander_pct * float(rng.standard_normal())
            wander = float(np.clip(self.wander, -2 * p.wander_pct, 2 * p.wander_pct))
            load, step = self.setpoint + wander, None
            if self.changes and len(p.setpoints) > 1 and rng.random() < p.changes_per_hour * dur / 3600.0:
                self.setpoint = float(rng.choice([s for s in p.setpoints if s != self.setpoint]))
                step = (float(rng.uniform(0.0, dur)), self.setpoint + wander)
            target = self.k_thermal * (load / 100.0) ** 2
            self.T_w = target + (self.T_w - target) * math.exp(-dur / p.thermal_tau_s)
            onset = None
            cond = "healthy"
            if self.fault and self.fault_at is not None and self.t + dur > self.fault_at:
                cond = self.fault
                if self.t <= self.fault_at:
                    onset = self.fault_at - self.t
            yield Segment(self.count, self.t, dur, load, cond, self.T_w, onset, step)
            self.t += dur
            self.count += 1

    def record(self, profile, seg: Segment):
        """The segment's record from the rig simulator, with its temperatures."""
        seed = self.seed * 1_000_003 + seg.index
        x = seg.load_pct / 100.0
        dT_m = self.plant.magnet_share * seg.t_winding_rise
        rig = dataclasses.replace(RigParams(), T_amb=RigParams().T_amb + dT_m,
                                  dT_w_rated=(seg.t_winding_rise - dT_m) / max(x * x, 1e-6), dT_m_rated=0.0)
        kw = dict(seed=seed, rig=rig, load_step=seg.step)
        if seg.onset_s is None:
            return simulate(profile, seg.condition, seg.load_pct, seg.seconds, **kw)
        healthy = simulate(profile, "healthy", seg.load_pct, seg.seconds, **kw)
        faulty = simulate(profile, seg.condition, seg.load_pct, seg.seconds, **kw)
        k = int(round(seg.onset_s * profile.sampling.rate_hz))
        return dataclasses.replace(healthy, v_abc=np.concatenate([healthy.v_abc[:, :k], faulty.v_abc[:, k:]], 1),
                                   i_abc=np.concatenate([healthy.i_abc[:, :k], faulty.i_abc[:, k:]], 1))


def stream(monitor: DriveMonitor, op: Operation, profile, seconds: float, on_status=None, until=None) -> int:
    """Feed operation up to ``seconds`` into ``monitor`` as blocks; ``on_status(t_s, status, segment)``
    per hop (t_s: time since the start of operation at the hop's end); stop early once ``until()``
    is true (checked per block). Returns hops seen."""
    rate = profile.sampling.rate_hz
    first, hops = 0, 0
    for seg in op.segments(seconds):
        rec = op.record(profile, seg)
        for start in range(0, rec.n - BLOCK + 1, BLOCK):
            cut = slice(start, start + BLOCK)
            for status in monitor.process(Block("d1", rate, rec.v_abc[:, cut], rec.i_abc[:, cut], first + start)):
                hops += 1
                if on_status is not None:
                    on_status(seg.t0 + (start + BLOCK) / rate, status, seg)
            if until is not None and until():
                return hops
        first += rec.n + BLOCK  # a new stream: the next segment is a new session
    return hops


def commission(profile, library: ModelLibrary, plant: Plant, setpoint: float, seed: int,
               config: PipelineConfig = PipelineConfig(), name: str | None = None, max_s: float = 7200.0) -> dict:
    """Learn a baseline at ``setpoint`` with the agent's own learning (cold start, load wander, no
    setpoint changes). Returns {"name", "seconds" of operation it took, "events"}."""
    events = []
    mon = DriveMonitor("d1", profile, library, config, on_event=lambda kind, detail: events.append((kind, detail)))
    name = name or f"d1_{setpoint:.0f}pct"
    mon.start_learning(name)
    op = Operation(dataclasses.replace(plant, setpoints=(setpoint,)), seed, start_setpoint=setpoint, changes=False)
    done = {"t": None}

    def watch(t, status, seg):
        if done["t"] is None and not mon.learning:
            done["t"] = t

    chunk = 60.0
    while mon.learning and op.t < max_s:
        stream(mon, op, profile, op.t + chunk, watch)
    refused = [d for k, d in events if k == "learning_refused"]
    if refused or mon.learning:
        raise RuntimeError(f"commissioning at {setpoint} % failed: {refused or 'did not finish'}")
    return {"name": name, "seconds": done["t"], "events": events}
