"""Test-session settings: the compiled kernels (logtools.jit) as before this switch existed, and no
background compile started by the CLI runs the tests make; tests of the reference code and of the
automatic choice set TAPOST_KERNELS themselves (in a child process)."""
import os

os.environ.setdefault("TAPOST_KERNELS", "compiled")
os.environ.setdefault("TAPOST_WARMUP", "0")
# one BLAS thread per test worker and no huge pages for numpy's arrays, as the CLI runs: with a worker per
# core (-n auto), BLAS threads only wait on each other (scripts/test.sh sets them before pytest imports
# numpy; pipelines.cli imports no numpy)
from pipelines.cli import set_numpy_environment  # noqa: E402

set_numpy_environment()
