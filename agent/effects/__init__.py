"""Effect library of the model workbench: named physical effects the baseline dq model lacks.

Each effect is one module defining ``EFFECT`` (an :class:`Effect`): its id (CONTRACT section 5),
the physics in a sentence with units, the regressor columns it adds to the d/q voltage equations
(``kind="voltage"``, columns in V per unit of each parameter) or to the measured current
(``kind="output"``, columns in A per unit), its parameters with their physical meaning and units,
its signature (harmonics of fe in dq and abc, correlations) and the data that reveal it.

Adding an effect: write ``agent/effects/<id>.py`` with ``EFFECT = Effect(...)`` and add ``"<id>"``
to :data:`MODULES`.
"""

from __future__ import annotations

import importlib

from agent.effects.base import Effect, Param
from agent.errors import InputError

#: The registry: one module per effect, in the order they are listed.
MODULES = (
    "inverter_deadtime",
    "flux_harmonics",
    "voltage_delay",
    "current_offset",
    "current_gain_mismatch",
    "resistance_drift",
    "magnetic_saturation",
    "speed_ripple",
)

EFFECTS: dict[str, Effect] = {}
for _name in MODULES:
    _eff = importlib.import_module(f"agent.effects.{_name}").EFFECT
    EFFECTS[_eff.id] = _eff


def get(effect_id: str) -> Effect:
    """The effect named ``effect_id``; ``InputError`` listing the known ids otherwise."""
    try:
        return EFFECTS[effect_id]
    except KeyError:
        raise InputError(f"unknown effect '{effect_id}' (known: {', '.join(EFFECTS)})") from None


def model_terms(effect_ids) -> tuple[tuple, tuple]:
    """Extra regressor terms (d, q) of a list of effect ids, in order (see :meth:`Effect.terms`)."""
    extra_d, extra_q = (), ()
    for effect_id in effect_ids:
        d, q = get(effect_id).terms()
        extra_d, extra_q = extra_d + d, extra_q + q
    return extra_d, extra_q


def params_text(params: dict, sep: str = " ", bounds: dict | None = None) -> str:
    """An effect's reported parameters as text, each with its bound (+-, where ``bounds`` gives
    one); "not identifiable" for one the records do not pin down (its values are None, see
    :func:`agent.workbench.explain.reported`)."""
    if params and all(v is None for v in params.values()):
        return "not identifiable"
    bounds = bounds or {}
    return ", ".join(f"{k}{sep}{'n/a' if v is None else format(v, '.4g')}"
                     + ("" if v is None or bounds.get(k) is None else f" +-{bounds[k]:.2g}") for k, v in params.items())


__all__ = ["EFFECTS", "MODULES", "Effect", "Param", "get", "model_terms", "params_text"]
