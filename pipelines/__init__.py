"""Orchestration: analyze (one pair), batch (a campaign), report (JSON + HTML), recording (rerun),
simulate, inspect, and the CLI. Thin: every numeric step is a call into ``logtools``."""
