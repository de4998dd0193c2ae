"""Benchmarks: each script prints a markdown table against a named peer (see README)."""
