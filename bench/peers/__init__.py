"""bench/peers/: see bench/README.md and docs/bench/peers.md."""
