"""Test-session settings: the compiled kernels (logtools.jit) as before this switch existed, and no
background compile started by the CLI runs the tests make; tests of the reference code and of the
automatic choice set TAPOST_KERNELS themselves (in a child process)."""
import os

os.environ.setdefault("TAPOST_KERNELS", "compiled")
os.environ.setdefault("TAPOST_WARMUP", "0")
