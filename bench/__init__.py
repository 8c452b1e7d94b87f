"""The benchmarks: bench/registry.py declares each one, `python -m bench` lists and runs them (see harness.py for
what they share)."""
