"""Helpers shared by the streaming-transport tests (CAN bus, serial bridge): a test record,
reading a number of samples from a source, and checks on the blocks read."""

import time

import numpy as np

from agent.records import Record

FS = 25_000.0


def make_record(n, encoder=False, seed=0):
    """``n`` samples of a noisy 50 Hz three-phase signal at :data:`FS` (with encoder angles when
    ``encoder``)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FS
    ph = 2 * np.pi * 50 * t - 2 * np.pi / 3 * np.arange(3)[:, None]
    return Record(t=t, v_abc=300 * np.cos(ph) + rng.normal(0, 2, (3, n)), i_abc=8 * np.sin(ph),
                  theta_e=np.mod(2 * np.pi * 50 * t, 2 * np.pi) if encoder else None,
                  omega_e=np.full(n, 2 * np.pi * 50) if encoder else None)


def read_samples(src, n, timeout=8.0):
    """Blocks read from ``src`` until they hold ``n`` samples or ``timeout`` s have passed."""
    blocks, got, t0 = [], 0, time.monotonic()
    while got < n and time.monotonic() - t0 < timeout:
        b = src.read(0.2)
        if b is not None:
            blocks.append(b)
            got += b.n
    return blocks


def joined(blocks, name):
    """The blocks' ``name`` arrays joined along the sample axis."""
    return np.concatenate([getattr(b, name) for b in blocks], axis=-1)


def assert_contiguous(blocks, start=0):
    """The blocks follow each other without a gap from sample ``start``."""
    first = start
    for k, b in enumerate(blocks):
        assert b.first_sample == first, (k, b.first_sample, first)
        first += b.n
