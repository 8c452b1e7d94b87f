"""Benchmarks of one concern; declared in bench/registry.py."""
