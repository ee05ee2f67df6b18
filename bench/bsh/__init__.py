"""bench/bsh/: see bench/README.md and docs/bench/bsh.md."""
