"""Prefect flows and the typer CLI that triggers them.

Prefect's temporary server migrates a SQLite database on first start, which can
exceed its default 20 s allowance on a fresh machine; allow more unless the user
configured otherwise.
"""

import os

os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
