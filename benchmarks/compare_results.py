"""Compare two benchmark result files run by run: did a change move any estimate?

    python benchmarks/compare_results.py A.json B.json [--tol 1e-9]

Rows are matched by their identity (set, run, seed, scenario, delay) in both files: the ``rows`` list of
``bench_latency*.py`` and ``bench_alignment_random.py``, or the ``runs`` of ``bench_alignment.py``. Per
method (every entry of a row that carries ``latency_s``/``sigma_s``, or a mounting error) it prints the
largest |difference| of the latency and of its sigma (s), or of the mounting error and its sigma (arcmin),
and how many runs differ at all. Runs present in one file only, and rows whose estimate failed in one file
only, are counted. Exit status 1 when some difference exceeds ``--tol`` (0 otherwise).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict

ID_KEYS = ("set", "run", "seed", "scenario", "delay_ms", "sim_s")
#: (value, sigma) field pairs of a method's entry: latency (s) and mounting (arcmin)
FIELDS = (("latency_s", "sigma_s"), ("error_arcmin", "sigma_arcmin"), ("mounting_err_arcmin", "mounting_sigma_arcmin"))


def _rows(doc: dict) -> list[dict]:
    if isinstance(doc.get("rows"), list):
        return doc["rows"]
    return [r for r in doc.get("runs", []) if isinstance(r, dict)]


def _key(row: dict) -> tuple:
    return tuple((k, json.dumps(row[k], sort_keys=True)) for k in ID_KEYS if k in row)


def _entries(row: dict, prefix: str = ""):
    """(method name, value field, value, sigma) of every estimate in a row (nested dicts searched)."""
    for name, v in row.items():
        if not isinstance(v, dict):
            continue
        label = f"{prefix}{name}"
        found = False
        for val, sig in FIELDS:
            if val in v:
                found = True
                yield label, val, v[val], v.get(sig)
        if not found:
            yield from _entries(v, label + "/")


def _diff(a, b) -> float:
    """|a - b| elementwise max (lists), 0 for equal NaNs, inf where one side is missing or NaN alone."""
    if isinstance(a, list) or isinstance(b, list):
        if not (isinstance(a, list) and isinstance(b, list)) or len(a) != len(b):
            return math.inf
        return max((_diff(x, y) for x, y in zip(a, b)), default=0.0)
    if a is None or b is None:
        return 0.0 if a is None and b is None else math.inf
    a, b = float(a), float(b)
    if math.isnan(a) or math.isnan(b):
        return 0.0 if math.isnan(a) and math.isnan(b) else math.inf
    if math.isinf(a) or math.isinf(b):
        return 0.0 if a == b else math.inf
    return abs(a - b)


def compare(doc_a: dict, doc_b: dict) -> tuple[dict, dict]:
    """({(method, field): {"value": max diff, "sigma": max diff, "runs": n compared, "differ": n}},
    {"only_a": n, "only_b": n, "matched": n})."""
    ra = {_key(r): r for r in _rows(doc_a)}
    rb = {_key(r): r for r in _rows(doc_b)}
    out: dict = defaultdict(lambda: {"value": 0.0, "sigma": 0.0, "runs": 0, "differ": 0})
    for k in ra.keys() & rb.keys():
        eb = {(m, f): (v, s) for m, f, v, s in _entries(rb[k])}
        for m, f, v, s in _entries(ra[k]):
            if (m, f) not in eb:
                continue
            v2, s2 = eb[(m, f)]
            o = out[(m, f)]
            dv, ds = _diff(v, v2), _diff(s, s2)
            o["value"], o["sigma"] = max(o["value"], dv), max(o["sigma"], ds)
            o["runs"] += 1
            o["differ"] += int(dv > 0 or ds > 0)
    counts = {"matched": len(ra.keys() & rb.keys()), "only_a": len(ra.keys() - rb.keys()),
              "only_b": len(rb.keys() - ra.keys())}
    return dict(out), counts


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--tol", type=float, default=1e-9, help="a difference above this fails (default 1e-9)")
    args = ap.parse_args(argv)
    docs = []
    for path in (args.a, args.b):
        try:
            with open(path) as fh:
                docs.append(json.load(fh))
        except (OSError, json.JSONDecodeError) as exc:
            print(f"{path}: cannot read a benchmark result ({exc})", file=sys.stderr)
            return 2
    out, counts = compare(*docs)
    print(f"runs matched {counts['matched']}, only in A {counts['only_a']}, only in B {counts['only_b']}")
    print(f"{'method':40s} {'field':20s} {'runs':>5s} {'differ':>6s} {'max |d value|':>14s} {'max |d sigma|':>14s}")
    worst = 0.0
    for (m, f), o in sorted(out.items()):
        print(f"{m:40s} {f:20s} {o['runs']:5d} {o['differ']:6d} {o['value']:14.3e} {o['sigma']:14.3e}")
        worst = max(worst, o["value"], o["sigma"])
    print(f"largest difference {worst:.3e}")
    return int(worst > args.tol or counts["only_a"] > 0 or counts["only_b"] > 0)


if __name__ == "__main__":
    sys.exit(main())
