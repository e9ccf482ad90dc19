"""tapost numerics: conventions, earth model, InsLog, latency, compensation, strapdown, alignment.

Imports neither ``parsers`` nor ``pipelines`` nor rerun.
"""
__version__ = "0.1.0"
