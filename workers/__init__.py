"""Job execution: the Celery app and tasks (distributed), the in-process pool (embedded) and the
outbox relay. Tasks are thin: they take a job id and call :mod:`workers.jobs`."""
