"""bench/batch/: see bench/README.md and docs/bench/batch.md."""
