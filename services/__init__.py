"""CSR service layer: HTTP API, persistence and the command line (imports nothing heavy at import time)."""
