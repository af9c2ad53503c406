"""The benchmark (`csr bench`): scenario sets, running `csr reconstruct`, evaluation (contract
section 6 via :mod:`csr_core.metrics`), tables and figures. File I/O and matplotlib (Agg) only."""
