"""Speed of the strapdown mechanisation (``logtools.strapdown.mechanise``): 1 h of 200 Hz IMU samples.

The compiled kernel against the reference code (the same loop as plain Python, ``TAPOST_KERNELS=reference``),
each in its own process in the same run; the compiled one after a warm-up call (numba's cache loaded).
Target: 1 h at 200 Hz in under 5 s compiled (it was a timed test before).

    python benchmarks/bench_strapdown.py            # 1 h
    python benchmarks/bench_strapdown.py --quick    # 10 min

Figures go to ``benchmarks/results/strapdown.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHILD = """
import json, sys, time
import numpy as np
from logtools import jit, strapdown as sd
n = int(sys.argv[1])
t = np.arange(n) / 200.0
rng = np.random.default_rng(1)
gyro = rng.normal(0, 0.01, (n, 3))
accel = rng.normal(0, 0.05, (n, 3)) + [0, 0, -9.79]
sd.mechanise(t[:100], gyro[:100], accel[:100], [1, 0, 0, 0], np.zeros(3), 0.5, 0.0, 0.0)  # warm-up
t0 = time.perf_counter()
sol = sd.mechanise(t, gyro, accel, [1, 0, 0, 0], np.zeros(3), 0.5, 0.0, 0.0)
dt = time.perf_counter() - t0
assert np.isfinite(sol.vel_ned_m_s).all()
print(json.dumps({"mode": jit.mode(), "samples": n, "seconds": dt}))
"""


def run(mode: str, n: int) -> dict:
    env = {**os.environ, "TAPOST_KERNELS": mode, "TAPOST_WARMUP": "0",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    p = subprocess.run([sys.executable, "-c", CHILD, str(n)], capture_output=True, text=True, env=env, check=True)
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 min instead of 1 h")
    a = ap.parse_args(argv)
    n = (600 if a.quick else 3600) * 200
    comp, ref = run("compiled", n), run("reference", n)
    out = {"imu_hz": 200.0, "duration_s": n / 200.0, "compiled_s": comp["seconds"], "reference_s": ref["seconds"],
           "speed_up": ref["seconds"] / comp["seconds"], "target_compiled_s": 5.0,
           "target_met": comp["seconds"] < 5.0, "cpus": os.cpu_count()}
    print(f"{n / 200 / 60:.0f} min at 200 Hz: compiled {comp['seconds']:.2f} s, reference {ref['seconds']:.2f} s "
          f"({out['speed_up']:.0f}x); target < 5 s: {'met' if out['target_met'] else 'NOT met'}")
    if not a.quick:
        res = ROOT / "benchmarks" / "results" / "strapdown.json"
        res.write_text(json.dumps(out, indent=2) + "\n")
        print(f"-> {res.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
