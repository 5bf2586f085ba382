"""Offline studies and their reports: every method on every case, the k rules, observability, export, plots."""
