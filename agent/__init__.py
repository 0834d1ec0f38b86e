"""PMSM transmission-fault detection: signal chain, models, baselines and decisions.

The package is pure computation (no I/O besides record and model files); transports live in
``protocols`` and wire layouts shared with drive firmware in ``firmware_if``.
"""

__version__ = "0.1.0"
