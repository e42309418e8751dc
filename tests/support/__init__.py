"""Shared test helpers (not tests): importable as ``support.<module>`` because tests/ is on sys.path."""
