"""Measuring the pipeline: evaluate (Table 2) and trade (what each second buys, the presets)."""
