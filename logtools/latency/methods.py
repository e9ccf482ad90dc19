"""The latency methods by name (``logtools.results.LatencyMethod``) and the seeds' methods' dispatch."""
from __future__ import annotations

from logtools.inslog import InsLog
from logtools.latency.config import DEFAULT, LatencyConfig
from logtools.results import LATENCY_METHODS, LatencyMethod, MethodEstimate


#: the method names (``Method.TAPOST`` ...) and the names in report order: the table lives with the result
#: records (``logtools.results``), where the CLI reads its choices without loading the numerics
Method = LatencyMethod
METHODS: tuple[str, ...] = LATENCY_METHODS
#: the seeds' methods' functions in logtools.latency_seeds
SEED_FUNCTIONS = {Method.S000.value: "s000_rate_integral", Method.S002.value: "s002_attitude_shift"}


def run_seed(name: str, master: InsLog, slave: InsLog, max_lag_s: float | None,
             headline: bool = False, cfg: LatencyConfig = DEFAULT) -> MethodEstimate:
    """A seed's method. As the headline it runs as asked; for comparison only, on a record of at most
    cfg.output.compare_record_s and never over the whole overlap (``max_lag_s=None``: quadratic in the log length)."""
    if not headline and max_lag_s is None:
        return MethodEstimate(float("nan"), float("nan"),
                              "not run for comparison with --max-lag auto (a grid search over the whole "
                              "overlap); choose it with --latency-method to run it")
    kw = {} if headline else {"record_s": cfg.output.compare_record_s}
    try:
        from logtools import latency_seeds  # noqa: PLC0415 (lazy: written separately)
    except ImportError as exc:
        return MethodEstimate(float("nan"), float("nan"), f"not available ({exc})")
    fn = SEED_FUNCTIONS[name]
    f = getattr(latency_seeds, fn, None)
    if f is None:
        return MethodEstimate(float("nan"), float("nan"), f"not available (latency_seeds.{fn} missing)")
    return f(master, slave, max_lag_s=max_lag_s, **kw)
