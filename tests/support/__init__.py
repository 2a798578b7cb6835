"""Helpers the tests share with the benchmarks: private servers (PostgreSQL, Ray)."""
