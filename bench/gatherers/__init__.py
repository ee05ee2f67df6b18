"""bench/gatherers/: see bench/README.md and docs/bench/gatherers.md."""
