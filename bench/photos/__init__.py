"""bench/photos/: see bench/README.md and docs/bench/photos.md."""
