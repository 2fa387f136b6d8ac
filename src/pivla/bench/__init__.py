"""Benchmarks of pivla's components: library functions that take a typed config and return measured figures."""
