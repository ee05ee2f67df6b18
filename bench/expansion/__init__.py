"""bench/expansion/: see bench/README.md and docs/bench/expansion.md."""
