"""Persistence: engine and sessions, models, migrations and keyword-only repository functions."""
