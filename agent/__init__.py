"""PMSM transmission-fault detection: signal chain, models, baselines and decisions.

The package is pure computation (no I/O besides record and model files); transports live in
``protocols`` and wire layouts shared with drive firmware in ``firmware_if``.
"""

import os

__version__ = "0.1.0"

# One BLAS thread unless the user says otherwise: the agent's matrices are small, and idle
# OpenBLAS workers spin (about 8 % of a core measured at idle). Set before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
