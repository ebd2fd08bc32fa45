"""Helpers that tests and benches share and the library does not use (no test_ modules here, so
pytest collects nothing from this package)."""
