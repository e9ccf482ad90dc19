"""bytes -> InsLog. One module per format; ``parsers.registry`` detects by content and dispatches.

The only package that knows a format's units, axes and clocks.
"""
from parsers.registry import inspect_log, load, parse_log_arg, path_arg, write

__all__ = ["inspect_log", "load", "parse_log_arg", "path_arg", "write"]
