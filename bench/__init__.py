"""Benchmarks and evaluations; each writes JSON and a PNG under bench/results/."""
