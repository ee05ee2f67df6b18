"""bench/speed/: see bench/README.md and docs/bench/speed.md."""
