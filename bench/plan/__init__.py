"""bench/plan/: see bench/README.md and docs/bench/plan.md."""
