"""StreamingRLS (block information form) vs padasip FilterRLS (per sample) on the same data.

    python -m bench.bench_rls [--samples 100000] [--block 2500]

``run()`` returns a dict of figures for ``bench/run.py``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from agent.rls import StreamingRLS


def _data(n_samples, n_params, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n_samples, n_params))
    theta = np.linspace(1.0, -1.0, n_params)
    return X, X @ theta + 0.1 * rng.standard_normal(n_samples)


def _best_of(fn, repeats):
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def run(n_samples: int = 100_000, n_params: int = 4, block: int = 2500, lam: float = 0.999,
        repeats: int = 5) -> dict:
    """Time both on the same data, check they agree, return samples/s and speedup."""
    import padasip as pa

    X, y = _data(n_samples, n_params)
    theta0, eps = np.zeros(n_params), 0.1  # padasip: P0 = I/eps, mu = lam, W = 1

    def ours():
        est = StreamingRLS(n_params, lam=lam, theta0=theta0, p0=1.0 / eps, stabilize=False)
        for a in range(0, n_samples, block):
            est.update(X[a:a + block], y[a:a + block])
        return est.theta

    def theirs():
        f = pa.filters.FilterRLS(n=n_params, mu=lam, eps=eps, w=theta0.copy())
        for x, d in zip(X, y):  # the per-sample loop an edge agent would run
            f.adapt(d, x)
        return f.w

    t_ours, th_ours = _best_of(ours, repeats)
    t_pa, th_pa = _best_of(theirs, max(1, repeats // 5))
    rel_diff = float(np.linalg.norm(th_ours - th_pa) / np.linalg.norm(th_pa))
    if not rel_diff < 1e-10:
        raise AssertionError(f"StreamingRLS and padasip disagree: rel diff {rel_diff:.2e}")
    return {
        "n_samples": n_samples, "n_params": n_params, "block": block, "lam": lam,
        "streaming_rls_samples_per_s": n_samples / t_ours,
        "padasip_samples_per_s": n_samples / t_pa,
        "speedup": t_pa / t_ours,
        "theta_rel_diff": rel_diff,
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=100_000)
    p.add_argument("--block", type=int, default=2500)
    p.add_argument("--params", type=int, default=4)
    a = p.parse_args(argv)
    r = run(n_samples=a.samples, n_params=a.params, block=a.block)
    print(f"RLS n={r['n_params']}, {r['n_samples']} samples, lam={r['lam']}, block={r['block']}")
    print(f"  StreamingRLS (blocks) : {r['streaming_rls_samples_per_s']:14,.0f} samples/s")
    print(f"  padasip FilterRLS     : {r['padasip_samples_per_s']:14,.0f} samples/s")
    print(f"  speedup               : {r['speedup']:14,.0f} x   (target >= 300 x)")
    print(f"  theta agreement       : {r['theta_rel_diff']:.1e} relative")
    return r


if __name__ == "__main__":
    main()
