"""Benchmarks by topic (bench/README.md); run as ``python -m bench.<topic>.<script>`` or ``python bench/run.py``."""
