"""Celery app and tasks: thin adapters (load -> csr_core -> persist)."""
