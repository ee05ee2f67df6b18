"""bench/relight/: see bench/README.md and docs/bench/relight.md."""
