"""Transfer alignment of a slave INS to a master INS (issue 5): error-state model (model.py), filters
and RTS smoother (kf.py, hinf.py), orchestration (run.py)."""
from __future__ import annotations

from .run import run_alignment

__all__ = ["run_alignment"]
