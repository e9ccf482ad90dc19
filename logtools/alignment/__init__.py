"""Transfer alignment of a slave INS to a master INS (issue 5).

Map: options.py (the filter kinds, AlignmentOptions, AlignmentConfig: open it to add a filter kind or
change a tuning value), run.py (run_alignment: inputs -> coarse mounting -> epochs -> filter passes ->
result), kf.py (the time loop in named steps, its compiled twin, the RTS smoother), model.py (the
error-state model: F, H, discretisation), hinf.py (the H-infinity updates).

``run_alignment`` is loaded on first use, so the light ``options`` module (the CLI's choices) can be
imported without the filters."""
from __future__ import annotations

from .options import CONFIG, FILTERS, MATCHES, AlignmentConfig, AlignmentOptions, FilterKind

__all__ = ["run_alignment", "AlignmentOptions", "AlignmentConfig", "CONFIG", "FilterKind", "FILTERS", "MATCHES"]


def __getattr__(name: str):
    if name == "run_alignment":
        from .run import run_alignment

        globals()["run_alignment"] = run_alignment
        return run_alignment
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
