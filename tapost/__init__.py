"""``import tapost``: the Python API (``pipelines.api``): load, analyze, Analysis."""
from logtools import __version__
from pipelines.api import *  # noqa: F401,F403
from pipelines.api import __all__ as _api_all

__all__ = ["__version__", *_api_all]
