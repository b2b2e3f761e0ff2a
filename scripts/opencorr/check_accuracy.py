"""Accuracy check of an OpenCorr result CSV written by bench_fftcc_icgn1.

usage: python3 check_accuracy.py OUT.csv [U_TRUE V_TRUE]
Prints median u, v over valid POIs (zncc >= 0), RMS difference from the median and from the
given truth, and the count of POIs OpenCorr flagged (zncc < 0: -3 skipped, -4 not converged in
max iterations, -5 NaN).
"""
import sys

import numpy as np

path = sys.argv[1]
u_true = float(sys.argv[2]) if len(sys.argv) > 2 else 1.3 + 0.15 * 5
v_true = float(sys.argv[3]) if len(sys.argv) > 3 else -0.7 + 0.1 * 5
d = np.genfromtxt(path, delimiter=",", names=True)
ok = d["zncc"] >= 0
z = d["zncc"]
print(f"{path}: POIs {len(d)}, valid {ok.sum()}, flagged {(~ok).sum()} "
      f"(-4 not converged: {(z == -4).sum()}, -3: {(z == -3).sum()}, -5: {(z == -5).sum()})")
for k, t in (("u", u_true), ("v", v_true)):
    x = d[k][ok]
    m = np.median(x)
    xa = d[k]
    print(f"  {k}: median {m:.5f} (truth {t:.3f}, diff {m - t:+.5f}); "
          f"RMS from median {np.sqrt(np.mean((x - m) ** 2)):.5f}; "
          f"RMS from truth {np.sqrt(np.mean((x - t) ** 2)):.5f}; "
          f"max |dev from median| {np.max(np.abs(x - m)):.4f}; "
          f"all POIs RMS from median {np.sqrt(np.mean((xa - m) ** 2)):.5f}")
print(f"  iterations: mean {d['iteration'].mean():.3f}, median {np.median(d['iteration']):.0f}, "
      f"max {d['iteration'].max():.0f}; ZNCC median {np.median(d['zncc'][ok]):.5f}")
u0, c = np.unique(d["u0"], return_counts=True)
v0, cv = np.unique(d["v0"], return_counts=True)
print(f"  FFT-CC integer estimates: u0 {dict(zip(u0.tolist(), c.tolist()))}, "
      f"v0 {dict(zip(v0.tolist(), cv.tolist()))}")
