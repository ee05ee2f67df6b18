"""Running the pipeline: the stage registry and runner, the planner, your own room (own, place), the report, info, batches and executors."""
