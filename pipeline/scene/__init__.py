"""make-scene: the synthetic rooms, their geometry and their Mitsuba 3 ground truth."""
